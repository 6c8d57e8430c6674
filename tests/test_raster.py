"""The Warp rasterizer against its float64 torch reference twin (SPEC §2), finite differences, and
closed-form cases."""
import math

import pytest
import torch

from tlvg_warp import Camera, Gaussians, InputError, render
from tlvg_warp.kernels.blend import ALPHA_MAX, T_MIN
from tlvg_warp.reference import project_reference, render_reference

# Same arithmetic in float64 on both sides; differences are summation order only.
F64_TOL = 1e-9
# Warp float32 against the float64 oracle: ~1e-7 relative per op, over up to a few hundred blended splats.
F32_TOL = 2e-4
# gradcheck central differences in float64 with eps 1e-6: truncation error ~eps² times curvature.
GRADCHECK_ATOL = 1e-5
FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def random_scene(n, degree=1, seed=0, dtype=torch.float64, spread=0.6, log_scale=-2.5, opacity_shift=0.5):
    gen = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=gen, dtype=dtype)  # noqa: E731
    return Gaussians(r(n, 3) * spread, r(n, 4), r(n, 3) * 0.3 + log_scale, r(n) + opacity_shift,
                     r(n, (degree + 1) ** 2, 3) * 0.3)


def camera(width=53, height=37, eye=(0.2, -3.0, 0.3), fov=60.0):
    return Camera.look_at(eye, [0, 0, 0], width=width, height=height, fov_deg=fov)


def leafs(g):
    return Gaussians(**{f: getattr(g, f).detach().clone().requires_grad_(True) for f in FIELDS})


def upstream(out, seed=1):
    gen = torch.Generator().manual_seed(seed)
    return [torch.randn(t.shape, generator=gen, dtype=t.dtype) for t in (out.color, out.alpha, out.depth)]


def loss_grads(g, out, ups):
    loss = sum((o * u).sum() for o, u in zip((out.color, out.alpha, out.depth), ups))
    return torch.autograd.grad(loss, [getattr(g, f) for f in FIELDS] + [out.means2d], allow_unused=True)


def assert_close(a, b, tol, what):
    err = (a - b).abs().max().item() if a.numel() else 0.0
    scale = max(1.0, b.abs().max().item() if b.numel() else 0.0)
    assert err <= tol * scale, f"{what}: max error {err:.3g} > {tol:.1g} x {scale:.3g}"


def compare(g, cam, tol=F64_TOL, background=None, **kw):
    g1, g2 = leafs(g), leafs(g)
    out = render(g1, cam, background, return_weights=True, **kw)
    ref = render_reference(g2, cam, background, return_weights=True, **kw)
    for k in ("color", "alpha", "depth", "weights"):
        assert_close(getattr(out, k), getattr(ref, k), tol, k)
    assert torch.equal(out.radii, ref.radii)
    ups = upstream(ref)
    for name, a, b in zip(FIELDS + ("means2d",), loss_grads(g1, out, ups), loss_grads(g2, ref, ups)):
        assert_close(a, b, tol, f"d/d{name}")
    return out, ref


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_matches_reference_each_sh_degree(degree):
    out, _ = compare(random_scene(250, degree, seed=degree), camera(), background=[0.1, 0.2, 0.3])
    assert out.alpha.max() > 0.5  # the scene is actually visible


def test_float32_matches_float64_reference():
    g = random_scene(250, 2, seed=5)
    out = render(g.to(dtype=torch.float32), camera())
    ref = render_reference(g, camera())
    for k in ("color", "alpha", "depth"):
        assert_close(getattr(out, k).double(), getattr(ref, k), F32_TOL, k)


def test_gradcheck_warp_path_float64():
    # low opacity keeps every pixel away from the clamp/stop thresholds, where the image is not smooth
    g = random_scene(6, 1, seed=3, spread=0.3, log_scale=-1.8, opacity_shift=-1.5)
    cam = camera(20, 15)

    def fn(*tensors):
        out = render(Gaussians(*tensors), cam, background=[0.3, 0.2, 0.1])
        return out.color, out.alpha, out.depth

    inputs = tuple(getattr(g, f).detach().clone().requires_grad_(True) for f in FIELDS)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=GRADCHECK_ATOL, rtol=1e-4)


@pytest.mark.parametrize("size", [(16, 16), (33, 17), (17, 33), (1, 1), (70, 5)])
def test_image_sizes_and_tile_edges(size):
    w, h = size
    g = random_scene(120, 1, seed=w * 100 + h)
    compare(g, camera(w, h))


def test_gaussians_on_tile_boundaries():
    # centers exactly on tile corners/edges: the bounding box touches neighbouring tiles exactly
    cam = Camera(torch.eye(4), 40.0, 40.0, 24.0, 16.0, 48, 32)
    uv = torch.tensor([[16.0, 16.0], [32.0, 16.0], [16.0, 0.0], [0.0, 0.0], [48.0, 32.0], [31.5, 15.5]], dtype=torch.float64)
    z = torch.full((6, 1), 2.0, dtype=torch.float64)
    means = torch.cat([(uv - torch.tensor([24.0, 16.0], dtype=torch.float64)) / 40.0 * z, z], 1)
    g = Gaussians.from_colors(means, torch.rand(6, 3, dtype=torch.float64), 0.02, opacity=0.8)
    out, _ = compare(g, cam)
    assert (out.radii > 0).all()


def test_binned_equals_brute_force():
    # opacity < 0.35: beyond 3σ alpha < 1/255, so tile membership cannot change the image at all
    g = random_scene(300, 1, seed=9, opacity_shift=-2.5)
    g.opacity_logits.data.clamp_(max=math.log(0.34 / 0.66))
    cam = camera(45, 29)
    binned = render(g, cam)
    brute = render(g, cam, all_tiles=True)
    for k in ("color", "alpha", "depth"):
        assert_close(getattr(binned, k), getattr(brute, k), F64_TOL, k)
    # and brute force itself against the reference's brute force, at full opacity
    compare(random_scene(150, 1, seed=10, opacity_shift=2.0), cam, all_tiles=True)


