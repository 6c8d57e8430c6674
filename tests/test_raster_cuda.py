"""The same rasterizer on a CUDA device (skipped without one): CUDA results against the CPU float64 oracle."""
import pytest
import torch

from tlvg_warp import render
from tlvg_warp.reference import render_reference

from test_raster import (F32_TOL, F64_TOL, FIELDS, assert_close, camera, check_fitted_binning, fitted_like_scene, leafs,
                         loss_grads, random_scene, upstream)

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.parametrize("dtype,tol", [(torch.float64, F64_TOL), (torch.float32, F32_TOL)])
def test_cuda_matches_cpu_reference(dtype, tol):
    g = random_scene(400, 3, seed=21)
    cam = camera(70, 45)
    gc = leafs(g.to("cuda", dtype))
    out = render(gc, cam, background=[0.2, 0.1, 0.3], return_weights=True)
    gr = leafs(g)
    ref = render_reference(gr, cam, background=[0.2, 0.1, 0.3], return_weights=True)
    for k in ("color", "alpha", "depth", "weights"):
        assert_close(getattr(out, k).cpu().double(), getattr(ref, k), tol, k)
    ups = upstream(ref)
    ga = loss_grads(gc, out, [u.to("cuda", dtype) for u in ups])
    gb = loss_grads(gr, ref, ups)
    for name, a, b in zip(FIELDS + ("means2d",), ga, gb):
        assert_close(a.cpu().double(), b, tol * 10 if dtype == torch.float32 else tol, f"d/d{name}")


@pytest.mark.parametrize("n", [1500, 3000])
def test_cuda_batches_and_early_stop(n):
    """Tiles holding several shared-memory batches (>256 Gaussians each) and pixels that saturate mid-batch:
    the batched GPU blending against the float64 oracle, image and gradients."""
    g = random_scene(n, 1, seed=n, spread=0.08, log_scale=-1.5, opacity_shift=1.0)
    cam = camera(40, 36)
    gc = leafs(g.to("cuda"))
    out = render(gc, cam, background=[0.1, 0.2, 0.3])
    gr = leafs(g)
    ref = render_reference(gr, cam, background=[0.1, 0.2, 0.3])
    assert (ref.alpha > 1 - 2e-4).float().mean() > 0.15  # many pixels stop early (T < T_MIN)
    for k in ("color", "alpha", "depth"):
        assert_close(getattr(out, k).cpu(), getattr(ref, k), F64_TOL, k)
    ups = upstream(ref)
    ga = loss_grads(gc, out, [u.to("cuda") for u in ups])
    gb = loss_grads(gr, ref, ups)
    for name, a, b in zip(FIELDS + ("means2d",), ga, gb):
        assert_close(a.cpu(), b, F64_TOL, f"d/d{name}")


@pytest.mark.parametrize("dtype,log_scale,n_small", [(torch.float32, -3.6, 1500), (torch.float64, -3.6, 1500),
                                                      (torch.float32, -2.6, 4000), (torch.float32, -3.0, 12000)])
def test_cuda_binning_of_huge_and_small_gaussians(dtype, log_scale, n_small):
    """The warp-pooled binning on the GPU (32 lanes share the large Gaussians' rows; on the CPU a warp has one lane):
    the binned (tile, Gaussian) set equals the brute-force criterion, counts match, no sentinel in any list, each
    tile's list in depth order, no visible pixel's tile missing, with warps holding one, several or many large
    Gaussians (the larger log scales make most Gaussians span several work items)."""
    check_fitted_binning("cuda", dtype, log_scale=log_scale, n_small=n_small)


def test_cuda_huge_and_small_gaussians_match_cpu_reference():
    g = fitted_like_scene(n_small=400, seed=3)
    cam = camera(72, 56, fov=55.0)
    gc = leafs(g.to("cuda"))
    out = render(gc, cam, background=[0.2, 0.3, 0.1], return_weights=True)
    gr = leafs(g)
    ref = render_reference(gr, cam, background=[0.2, 0.3, 0.1], return_weights=True)
    for k in ("color", "alpha", "depth", "weights"):
        assert_close(getattr(out, k).cpu(), getattr(ref, k), F64_TOL, k)
    ups = upstream(ref)
    for name, a, b in zip(FIELDS + ("means2d",), loss_grads(gc, out, [u.to("cuda") for u in ups]), loss_grads(gr, ref, ups)):
        assert_close(a.cpu(), b, F64_TOL, f"d/d{name}")
    again = render(gc, cam, background=[0.2, 0.3, 0.1], return_weights=True)  # through the recorded launches
    for k in ("color", "alpha", "depth", "weights"):
        assert torch.equal(getattr(again, k), getattr(out, k)) or k == "weights", k  # weights: atomics


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_without_depth_same_image_and_gradients(dtype):
    g = random_scene(300, 2, seed=13).to("cuda", dtype)
    g1, g2 = leafs(g), leafs(g)
    full, lean = render(g1, camera(), background=[0.1, 0.2, 0.3]), render(g2, camera(), background=[0.1, 0.2, 0.3], depth=False)
    assert lean.depth is None
    for k in ("color", "alpha"):
        assert torch.equal(getattr(full, k), getattr(lean, k)), k
    ups = [torch.randn_like(full.color), torch.randn_like(full.alpha)]
    ga = torch.autograd.grad((full.color * ups[0]).sum() + (full.alpha * ups[1]).sum(), [getattr(g1, f) for f in FIELDS])
    gb = torch.autograd.grad((lean.color * ups[0]).sum() + (lean.alpha * ups[1]).sum(), [getattr(g2, f) for f in FIELDS])
    for name, a, b in zip(FIELDS, ga, gb):
        assert_close(a, b, 1e-6 if dtype == torch.float32 else 1e-12, name)  # atomics: summation order only