def test_int64_scan_of_the_key_ends_equals_the_int32_one(monkeypatch):
    """Scenes whose total could pass int32 (N x tiles >= 2**31) scan the key ends in int64 before checking the
    total: forced here (the bound lowered to 0), the image, the gradients and the binning equal the int32 scan's."""
    import tlvg_warp.raster as raster

    g = random_scene(300, 1, seed=12)
    cam = camera(45, 29)
    runs = []
    for limit in (2**31, 0):
        monkeypatch.setattr(raster, "SCAN_INT32_LIMIT", limit)
        gl = leafs(g)
        with raster.capture_binning() as cap:
            out = render(gl, cam)
        ups = upstream(out)
        runs.append((out, loss_grads(gl, out, ups), cap["total"], cap["ids"].clone()))
    (a, ga, ta, ia), (b, gb, tb, ib) = runs
    assert ta == tb > 0 and torch.equal(ia, ib)
    for k in ("color", "alpha", "depth"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k
    for name, x, y in zip(FIELDS, ga, gb):
        assert_close(x, y, 1e-12, name)  # the same sums; atomics may order them differently


def test_empty_scene_and_everything_culled():
    cam = camera(20, 12)
    bg = [0.25, 0.5, 0.75]
    empty = Gaussians(*(torch.zeros(0, *s, dtype=torch.float64) for s in [(3,), (4,), (3,)]),
                      torch.zeros(0, dtype=torch.float64), torch.zeros(0, 1, 3, dtype=torch.float64))
    behind = random_scene(50, 0, seed=2)
    behind.means.data[:, 1] = -10.0  # behind the camera at y = -3 looking along +y
    for g in (empty, behind):
        gl = leafs(g)
        out = render(gl, cam, background=bg)
        assert torch.allclose(out.color, torch.tensor(bg, dtype=torch.float64).expand(12, 20, 3))
        assert (out.alpha == 0).all() and (out.depth == 0).all() and (out.radii == 0).all()
        grads = torch.autograd.grad(out.color.sum() + out.alpha.sum(), [gl.means, gl.sh], allow_unused=True)
        assert all(gr is None or (gr == 0).all() for gr in grads)


def test_one_gaussian_covering_the_whole_image():
    cam = camera(40, 30)
    g = Gaussians.from_colors(torch.zeros(1, 3, dtype=torch.float64), torch.tensor([[0.9, 0.4, 0.1]], dtype=torch.float64),
                              3.0, opacity=0.7)
    out, _ = compare(g, cam)
    assert (out.alpha > 0.3).all()  # every pixel, corners included
    # closed form at the image center: alpha = o · exp(-½ dᵀΣ⁻¹d) with d ≈ 0
    assert abs(out.alpha[15, 20].item() - 0.7) < 1e-3


def test_thousands_on_one_pixel_stop_early():
    # 3000 identical splats: each pixel blends k of them, k the largest with (1-α)^k >= T_MIN (closed form)
    n = 3000
    g = Gaussians.from_colors(torch.zeros(n, 3, dtype=torch.float64), torch.full((n, 3), 0.6, dtype=torch.float64),
                              0.05, opacity=0.9)
    cam = camera(24, 20)
    out, _ = compare(g, cam)
    proj = project_reference(g.subset(slice(0, 1)), cam)
    jj, ii = torch.meshgrid(torch.arange(24, dtype=torch.float64) + 0.5, torch.arange(20, dtype=torch.float64) + 0.5,
                            indexing="xy")
    dx, dy = jj - proj.means2d[0, 0], ii - proj.means2d[0, 1]
    q = proj.conic[0]
    a = (0.9 * torch.exp(-0.5 * (q[0] * dx * dx + q[2] * dy * dy) - q[1] * dx * dy)).clamp(max=ALPHA_MAX)
    k = torch.floor(math.log(T_MIN) / torch.log1p(-a) + 1e-9).clamp(max=n)
    expect = torch.where(a >= 1 / 255, 1 - (1 - a) ** k, torch.zeros_like(a))
    assert_close(out.alpha, expect, 1e-9, "alpha after the early stop")
    assert k.min() < 0.01 * n  # the center pixels stopped after a few splats out of thousands


def test_sh_degree_argument_truncates():
    """Evaluating fewer SH degrees than stored: the image and every gradient equal those of the truncated scene,
    and the coefficients past the degree get an exact zero gradient (not left unwritten)."""
    g = random_scene(100, 3, seed=4)
    gl = leafs(g)
    low = render(gl, camera(), sh_degree=1)
    gt = leafs(g.with_sh_degree(1))
    ref = render_reference(gt, camera())
    assert_close(low.color, ref.color, F64_TOL, "color at degree 1")
    ups = upstream(ref)
    for name, a, b in zip(FIELDS, loss_grads(gl, low, ups), loss_grads(gt, ref, ups)):
        if name == "sh":
            assert torch.equal(a[:, 4:], torch.zeros_like(a[:, 4:])), "gradient past the evaluated degree"
            a = a[:, :4]
        assert_close(a, b, F64_TOL, f"d/d{name} at degree 1")


def test_degenerate_gaussians_do_not_poison_others():
    g = random_scene(60, 1, seed=7)
    bad = random_scene(5, 1, seed=8)
    bad.log_scales.data[0] = -torch.inf  # zero scale: a point, blurred to ~one pixel
    bad.log_scales.data[1] = 200.0  # huge: exp overflows, culled
    bad.quats.data[2] = 0.0  # zero quaternion: identity rotation
    cam = camera()
    bad.means.data[3] = cam.center + 0.005 * cam.R[2]  # 5 mm in front of the camera, inside near
    bad.means.data[4, 0] = torch.nan  # NaN: culled alone
    both = Gaussians(**{f: torch.cat([getattr(g, f), getattr(bad, f)]) for f in FIELDS})
    gl = leafs(both)
    out = render(gl, camera())
    ups = upstream(out)
    grads = loss_grads(gl, out, ups)
    assert all(torch.isfinite(t).all() for t in (out.color, out.alpha, out.depth))
    assert all(torch.isfinite(gr[:60]).all() for gr in grads[:5])
    # removing the culled ones changes nothing
    keep = torch.tensor([True] * 60 + [True, False, True, False, False])
    sub = leafs(both.subset(keep))
    out2 = render(sub, camera())
    assert_close(out.color, out2.color, F64_TOL, "color without culled")
    grads2 = loss_grads(sub, out2, ups)
    for a, b in zip(grads[:5], grads2[:5]):
        assert_close(a[:60], b[:60], F64_TOL, "gradients of the healthy Gaussians")
    assert (out.radii[[61, 63, 64]] == 0).all()


def test_screen_space_gradient_is_mean2d_gradient():
    g = random_scene(80, 0, seed=11)
    gl = leafs(g)
    out = render(gl, camera())
    out.color.sum().backward()
    ref = render_reference(g, camera())
    (gref,) = torch.autograd.grad(ref.color.sum(), [ref.means2d])
    assert_close(out.means2d.grad, gref, F64_TOL, "screen-space mean gradient")
    assert out.means2d.grad[out.radii > 0].abs().sum() > 0


def test_input_descriptors_follow_the_requested_layout():
    """launch.input_ct keeps one descriptor per tensor and layout: the shading forward reads the SH coefficients as
    [N, K, 3] scalars, its backward as [N, K] vec3s. One entry per tensor would hand the later reader the first
    one's layout (a [N, K] vec3 descriptor read as [N, K, 3] has channel stride 0: every channel reads red)."""
    from tlvg_warp import launch

    K = launch.kernels_for(torch.float32)
    for first, second in ((K.vec3, None), (None, K.vec3)):
        sh = torch.randn(5, 4, 3)
        got = {id(first): launch.input_ct(sh, first), id(second): launch.input_ct(sh, second)}
        vec, flat = got[id(K.vec3)], got[id(None)]
        assert (vec.ndim, tuple(vec.shape)[:2], tuple(vec.strides)[:2]) == (2, (5, 4), (48, 12))
        assert (flat.ndim, tuple(flat.shape)[:3], tuple(flat.strides)[:3]) == (3, (5, 4, 3), (48, 12, 4))
        assert launch.input_ct(sh, first) is got[id(first)]  # both stay cached


def test_shade_op_matches_its_torch_twin():
    """The SH stage is its own autograd op (autograd.ShadeFn): colours and both gradients against reference.shade_reference
    in float64, at the stored degree and a lower one (the higher coefficients get exactly zero). Gaussians whose
    colour gradient is zero (no pixel saw them; the kernels skip them) get zero gradients, even with a non-finite
    mean, which the twin turns into NaN."""
    from tlvg_warp.autograd import ShadeFn
    from tlvg_warp.launch import kernels_for
    from tlvg_warp.raster import camera_arg
    from tlvg_warp.reference import shade_reference

    g = random_scene(40, 3, seed=11)
    g.means.data[7, 1] = torch.nan
    cam = camera()
    gen = torch.Generator().manual_seed(3)
    for degree in (3, 1):
        m1, s1, m2, s2 = (t.detach().clone().requires_grad_(True) for t in (g.means, g.sh, g.means, g.sh))
        ours = ShadeFn.apply(m1, s1, camera_arg(kernels_for(m1.dtype), cam), degree)
        ref = shade_reference(m2, s2, cam, degree)
        up = torch.randn(ref.shape, generator=gen, dtype=ref.dtype)
        up[::5] = 0.0  # rows 0, 5, 10, ...: unseen Gaussians, row 7 among the seen ones but NaN: zero it too
        up[7] = 0.0
        seen = up.abs().sum(1) > 0
        finite = torch.isfinite(g.means).all(1)
        assert_close(ours[finite], ref[finite], F64_TOL, f"colours at degree {degree}")
        ga = torch.autograd.grad((ours * up).sum(), [m1, s1])
        gb = torch.autograd.grad((ref * up).sum(), [m2, s2])
        for name, a, b in zip(("means", "sh"), ga, gb):
            assert torch.isfinite(a).all(), f"d/d{name} at degree {degree}"
            assert_close(a[finite], b[finite], F64_TOL, f"d/d{name} at degree {degree}")
            assert a[~seen].abs().max() == 0, f"d/d{name} of unseen Gaussians at degree {degree}"
        assert gb[1][seen].abs().sum() > 0
        if degree < 3:
            assert ga[1][:, (degree + 1) ** 2:].abs().max() == 0


def test_second_backward_through_the_graph_rebuilds_the_freed_state():
    # the first backward frees the sorted ids and per-pixel state; a retained graph's second backward must
    # rebuild them and give the same gradients as the reference (each call's sums start from zero)
    g = random_scene(120, 2, seed=5)
    g1, g2 = leafs(g), leafs(g)
    out, ref = render(g1, camera()), render_reference(g2, camera())
    ups = upstream(ref)
    loss = sum((o * u).sum() for o, u in zip((out.color, out.alpha, out.depth), ups))
    params = [getattr(g1, f) for f in FIELDS]
    first = torch.autograd.grad(loss, params, retain_graph=True)
    second = torch.autograd.grad(loss, params)
    for name, a, b, r in zip(FIELDS, first, second, loss_grads(g2, ref, ups)):
        assert_close(a, r, F64_TOL, f"first backward d/d{name}")
        assert_close(b, r, F64_TOL, f"second backward d/d{name}")


def test_inputs_changed_between_renders_are_seen():
    # the Warp wrappers of the inputs are reused across renders: an in-place step and a swapped storage must
    # both show in the next render (oracle: the reference on the same values)
    g = leafs(random_scene(60, 1, seed=9))
    cam = camera()
    render(g, cam)
    with torch.no_grad():
        g.means.add_(0.05)  # in place, as an optimizer steps
    assert_close(render(g, cam).color, render_reference(g, cam).color, F64_TOL, "after an in-place step")
    g.sh.data = g.sh.data * 0.5 + 0.1  # new storage under the same tensor object
    assert_close(render(g, cam).color, render_reference(g, cam).color, F64_TOL, "after a storage swap")


def test_bad_input_is_a_clear_error():
    g = random_scene(10, 0)
    cam = camera()
    with pytest.raises(InputError, match="means has shape"):
        Gaussians(torch.zeros(10, 2), g.quats.float(), g.log_scales.float(), g.opacity_logits.float(), g.sh.float())
    with pytest.raises(InputError, match="float32 or all float64"):
        Gaussians(g.means.half(), g.quats.half(), g.log_scales.half(), g.opacity_logits.half(), g.sh.half())
    with pytest.raises(InputError, match="float32 or all float64"):
        Gaussians(g.means.float(), g.quats, g.log_scales, g.opacity_logits, g.sh)
    with pytest.raises(InputError, match="mixed devices"):
        Gaussians(g.means.to("meta"), g.quats, g.log_scales, g.opacity_logits, g.sh)
    with pytest.raises(InputError, match="non-finite"):
        Camera(torch.full((4, 4), float("nan")), 10, 10, 5, 5, 10, 10)
    with pytest.raises(InputError, match="size must be positive"):
        Camera(torch.eye(4), 10, 10, 5, 5, 0, 10)
    cam.world_to_camera[0, 3] = float("inf")  # mutated after construction
    with pytest.raises(InputError, match="non-finite"):
        render(g, cam)
    with pytest.raises(InputError, match="background"):
        render(g, camera(), background=[1.0, 2.0])
    for bad in ((0.0, float("nan"), 0.0), torch.tensor([0.0, float("inf"), 0.0])):  # floats and a tensor
        with pytest.raises(InputError, match="background"):
            render(g, camera(), background=bad)


def test_backward_after_an_in_place_change_is_refused():
    """The raster op saves its inputs for backward: autograd's version check catches a stale graph."""
    g = leafs(random_scene(30, 0, seed=3))
    out = render(g, camera())
    with torch.no_grad():
        g.means.add_(0.01)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        out.color.sum().backward()


# -- binning in the fitted-scene regime: a few huge Gaussians among many small ones -------------------------------

def fitted_like_scene(n_small=1500, seed=0, dtype=torch.float64, log_scale=-3.6):
    """Many small Gaussians and a few huge ones (a needle across the image, rotated disks, one partly off
    screen, one larger than the view): the per-Gaussian tile counts of a fitted scene, from 1 to every tile."""
    g = random_scene(n_small, 1, seed=seed, dtype=dtype, spread=0.5, log_scale=log_scale, opacity_shift=0.5)
    gen = torch.Generator().manual_seed(seed + 1)
    big_means = torch.tensor([[0.0, 0.0, 0.0], [0.4, 0.3, -0.2], [-0.9, 0.2, 0.5], [1.6, -0.2, 0.1],
                              [0.0, 1.0, 0.0], [-0.3, -0.5, -0.4]], dtype=dtype)
    big_scales = torch.tensor([[1.5, 0.004, 0.004], [0.8, 0.6, 0.05], [0.5, 0.1, 0.9], [0.9, 0.9, 0.9],
                               [4.0, 4.0, 4.0], [0.7, 0.02, 0.3]], dtype=dtype)
    k = big_means.shape[0]
    big = Gaussians(big_means, torch.randn(k, 4, generator=gen, dtype=dtype), big_scales.log(),
                    torch.randn(k, generator=gen, dtype=dtype) - 0.5, torch.randn(k, 4, 3, generator=gen, dtype=dtype) * 0.3)
    return Gaussians(**{f: torch.cat([getattr(g, f), getattr(big, f)]) for f in FIELDS})


def reference_tile_pairs(proj, width, height, tol=1e-9):
    """The binning criterion by brute force in float64, from the float32 values the binning kernels read:
    (Gaussian, tile) pairs of each visible Gaussian's 3σ box whose pixel-center rectangle holds a point with
    dᵀQd <= k2 (the exact minimum of the quadratic over the rectangle). Returns (in [N, tiles] bool, borderline
    [N, tiles] bool: within tol of the level, either answer is right)."""
    from tlvg_warp.kernels.binning import TILE

    m = proj.means2d.float().double()
    q = proj.conic.float().double()
    o32 = proj.opacity.float()
    k2 = (2.0 * torch.log(255.0 * o32.clamp_min(1 / 255)) * (1.0 + 1e-4) + 1e-3).double()  # float32, as the kernel
    r = proj.radii.double()
    tiles_x, tiles_y = math.ceil(width / TILE), math.ceil(height / TILE)
    ty, tx = torch.meshgrid(torch.arange(tiles_y, dtype=torch.float64), torch.arange(tiles_x, dtype=torch.float64),
                            indexing="ij")
    tx, ty = tx.flatten()[None], ty.flatten()[None]  # [1, tiles]
    u, v = m[:, 0:1], m[:, 1:2]
    X0, X1 = tx * TILE + 0.5 - u, torch.clamp(tx * TILE + TILE, max=width) - 0.5 - u
    Y0, Y1 = ty * TILE + 0.5 - v, torch.clamp(ty * TILE + TILE, max=height) - 0.5 - v
    qa, qb, qc = q[:, 0:1], q[:, 1:2], q[:, 2:3]
    quad = lambda x, y: qa * x * x + 2 * qb * x * y + qc * y * y  # noqa: E731
    cands = [quad(x, torch.clamp(-qb * x / qc, Y0, Y1)) for x in (X0, X1)]
    cands += [quad(torch.clamp(-qb * y / qa, X0, X1), y) for y in (Y0, Y1)]
    mins = torch.stack(cands).amin(0)
    inside = (X0 <= 0) & (X1 >= 0) & (Y0 <= 0) & (Y1 >= 0)
    mins = torch.where(inside, torch.zeros_like(mins), mins)
    det = qa * qc - qb * qb
    ok = (det > 0) & (qa > 0) & (qc > 0)
    xmax = torch.where(ok, torch.sqrt(k2[:, None] * qc / det.clamp_min(1e-300)), r[:, None])
    ymax = torch.where(ok, torch.sqrt(k2[:, None] * qa / det.clamp_min(1e-300)), r[:, None])
    rx, ry = torch.minimum(r[:, None], xmax), torch.minimum(r[:, None], ymax)
    box = ((tx >= torch.floor((u - rx) / TILE)) & (tx < torch.floor((u + rx) / TILE) + 1)
           & (ty >= torch.floor((v - ry) / TILE)) & (ty < torch.floor((v + ry) / TILE) + 1))
    visible = ((proj.radii > 0) & (o32 * 255 >= 1))[:, None]
    member = visible & box & (~ok | (mins <= k2[:, None]))
    borderline = visible & box & ok & ((mins - k2[:, None]).abs() <= tol * (1 + k2[:, None]))
    return member, borderline


def binned_pairs(cap):
    """[N, tiles] bool of the (Gaussian, tile) pairs in a captured binning, and a check of its lists."""
    ranges, ids = cap["ranges"].cpu(), cap["ids"].cpu().long()
    n = cap["counts"].shape[0]
    tiles = ranges.shape[0]
    lengths = (ranges[:, 1] - ranges[:, 0]).long()
    assert int(lengths.sum()) == cap["total"] == int(cap["counts"].sum())  # no sentinel left in any list
    out = torch.zeros(n, tiles, dtype=torch.bool)
    tile_of = torch.repeat_interleave(torch.arange(tiles), lengths)
    starts = ranges[:, 0].long()
    order = torch.cat([torch.arange(s, s + length) for s, length in zip(starts.tolist(), lengths.tolist())]) \
        if cap["total"] else torch.zeros(0, dtype=torch.long)
    gid = ids[order]
    assert not out[gid, tile_of].any()
    out[gid, tile_of] = True
    assert int(out.sum()) == cap["total"]  # each Gaussian at most once per tile
    # each tile's list in depth order (ties by index: the depth sort is stable)
    depth = cap["proj"].depth.float().cpu()
    d, same_tile = depth[gid], tile_of[1:] == tile_of[:-1]
    later = (d[1:] > d[:-1]) | ((d[1:] == d[:-1]) & (gid[1:] > gid[:-1]))
    assert bool((later | ~same_tile).all()), "a tile's list is out of depth order"
    return out


def check_fitted_binning(device, dtype, **scene):
    from tlvg_warp.raster import capture_binning

    g = fitted_like_scene(dtype=torch.float64, **scene).to(device=device, dtype=dtype)
    cam = camera(200, 152, fov=55.0)  # 13 x 10 tiles, the last row and column narrower
    with capture_binning() as cap:
        render(g, cam)
    proj = cap["proj"]
    want, borderline = reference_tile_pairs(_cpu(proj), cam.width, cam.height)
    got = binned_pairs(cap)
    tiles = want.shape[1]
    per_gaussian = want.sum(1)
    assert int((per_gaussian > tiles // 2).sum()) >= 3 and int((per_gaussian > 0).sum()) > 100  # both regimes
    diff = (got != want) & ~borderline
    assert not diff.any(), f"{int(diff.sum())} pairs differ from the brute-force criterion, e.g. {diff.nonzero()[:5].tolist()}"
    assert torch.equal(cap["counts"].cpu().long(), got.sum(1))
    # and what the criterion is for: every (tile, Gaussian) with alpha >= 1/255 at a pixel center of the tile
    # (inside its 3σ box: the blending's membership) is binned
    p = _cpu(proj)
    m, q, o = p.means2d.float().double(), p.conic.float().double(), p.opacity.float().double()
    H, W = cam.height, cam.width
    r = p.radii.double()
    tiles_x = math.ceil(W / 16)
    for t in range(got.shape[1]):  # one tile's pixels at a time (memory)
        ty, tx = divmod(t, tiles_x)
        ys, xs = torch.meshgrid(torch.arange(ty * 16, min(ty * 16 + 16, H), dtype=torch.float64) + 0.5,
                                torch.arange(tx * 16, min(tx * 16 + 16, W), dtype=torch.float64) + 0.5, indexing="ij")
        dx, dy = xs.flatten()[:, None] - m[:, 0], ys.flatten()[:, None] - m[:, 1]
        power = -0.5 * (q[:, 0] * dx * dx + q[:, 2] * dy * dy) - q[:, 1] * dx * dy
        seen = ((power <= 0) & (o * torch.exp(power.clamp_max(0)) >= 1 / 255)).any(0) & (p.radii > 0)
        inbox = ((tx >= torch.floor((m[:, 0] - r) / 16)) & (tx < torch.floor((m[:, 0] + r) / 16) + 1)
                 & (ty >= torch.floor((m[:, 1] - r) / 16)) & (ty < torch.floor((m[:, 1] + r) / 16) + 1))
        assert got[seen & inbox, t].all(), f"tile {t}: a Gaussian visible at one of its pixels was not binned"


def _cpu(proj):
    from dataclasses import fields, replace

    return replace(proj, **{f.name: getattr(proj, f.name).cpu() for f in fields(proj) if getattr(proj, f.name) is not None})


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_binning_of_huge_and_small_gaussians_is_the_brute_force_set(dtype):
    """The (tile, Gaussian) pairs binned for a scene of a few huge and many small Gaussians are exactly the brute-force
    criterion's (float64, per tile), the counts match, no list holds a sentinel, each tile's list is in depth order,
    and no pixel a Gaussian reaches is missing its tile."""
    check_fitted_binning("cpu", dtype)


def test_huge_and_small_gaussians_match_reference():
    g = fitted_like_scene(n_small=400, seed=3)
    out, _ = compare(g, camera(72, 56, fov=55.0), background=[0.2, 0.3, 0.1])
    assert out.alpha.min() > 0.05  # the largest Gaussian covers everything


def test_without_depth_same_image_and_gradients():
    """depth=False skips the expected depth: color, alpha and their gradients are those of the full render."""
    g = random_scene(200, 2, seed=12)
    g1, g2 = leafs(g), leafs(g)
    full, lean = render(g1, camera(), background=[0.1, 0.2, 0.3]), render(g2, camera(), background=[0.1, 0.2, 0.3], depth=False)
    assert lean.depth is None and render_reference(g, camera(), depth=False).depth is None
    for k in ("color", "alpha"):
        assert torch.equal(getattr(full, k), getattr(lean, k)), k
    ups = upstream(full)[:2]
    ga = torch.autograd.grad(sum((o * u).sum() for o, u in zip((full.color, full.alpha), ups)), [getattr(g1, f) for f in FIELDS])
    gb = torch.autograd.grad(sum((o * u).sum() for o, u in zip((lean.color, lean.alpha), ups)), [getattr(g2, f) for f in FIELDS])
    for name, a, b in zip(FIELDS, ga, gb):
        assert torch.equal(a, b), name


@pytest.mark.parametrize("output", ["color", "alpha", "depth"])
def test_a_loss_on_one_output_has_the_reference_gradients(output):
    """The other outputs get no gradient: the backward receives None for them (autograd does not materialize zeros)
    and must read them as zeros, for every input and the screen-space probe."""
    g = random_scene(150, 2, seed=31)
    g1, g2 = leafs(g), leafs(g)
    out, ref = render(g1, camera(), background=[0.1, 0.2, 0.3]), render_reference(g2, camera(), background=[0.1, 0.2, 0.3])
    up = upstream(ref)[("color", "alpha", "depth").index(output)]
    grads = []
    for o, gl in ((out, g1), (ref, g2)):
        wrt = [getattr(gl, f) for f in FIELDS] + [o.means2d]
        gs = torch.autograd.grad((getattr(o, output) * up).sum(), wrt, allow_unused=True)  # alpha: no path to sh
        grads.append([torch.zeros_like(w) if x is None else x for x, w in zip(gs, wrt)])
    assert grads[1][0].abs().max() > 0  # the loss reaches the means
    for name, a, b in zip(FIELDS + ("means2d",), *grads):
        assert_close(a, b, F64_TOL, f"d/d{name}")


def test_fast_launch_reuses_its_launch_and_keeps_no_tensor_alive():
    """launch.fast_launch records one wp.Launch per kernel and resets its parameters per call (no per-call packing):
    each call must see its own arguments, and the recorded launch must not keep the last call's tensors alive."""
    import gc
    import weakref

    import warp as wp

    from tlvg_warp.kernels.binning import tile_ranges_kernel
    from tlvg_warp.launch import ct, fast_launch

    wp.init()
    for keys in ([0, 0, 2, 2, 2], [1, 1, 1]):  # sorted tile ids of two "renders"
        k = torch.tensor(keys, dtype=torch.int32)
        ranges = torch.zeros(3, 2, dtype=torch.int32)
        fast_launch(tile_ranges_kernel, len(keys), [ct(k), len(keys), ct(ranges)], wp.get_device("cpu"))
        want = torch.zeros(3, 2, dtype=torch.int32)
        for t in set(keys):
            want[t] = torch.tensor([keys.index(t), len(keys) - keys[::-1].index(t)])
        assert torch.equal(ranges, want)
    gone = weakref.ref(k)
    del k
    gc.collect()
    assert gone() is None


def test_kept_camera_values_survive_later_launches():
    """camera_arg keeps its camera struct per camera, and fast_launch writes later calls' values into its recorded
    launch's slots: the first call must copy value arguments, or the slot is the kept object and the next camera
    overwrites the first camera's values (renders of the first camera would then use the second's pose)."""
    from tlvg_warp import launch, raster
    from tlvg_warp.launch import kernels_for
    from tlvg_warp.raster import camera_arg, camera_values

    launch._sites.clear()  # the first launches below record their sites (whatever ran earlier in this process)
    raster._values.clear()
    g = random_scene(20, seed=4)
    cam_a, cam_b = camera(), camera(width=40, height=30, eye=(1.5, -2.0, 0.5), fov=50.0)
    K = kernels_for(torch.float64)
    fresh = camera_arg(K, cam_a)  # built before any launch (kept from here on)
    want = bytes(fresh.__ctype__())
    for cam in (cam_a, cam_b, cam_a, cam_b):
        render(g, cam)
    R, t, center = camera_values(cam_a)
    assert camera_arg(K, cam_a) is fresh and bytes(fresh.__ctype__()) == want
    assert bytes(fresh.R) == bytes(K.mat33(*[K.scalar(v) for row in R for v in row]))
    assert list(fresh.t) == t and list(fresh.center) == center
    assert (fresh.fx, fresh.fy, fresh.cx, fresh.cy, fresh.width, fresh.height, fresh.near, fresh.far) == (
        cam_a.fx, cam_a.fy, cam_a.cx, cam_a.cy, cam_a.width, cam_a.height, cam_a.near, cam_a.far)


def test_runtime_radix_sort_matches_warp_utils():
    """launch.sort_pairs calls Warp's runtime sort directly (private API, checked here against wp.utils)."""
    import warp as wp

    from tlvg_warp.launch import _runtime_sort, sort_pairs

    assert _runtime_sort("float", "host") is not None and _runtime_sort("int", "host") is not None
    gen = torch.Generator().manual_seed(0)
    for keys in (torch.randn(300, generator=gen), torch.randint(0, 9, (300,), generator=gen, dtype=torch.int32)):
        a = torch.cat([keys, torch.zeros_like(keys)])
        va = torch.cat([torch.arange(300, dtype=torch.int32), torch.zeros(300, dtype=torch.int32)])
        b, vb = a.clone(), va.clone()
        sort_pairs(a, va, 300, 0, 32 if keys.dtype == torch.float32 else 4)
        wp.utils.radix_sort_pairs(wp.from_torch(b), wp.from_torch(vb), 300, 0, 32 if keys.dtype == torch.float32 else 4)
        assert torch.equal(a[:300], b[:300]) and torch.equal(va[:300], vb[:300])
        assert torch.equal(va[:300].long(), torch.sort(keys, stable=True).indices)


def _blend_launches(monkeypatch) -> list:
    """Records every blending launch (kernel name, threads, recorded-launch instance, from the main thread?)."""
    import threading

    import tlvg_warp.autograd as autograd
    import tlvg_warp.raster as raster

    calls = []

    def recording(launch):
        def wrapped(kernel, dim, args, device, block_dim=None, adj_args=None, instance=0):
            if "blend_" in kernel.key:
                calls.append((kernel.key.split("__")[-1], dim, instance,
                              threading.current_thread() is threading.main_thread()))
            return launch(kernel, dim, args, device, block_dim, adj_args, instance)
        return wrapped

    monkeypatch.setattr(raster, "fast_launch", recording(raster.fast_launch))
    monkeypatch.setattr(autograd, "fast_launch", recording(autograd.fast_launch))
    return calls


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("depth", [True, False])
def test_the_cpu_walk_equals_the_staged_kernels_bit_for_bit(monkeypatch, dtype, depth):
    """On the CPU the blending runs kernels that walk a pixel's list without staging (raster.CPU_WALK); the GPU's
    staged kernels (run on the CPU with CPU_WALK off) are the oracle: the same images, weights and gradients to the
    last bit, on a scene with saturated pixels, huge splats and tiles most splats do not reach."""
    import tlvg_warp.raster as raster

    g = fitted_like_scene(1500, seed=3, dtype=dtype)
    g = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits + 2.0 * (torch.arange(g.num) % 3 == 0), g.sh)
    cam = camera(61, 45)
    got, launched = {}, {}
    calls = _blend_launches(monkeypatch)
    monkeypatch.setattr(raster, "CPU_HALVES", False)  # one backward launch: the sums in the staged kernels' order
    for walk in (True, False):
        monkeypatch.setattr(raster, "CPU_WALK", walk)
        calls.clear()
        gl = leafs(g)
        out = render(gl, cam, [0.1, 0.2, 0.3], return_weights=True, depth=depth)
        outs = [out.color, out.alpha] + ([out.depth] if depth else [])
        gen = torch.Generator().manual_seed(5)
        loss = sum((o * torch.randn(o.shape, generator=gen, dtype=o.dtype)).sum() for o in outs)
        got[walk] = outs + [out.weights] + list(torch.autograd.grad(loss, [getattr(gl, f) for f in FIELDS]))
        launched[walk] = {c[0] for c in calls}
    # each setting ran its own kernels (the comparison is not of one set with itself)
    assert launched[True] == {"blend_forward_cpu_kernel", "blend_backward_cpu_kernel"}
    assert launched[False] == {"blend_forward_kernel", "blend_backward_kernel"}
    assert float(got[True][1].detach().max()) > 1 - 2 * T_MIN  # some pixels saturated: the early stop was taken
    for a, b in zip(got[True], got[False]):
        assert torch.equal(a, b)


def test_the_power_cut_only_skips_splats_below_the_alpha_floor():
    """POWER_CUT skips the exp where even an opaque splat (opacity 1) stays under ALPHA_MIN, in both precisions;
    a cut one hundredth higher would not (so the margin is what it claims)."""
    from tlvg_warp.kernels.blend import ALPHA_MIN, POWER_CUT

    for dt in (torch.float32, torch.float64):
        assert float(torch.exp(torch.tensor(POWER_CUT, dtype=dt))) < ALPHA_MIN
    assert math.exp(POWER_CUT + 0.01) > ALPHA_MIN


@pytest.mark.parametrize("weights", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", [(61, 45), (16, 16), (40, 70)])
def test_the_cpu_blending_split_over_two_threads_equals_one_thread(monkeypatch, size, dtype, weights):
    """raster.CPU_THREADS 2 launches the CPU walk's two halves of the tiles from two threads, forward and backward;
    on one thread the per-Gaussian sums (the backward's gradients, the forward's weights when asked for) take the same
    two halves one after the other (raster.CPU_HALVES). Oracles: one thread, bit for bit (a run's result may not
    depend on the machine's cores; a lost or doubled half, a wrong offset or a half summed into the other's buffer
    would show), and the staged kernels in one launch (the same images to the last bit; weights and gradients up to
    the order of the sums)."""
    import tlvg_warp.raster as raster

    g = fitted_like_scene(800, seed=7, dtype=dtype)
    cam = camera(*size)
    tiles = math.ceil(size[0] / 16) * math.ceil(size[1] / 16)
    first, rest = tiles // 2 * 256, (tiles - tiles // 2) * 256
    got = []
    calls = _blend_launches(monkeypatch)
    for walk, threads in ((True, 2), (True, 1), (False, 1)):
        monkeypatch.setattr(raster, "CPU_WALK", walk)
        monkeypatch.setattr(raster, "CPU_THREADS", threads)
        calls.clear()
        gl = leafs(g)
        out = render(gl, cam, [0.1, 0.2, 0.3], return_weights=weights)
        gen = torch.Generator().manual_seed(2)
        loss = sum((o * torch.randn(o.shape, generator=gen, dtype=o.dtype)).sum() for o in (out.color, out.alpha, out.depth))
        sums = ([out.weights] if weights else []) + list(torch.autograd.grad(loss, [getattr(gl, f) for f in FIELDS]))
        got.append(([out.color, out.alpha, out.depth], sums))
        launched = {stage: sorted((c[2], c[1], c[3]) for c in calls if c[0].startswith(stage))
                    for stage in ("blend_forward", "blend_backward")}
        one = [(0, tiles * 256, True)]  # one launch (a single tile is not split; the staged kernels never are)
        two = [(0, rest, True), (1, first, False)]  # the first half on the helper thread's own launch
        in_turn = sorted([(0, first, True), (0, rest, True)])  # the two halves one after the other
        if tiles < 2 or not walk:
            assert launched == {"blend_forward": one, "blend_backward": one}
        elif threads == 2:
            assert launched == {"blend_forward": two, "blend_backward": two}
        else:  # without weights the forward's pixels are independent: one launch
            assert launched == {"blend_forward": in_turn if weights else one, "blend_backward": in_turn}
    for a, b in zip(got[0][0] + got[0][1], got[1][0] + got[1][1]):
        assert torch.equal(a, b)
    for a, b in zip(got[0][0], got[2][0]):  # images: each pixel is written by one launch
        assert torch.equal(a, b)
    names = (["weights"] if weights else []) + list(FIELDS)
    for name, a, b in zip(names, got[0][1], got[2][1]):  # the same terms, summed in another order
        assert_close(a, b, 1e-5 if dtype == torch.float32 else 1e-12, name)


# --- key buffers sized from a view's last count (IntersectionBudget) --------------------------------------------
def _tile_lists(cap) -> list:
    """Each tile's Gaussian ids, in list order, from a captured binning."""
    ranges, ids = cap["ranges"].cpu(), cap["ids"].cpu()
    return [ids[a:b].tolist() for a, b in ranges.tolist()]


def test_a_sized_render_equals_the_counted_one_and_reads_its_total_later():
    """A capacity above the total: the same image, depth and gradients, bit for bit, as the render that counted
    exactly (the sentinel-filled slots sort after every real key); the true total reaches the budget on the view's
    next render, and its capacity is the headroom times that."""
    from tlvg_warp.raster import IntersectionBudget, capture_binning

    g, cam = fitted_like_scene(dtype=torch.float32), camera(61, 45)
    g0, g1 = leafs(g), leafs(g)
    with capture_binning() as exact_cap:
        exact = render(g0, cam)
    budget = IntersectionBudget(1.25)
    budget.known["v"] = (g.num, 0, exact_cap["total"])  # as if an earlier render of the view had counted it
    cap_slots = budget.capacity("v", g.num)
    assert cap_slots == math.ceil(1.25 * exact_cap["total"])
    with capture_binning() as sized_cap:
        sized = render(g1, cam, budget=budget, budget_key="v")
    assert budget.sized == 1 and budget.exact == 0 and "v" in budget.pending  # the total is on its way
    for k in ("color", "alpha", "depth"):
        assert torch.equal(getattr(sized, k), getattr(exact, k)), k
    assert _tile_lists(sized_cap) == _tile_lists(exact_cap)
    ups = upstream(exact)
    for name, a, b in zip(FIELDS + ("means2d",), loss_grads(g1, sized, ups), loss_grads(g0, exact, ups)):
        assert torch.equal(a, b), name
    assert budget.capacity("v", g.num) == math.ceil(1.25 * exact_cap["total"])  # the total, read back
    assert budget.counts() == {"exact": 0, "sized": 1, "over_capacity": 0}
    assert budget.capacity("v", g.num + 1) is None  # the Gaussians changed (density control): count exactly
    budget.scene = 1
    assert budget.capacity("v", g.num) is None  # ... or the caller marked a structural change


@pytest.mark.parametrize("share", [2 / 3, 1 / 4])
def test_a_render_over_its_capacity_drops_the_deepest_keys_and_is_counted(share):
    """A capacity below the total: the render keeps the first keys in depth order, so each tile's list is a
    prefix of the exact one and the kept keys number the capacity; the budget counts the overflow, and the view's
    next render, sized from the true total, is the exact render again. At a quarter of the total the key buffer
    (the capacity's 2x room) ends at half the total: a key written past the capacity would land outside it."""
    from tlvg_warp.raster import IntersectionBudget, capture_binning

    g, cam = fitted_like_scene(dtype=torch.float32), camera(61, 45)
    with capture_binning() as exact_cap:
        exact = render(g, cam)
    short = int(exact_cap["total"] * share)
    budget = IntersectionBudget(1.25)
    budget.known["v"] = (g.num, 0, math.floor(short / 1.25))
    assert budget.capacity("v", g.num) <= short
    with capture_binning() as low_cap:
        low = render(g, cam, budget=budget, budget_key="v")
    kept, full = _tile_lists(low_cap), _tile_lists(exact_cap)
    assert sum(map(len, kept)) == budget.pending["v"][2] < exact_cap["total"]
    assert all(k == f[:len(k)] for k, f in zip(kept, full))
    assert any(len(k) < len(f) for k, f in zip(kept, full))
    assert torch.isfinite(low.color).all() and not torch.equal(low.color, exact.color)
    again = render(g, cam, budget=budget, budget_key="v")
    assert budget.overflows == 1 and budget.counts()["over_capacity"] == 1
    assert torch.equal(again.color, exact.color) and torch.equal(again.alpha, exact.alpha)


def test_headroom_must_exceed_one():
    from tlvg_warp.raster import IntersectionBudget

    for bad in (1.0, 0.5, float("nan")):
        with pytest.raises(ValueError):
            IntersectionBudget(bad)