def test_cuda_render_on_a_side_stream_and_warp_state_restored():
    """launch.warp_on runs the launches on torch's current stream and skips the CUDA context push when the context is
    already current: a render on a side stream (forward and backward there) equals one on the default stream, the
    default stream's next render is right again (the stream switched back), and Warp's default device and the
    thread's CUDA context are what they were before each render."""
    import warp as wp

    from tlvg_warp.launch import _runtime

    g = random_scene(500, 2, seed=5).to("cuda")
    cam = camera(64, 48)
    core = _runtime().core
    before_dev, before_ctx = wp.get_device(), core.wp_cuda_context_get_current()
    g1 = leafs(g)
    ref = render(g1, cam, background=[0.1, 0.2, 0.3])
    ups = [torch.randn_like(ref.color), torch.randn_like(ref.alpha)]
    ga = torch.autograd.grad((ref.color * ups[0]).sum() + (ref.alpha * ups[1]).sum(), [getattr(g1, f) for f in FIELDS])
    assert wp.get_device() == before_dev and core.wp_cuda_context_get_current() == before_ctx
    g2 = leafs(g)  # made on the default stream: the side stream waits for the copies too (a race under load)
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        out = render(g2, cam, background=[0.1, 0.2, 0.3])
        gb = torch.autograd.grad((out.color * ups[0]).sum() + (out.alpha * ups[1]).sum(),
                                 [getattr(g2, f) for f in FIELDS])
        assert wp.get_device(str(g.device)).stream.cuda_stream == side.cuda_stream  # the launches went to the side
    torch.cuda.current_stream().wait_stream(side)
    for k in ("color", "alpha", "depth"):
        assert torch.equal(getattr(out, k), getattr(ref, k)), k
    for name, a, b in zip(FIELDS, ga, gb):
        assert_close(a, b, 1e-6, name)  # atomics: summation order only
    again = render(leafs(g), cam, background=[0.1, 0.2, 0.3])  # back on the default stream
    assert torch.equal(again.color, ref.color)
    assert wp.get_device(str(g.device)).stream.cuda_stream == torch.cuda.current_stream().cuda_stream  # and back
    assert wp.get_device() == before_dev and core.wp_cuda_context_get_current() == before_ctx


def test_cuda_sized_render_reads_its_total_without_waiting_and_matches_the_counted_one():
    """On the GPU the budget's total travels to pinned memory behind a CUDA event: a render sized from the view's
    last count gives the counted render's image (the blending is deterministic) and gradients (atomic sums: to
    float32 rounding), and the next render of the view is sized from the total read back; one below it overflows
    and is counted."""
    import math

    from tlvg_warp.raster import IntersectionBudget, capture_binning

    g = fitted_like_scene(dtype=torch.float32).to("cuda")
    cam = camera(61, 45)
    g0, g1 = leafs(g), leafs(g)
    budget = IntersectionBudget(1.25)
    with capture_binning() as cap:
        exact = render(g0, cam, budget=budget, budget_key=0)  # the view's first render: counted exactly
    sized = render(g1, cam, budget=budget, budget_key=0)
    assert budget.counts() == {"exact": 1, "sized": 1, "over_capacity": 0}
    assert budget.capacity(0, g.num) == math.ceil(1.25 * cap["total"])
    for k in ("color", "alpha", "depth"):
        assert torch.equal(getattr(sized, k), getattr(exact, k)), k
    ups = [u.cuda() for u in upstream(exact)]
    for name, a, b in zip(FIELDS + ("means2d",), loss_grads(g1, sized, ups), loss_grads(g0, exact, ups)):
        assert_close(a, b, F32_TOL, f"d/d{name}")
    budget.known[0] = (g.num, 0, cap["total"] // 2)
    render(g, cam, budget=budget, budget_key=0)
    assert budget.counts()["over_capacity"] == 1
