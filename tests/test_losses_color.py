"""Color transfer (closed-form moments), sRGB->Lab vs OpenCV, the Lab chroma loss, luminance."""
import cv2
import numpy as np
import pytest
import torch

from tlvg_warp.losses import (apply_color_transform, color_transfer, lab_chroma_loss, lab_chroma_stats, luminance,
                              rgb_to_lab)
from tlvg_warp.losses.style import fast_loss

MOMENT_TOL = 1e-9  # float64 throughout; the map is exact up to round-off when nothing is clamped
# OpenCV's float RGB->Lab interpolates the sRGB gamma through a 1024-entry spline table and rounds; 0.37 Lab
# units measured on random colors. 0.5 is still far below a just-noticeable difference (~2.3).
LAB_TOL = 0.5


def _moments(p):
    p = p.reshape(-1, 3)
    return p.mean(0), np.cov(p.T, bias=True)


def test_color_transfer_matches_style_moments_when_unclamped():
    rng = np.random.default_rng(0)
    mix = np.array([[0.05, 0.02, 0.0], [0.01, 0.04, 0.01], [0.0, 0.02, 0.03]])
    content = [0.5 + rng.standard_normal((30, 40, 3)) @ mix.T for _ in range(2)]  # correlated, no clamping
    style = 0.4 + rng.standard_normal((25, 35, 3)) @ (0.6 * mix[::-1]).T
    out, m, t = color_transfer(content, style)
    assert isinstance(out, list) and out[0].shape == (30, 40, 3)
    pooled = np.concatenate([o.reshape(-1, 3) for o in out])
    assert pooled.min() > 0 and pooled.max() < 1  # the premise: no clamping happened
    mu, cov = _moments(pooled)
    mu_s, cov_s = _moments(style)
    assert np.abs(mu - mu_s).max() < MOMENT_TOL and np.abs(cov - cov_s).max() < MOMENT_TOL
    # the returned affine map reproduces the result and reapplies to torch batches
    again = apply_color_transform(torch.from_numpy(np.stack(content)), m, t)
    assert np.abs(again.numpy() - np.stack(out)).max() < 1e-12
    b, _, _ = color_transfer(torch.from_numpy(np.stack(content)).float(), torch.from_numpy(style).float())
    assert b.dtype == torch.float32 and b.shape == (2, 30, 40, 3)


def _sqrt_psd(c, p):  # float64 numpy c^p for a symmetric positive definite 3x3
    e, u = np.linalg.eigh(c)
    return u @ np.diag(e ** p) @ u.T


def test_color_transfer_weights_take_the_moments_of_the_covered_pixels():
    """weights: the content moments are the weighted ones (numpy's np.cov with aweights), the map ARF's closed form
    on them; pixels of weight 0 do not move the map; all-ones weights are the plain transfer."""
    rng = np.random.default_rng(3)
    content = [rng.random((12, 16, 3)) * 0.5 + 0.2 for _ in range(2)]
    weights = [np.zeros((12, 16, 1)) for _ in range(2)]
    for w in weights:
        w[3:10, 4:12] = rng.random((7, 8, 1)) * 0.9 + 0.1  # a soft-edged "object"; the rest is background
    style = rng.random((10, 14, 3))
    _, m, t = color_transfer(content, style, 0.004, weights)
    px = np.concatenate([c.reshape(-1, 3) for c in content])
    aw = np.concatenate([w.reshape(-1) for w in weights])
    mu_c, cov_c = np.average(px, axis=0, weights=aw), np.cov(px.T, aweights=aw, bias=True)
    mu_s, cov_s = _moments(style)
    m_ref = _sqrt_psd(cov_s, 0.5) @ _sqrt_psd(cov_c + 0.004 * np.eye(3), -0.5)
    assert np.abs(m.numpy() - m_ref).max() < MOMENT_TOL
    assert np.abs(t.numpy() - (mu_s - m_ref @ mu_c)).max() < MOMENT_TOL
    white = [np.where(w > 0, c, 1.0) for c, w in zip(content, weights)]  # the background painted white
    _, m_white, _ = color_transfer(white, style, 0.004, weights)
    assert np.abs(m_white.numpy() - m.numpy()).max() < MOMENT_TOL
    assert np.abs(color_transfer(white, style, 0.004)[1].numpy() - m.numpy()).max() > 0.05  # unweighted, it moves
    ones = [np.ones((12, 16, 1)) for _ in range(2)]
    assert np.abs(color_transfer(content, style, 0.0, ones)[1].numpy() - color_transfer(content, style)[1].numpy()).max() < MOMENT_TOL
    nothing = [np.zeros((12, 16, 1)) for _ in range(2)]  # nothing covered: the plain transfer, no division by zero
    assert np.abs(color_transfer(content, style, 0.0, nothing)[1].numpy() - color_transfer(content, style)[1].numpy()).max() < MOMENT_TOL


def test_color_transfer_clamps():
    rng = np.random.default_rng(1)
    out, _, _ = color_transfer(rng.random((2, 8, 8, 3)), rng.random((8, 8, 3)) * 3 - 1)
    assert out.min() >= 0 and out.max() <= 1


def test_rgb_to_lab_matches_opencv_float_path():
    rng = np.random.default_rng(2)
    x = rng.random((40, 40, 3)).astype(np.float32)
    x[0, :8] = [[0, 0, 0], [1, 1, 1], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.02, 0.01, 0.03], [0.5] * 3, [1, 1, 0]]
    ref = cv2.cvtColor(x, cv2.COLOR_RGB2Lab)
    got = rgb_to_lab(torch.from_numpy(x).double()).numpy()
    assert np.abs(got - ref).max() < LAB_TOL
    # differentiable everywhere, including black (cube root and gamma branches at 0)
    t = torch.from_numpy(x).double().requires_grad_(True)
    rgb_to_lab(t).sum().backward()
    assert torch.isfinite(t.grad).all()


def test_lab_chroma_loss_closed_form():
    rng = np.random.default_rng(3)
    tgt = torch.from_numpy(rng.random((16, 16, 3)))
    assert lab_chroma_loss(tgt, tgt).item() < 1e-12
    r = torch.from_numpy(rng.random((16, 16, 3))).requires_grad_(True)
    lab_r, lab_t = cv2.cvtColor(r.detach().numpy().astype(np.float32), cv2.COLOR_RGB2Lab), \
        cv2.cvtColor(tgt.numpy().astype(np.float32), cv2.COLOR_RGB2Lab)
    ab_r, ab_t = lab_r.reshape(-1, 3)[:, 1:], lab_t.reshape(-1, 3)[:, 1:]
    expect = 0.5 * (np.abs(ab_r.mean(0) - ab_t.mean(0)).sum() + np.abs(ab_r.std(0) - ab_t.std(0)).sum())
    loss = lab_chroma_loss(r, tgt)
    assert abs(loss.item() - expect) < 2 * LAB_TOL  # four L1 terms of statistics of OpenCV's rounded Lab
    loss.backward()
    assert torch.isfinite(r.grad).all() and r.grad.abs().sum() > 0
    # gray images have no chroma: a = b = 0, so gray vs gray costs nothing whatever the brightness
    g1, g2 = torch.full((4, 4, 3), 0.2), torch.full((4, 4, 3), 0.9)
    assert lab_chroma_loss(g1, g2).item() < 1e-3


def test_luminance_and_chroma_blind_style_loss():
    x = torch.rand(2, 3, 10, 12, dtype=torch.float64)
    y = luminance(x)
    expect = 0.299 * x[:, 0] + 0.587 * x[:, 1] + 0.114 * x[:, 2]
    assert y.shape == x.shape and torch.allclose(y, expect.unsqueeze(1).expand_as(x))
    hwc = x[0].permute(1, 2, 0)
    assert torch.allclose(luminance(hwc), expect[0].unsqueeze(-1).expand(10, 12, 3))
    # a chroma-only change (orthogonal to the luma weights) leaves the luminance style loss unchanged
    w = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    chroma = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    chroma = chroma - (chroma @ w) / (w @ w) * w  # [3], zero luminance
    x2 = x + 0.05 * chroma.view(1, 3, 1, 1)
    assert torch.allclose(luminance(x2), luminance(x), atol=1e-12)
    feats = lambda im: torch.nn.functional.avg_pool2d(luminance(im), 2)[0].reshape(3, -1)  # noqa: E731
    s = torch.rand(3, 40, dtype=torch.float64)
    assert abs(fast_loss(feats(x2), s).item() - fast_loss(feats(x), s).item()) < 1e-9


def test_recolored_gaussians_render_the_recolored_image():
    """recolor_sh: rendering the mapped Gaussians over M·bg + t equals M·(render) + t (float64 reference
    renderer), for view-dependent SH too, as long as no colour is clamped at 0."""
    from tlvg_warp.losses import recolor_sh
    from tlvg_warp.reference import render_reference
    from tlvg_warp.types import Camera, Gaussians

    gen = torch.Generator().manual_seed(3)
    r = lambda *s: torch.randn(*s, generator=gen, dtype=torch.float64)  # noqa: E731
    n = 60
    sh = r(n, 4, 3) * 0.05
    sh[:, 0] = (0.5 + 0.2 * torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) / 0.28209479177387814
    g = Gaussians(r(n, 3) * 0.5, r(n, 4), r(n, 3) * 0.3 - 2.0, r(n), sh)
    m = torch.tensor([[0.5, 0.2, 0.1], [0.1, 0.6, 0.1], [0.2, 0.1, 0.9]], dtype=torch.float64)
    t = torch.tensor([0.05, 0.1, 0.02], dtype=torch.float64)
    cam = Camera.look_at((0.2, -3.0, 0.3), [0, 0, 0], width=31, height=23, fov_deg=60.0)
    bg = torch.tensor([0.3, 0.4, 0.5], dtype=torch.float64)
    want = render_reference(g, cam, background=tuple(bg.tolist())).color @ m.T + t
    g2 = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, recolor_sh(g.sh, m, t))
    got = render_reference(g2, cam, background=tuple((m @ bg + t).tolist())).color
    assert torch.allclose(got, want, atol=1e-10)
    assert (got - render_reference(g, cam, background=tuple(bg.tolist())).color).abs().max() > 0.05


def _lab_chroma_autograd(render, target):
    """The loss through autograd of the torch sRGB->Lab (the formula before the Warp kernels): the oracle."""
    ab_r = rgb_to_lab(render).reshape(-1, 3)[:, 1:]
    ab_t = rgb_to_lab(target).reshape(-1, 3)[:, 1:].detach()
    return 0.5 * ((ab_r.mean(0) - ab_t.mean(0)).abs().sum()
                  + (ab_r.std(0, unbiased=False) - ab_t.std(0, unbiased=False)).abs().sum())


def test_lab_chroma_kernels_match_autograd_of_rgb_to_lab():
    rng = np.random.default_rng(5)
    x = rng.random((24, 30, 3)) * 1.1 - 0.05  # some negatives (clamped) and overshoots
    x[0, :4] = [[0.01, 0.02, 0.03], [0.03, 0.0401, 0.02], [0.001, 0.002, 0.0005], [0.3, 0.3, 0.3]]  # both segments
    tgt = torch.from_numpy(rng.random((24, 30, 3)))
    want = _lab_chroma_autograd(torch.from_numpy(x).requires_grad_(True), tgt)
    r1 = torch.from_numpy(x).requires_grad_(True)
    r2 = torch.from_numpy(x).requires_grad_(True)
    got = lab_chroma_loss(r1, tgt)
    want = _lab_chroma_autograd(r2, tgt)
    got.backward()
    want.backward()
    assert abs(got.item() - want.item()) < 1e-10  # float64 on both sides: operation order only
    assert torch.allclose(r1.grad, r2.grad, rtol=1e-9, atol=1e-12)
    # statistics once per view give the same loss; float32 stays within its round-off
    st = lab_chroma_stats(tgt)
    ab = rgb_to_lab(tgt).reshape(-1, 3)[:, 1:]
    assert torch.allclose(st, torch.cat([ab.mean(0), ab.std(0, unbiased=False)]), atol=1e-10)
    assert lab_chroma_loss(torch.from_numpy(x), target_stats=st).item() == got.item()
    r3 = torch.from_numpy(x).float().requires_grad_(True)
    l3 = lab_chroma_loss(r3, tgt.float())
    l3.backward()
    assert abs(l3.item() - want.item()) < 1e-4 and torch.allclose(r3.grad.double(), r2.grad, atol=1e-5)


def test_lab_chroma_through_torch_matches_the_kernels():
    """The torch twin a CUDA graph replays (the Warp kernels are not captured) gives the kernels' loss and gradient
    in float64, on a grey render too (σ = 0: a 0 gradient there, not NaN), and passes finite differences. Catches a
    sample σ for the population one, a σ term dropped, or NaN at grey."""
    from tlvg_warp.losses.color import lab_chroma_loss_torch

    rng = np.random.default_rng(7)
    st = lab_chroma_stats(torch.from_numpy(rng.random((6, 7, 3))))
    for x in (rng.random((9, 11, 3)) * 1.1 - 0.05, np.full((4, 4, 3), 0.5)):
        r1, r2 = (torch.from_numpy(x).requires_grad_(True) for _ in range(2))
        got, want = lab_chroma_loss_torch(r1, st), lab_chroma_loss(r2, target_stats=st)
        got.backward()
        want.backward()
        assert abs(got.item() - want.item()) < 1e-10 and want.item() > 1.0
        assert torch.isfinite(r1.grad).all() and torch.allclose(r1.grad, r2.grad, rtol=1e-8, atol=1e-11)
    x = torch.from_numpy(rng.random((5, 6, 3)) * 0.8 + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: lab_chroma_loss_torch(t, st), (x,))


def test_lab_chroma_backward_finite_differences_and_gray():
    rng = np.random.default_rng(6)
    x = torch.from_numpy(rng.random((5, 6, 3)) * 0.8 + 0.1).requires_grad_(True)  # away from the kinks
    tgt = torch.from_numpy(rng.random((5, 6, 3)))
    st = lab_chroma_stats(tgt)
    assert torch.autograd.gradcheck(lambda t: lab_chroma_loss(t, target_stats=st), (x,))
    # a gray render has σ_ab = 0: the σ term's gradient is 0 there (as torch's std backward), never NaN
    g = torch.full((4, 4, 3), 0.5, dtype=torch.float64, requires_grad=True)
    g2 = torch.full((4, 4, 3), 0.5, dtype=torch.float64, requires_grad=True)
    lab_chroma_loss(g, target_stats=st).backward()
    _lab_chroma_autograd(g2, tgt).backward()
    assert torch.isfinite(g.grad).all() and torch.allclose(g.grad, torch.nan_to_num(g2.grad), atol=1e-9)


def test_gray_gradient_keeps_the_value_and_spreads_the_gradient_over_the_channels():
    """gray_gradient: the same image (bit for bit), and a luminance-only loss's gradient spread evenly over R, G, B.
    Oracle, closed form: L = Σ Y·R with Y = 0.299R + 0.587G + 0.114B has ∂L/∂img_c = R·w_c through the plain image
    and R·(Σ w)/3 = R/3 through gray_gradient (the three weights sum to 1). Catches the channel mean returned as
    the value, the gradient left along the luma weights, a factor lost in the spread."""
    from tlvg_warp.losses import gray_gradient

    gen = torch.Generator().manual_seed(3)
    img = torch.rand(5, 7, 3, generator=gen, dtype=torch.float64)
    r = torch.randn(5, 7, generator=gen, dtype=torch.float64)
    w = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    grads = []
    for f in (lambda x: x, gray_gradient):
        x = img.clone().requires_grad_(True)
        y = f(x)
        assert torch.equal(y, img)
        (luminance(y)[..., 0] * r).sum().backward()
        grads.append(x.grad)
    assert torch.allclose(grads[0], r[..., None] * w, atol=1e-15)
    assert torch.allclose(grads[1], (r / 3)[..., None].expand(-1, -1, 3), atol=1e-15)


@pytest.mark.parametrize("rgb", [(0.3, 0.4, 0.6), (0.5, 0.5, 0.5), (0.2, 0.5, 0.3), (0.7, 0.6, 0.3)])
def test_a_step_along_the_luma_weights_moves_lab_chroma_and_a_grey_step_barely(rgb):
    """Why loss.luminance_grad gray exists: raising Y by 0.05 along Y's own gradient (0.299, 0.587, 0.114) moves Lab
    a, b by more than 5 units on these colours (as much as it moves L), along the grey axis (1, 1, 1) by under 1.
    Oracle: rgb_to_lab, itself checked against OpenCV above."""
    c = torch.tensor(rgb, dtype=torch.float64)
    w = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    moved = []
    for d in (w, torch.ones(3, dtype=torch.float64)):
        step = 0.05 / float(w @ d) * d  # raises Y by 0.05
        lab = rgb_to_lab(torch.stack([c, c + step]))
        moved.append(float((lab[1, 1:] - lab[0, 1:]).norm()))
    assert moved[0] > 5.0 > 1.0 > moved[1]


def test_lab_targets_raise_each_spread_to_the_paintings_and_keep_the_means():
    """``lab_sigma: painting``: per view (μ_a, μ_b) stay the recolored view's and each σ becomes max(view's σ,
    painting's σ), OpenCV's Lab the oracle; ``photo`` is the view's statistics unchanged. Catches the painting's
    means taken too, min for max, the two channels swapped, or the option not applied."""
    from tlvg_warp.stylize.pipeline import lab_targets

    rng = np.random.default_rng(5)
    grey = 0.5 + 0.02 * rng.standard_normal((12, 10, 3))  # a near-grey view: both of its σ under the painting's
    painting = np.stack([rng.random((20, 16)), 0.3 * rng.random((20, 16)), rng.random((20, 16))], -1)  # σ_b > σ_a
    coloured = rng.random((12, 10, 3))  # a view with more a-spread than the painting's
    views = [torch.from_numpy(np.clip(v, 0, 1)) for v in (grey, coloured)]
    ab = lambda im: cv2.cvtColor(np.asarray(im, np.float32), cv2.COLOR_RGB2Lab).reshape(-1, 3)[:, 1:]  # noqa: E731
    paint_sd = ab(painting).std(0)
    assert paint_sd[1] > paint_sd[0] + 5  # the test's premise: the two channels differ
    photo = lab_targets(views, torch.from_numpy(painting), "photo")
    raised = lab_targets(views, torch.from_numpy(painting), "painting")
    for v, st_photo, st in zip(views, photo, raised):
        lab = ab(v.numpy())
        assert np.allclose(st_photo.numpy(), np.r_[lab.mean(0), lab.std(0)], atol=LAB_TOL)
        assert np.allclose(st[:2].numpy(), lab.mean(0), atol=LAB_TOL)  # the view's means
        assert np.allclose(st[2:].numpy(), np.maximum(lab.std(0), paint_sd), atol=LAB_TOL)
    assert raised[0][3] > photo[0][3] + 5  # the grey view's b-spread raised to the painting's
    assert float(raised[1][2]) == pytest.approx(float(photo[1][2]))  # a spread already above the painting's kept


def test_lab_block_takes_the_statistics_over_block_means():
    """``loss.lab_block`` B: targets and render are averaged over blocks B x the view's height on a side before the
    Lab statistics (OpenCV's area resize, which averages whole blocks, and OpenCV's Lab the oracle); a chequerboard
    of two chromas has its per-pixel a, b spread but none left over 2 x 2 blocks, so the block term asks nothing of
    speckle. Catches the block ignored, applied to one side only, sized off the width, or strided unlike its size."""
    from tlvg_warp.losses import lab_chroma_loss
    from tlvg_warp.stylize.pipeline import block_mean, lab_block_px, lab_targets

    assert (lab_block_px(12, 1 / 3), lab_block_px(160, 0.03), lab_block_px(100, 0.0)) == (4, 5, 1)
    rng = np.random.default_rng(7)
    view = rng.random((12, 16, 3))  # 12 tall: blocks of 1/3 the height are 4 x 4 pixels
    oracle = cv2.resize(view.astype(np.float32), (4, 3), interpolation=cv2.INTER_AREA)  # 4 x 4 block means
    assert np.allclose(block_mean(torch.from_numpy(view), 4).numpy(), oracle, atol=1e-6)
    ab = cv2.cvtColor(oracle, cv2.COLOR_RGB2Lab).reshape(-1, 3)[:, 1:]
    st = lab_targets([torch.from_numpy(view)], torch.from_numpy(view), "photo", block=1 / 3)[0]
    assert np.allclose(st.numpy(), np.r_[ab.mean(0), ab.std(0)], atol=LAB_TOL)
    red, cyan = np.array([0.8, 0.3, 0.3]), np.array([0.3, 0.55, 0.55])  # two chromas
    board = np.where((np.add.outer(np.arange(8), np.arange(8)) % 2 == 0)[..., None], red, cyan)  # [8,8,3]
    flat = np.broadcast_to(board.reshape(-1, 3).mean(0), board.shape).copy()  # the same block means, no speckle
    b, f = torch.from_numpy(board), torch.from_numpy(flat)
    per_pixel = lab_chroma_loss(b, target_stats=lab_targets([f], f, "photo")[0])
    blocked = lab_chroma_loss(block_mean(b, 2), target_stats=lab_targets([f], f, "photo", block=0.25)[0])
    assert float(per_pixel) > 5.0 and float(blocked) < 1e-3


def test_lab_where_covered_reads_only_the_blocks_the_scene_covers():
    """``loss.lab_where: covered``: the Lab statistics of the blocks whose mean un-stylized alpha is at least 0.5
    (an object on white is asked for its own colour spread, not its background's); a capture covered everywhere reads
    every block (index None, the same statistics as ``all``). OpenCV's area resize and Lab the oracle. Catches the
    mask ignored, inverted, taken per pixel instead of per block, or applied to the target only."""
    from tlvg_warp.losses import lab_chroma_loss
    from tlvg_warp.stylize.pipeline import lab_blocks, lab_input, lab_targets

    rng = np.random.default_rng(11)
    view = rng.random((12, 16, 3))
    alpha = np.zeros((12, 16, 1))  # 4 x 4 blocks: 3 rows of 4
    alpha[:4, :8] = 1.0  # the object covers blocks 0 and 1
    alpha[4:6, :4] = 1.0  # and half of block 4 (its mean 0.5: covered)
    alpha[8:10, 4:8] = 0.4  # a faint block 9 (mean 0.2: not covered)
    (idx,) = lab_blocks([torch.from_numpy(alpha)], 1 / 3)
    assert sorted(idx.tolist()) == [0, 1, 4]
    means = cv2.resize(view.astype(np.float32), (4, 3), interpolation=cv2.INTER_AREA).reshape(-1, 3)
    ab = cv2.cvtColor(means[[0, 1, 4]][None], cv2.COLOR_RGB2Lab)[0, :, 1:]
    st = lab_targets([torch.from_numpy(view)], torch.from_numpy(view), "photo", 1 / 3, [idx])[0]
    assert np.allclose(st.numpy(), np.r_[ab.mean(0), ab.std(0)], atol=LAB_TOL)
    # the render is read at the same blocks: equal to the view there and anything elsewhere, it scores 0
    keep = np.zeros((12, 16, 1), bool)
    keep[:4, :8] = keep[4:8, :4] = True  # the pixels of blocks 0, 1 and 4
    other = torch.from_numpy(np.where(keep, view, rng.random((12, 16, 3))))
    assert float(lab_chroma_loss(lab_input(other, 1 / 3, idx), target_stats=st)) < 1e-3
    assert float(lab_chroma_loss(lab_input(other, 1 / 3, None), target_stats=st)) > 0.5
    assert lab_blocks([torch.ones(12, 16, 1, dtype=torch.float64)], 1 / 3) == [None]
    assert lab_blocks([torch.zeros(12, 16, 1, dtype=torch.float64)], 1 / 3) == [None]  # an empty view: all, not NaN


def test_smooth_chroma_blurs_rgb_minus_luminance_as_opencv_and_keeps_the_luminance():
    """smooth_chroma against OpenCV: the chroma (RGB - Y, BT.601) of a random image blurred by cv2.GaussianBlur in
    float64 with the same kernel size and reflected border, added back to Y; Y of the output equals Y of the input."""
    from tlvg_warp.losses.color import smooth_chroma

    rng = np.random.default_rng(3)
    img = rng.random((23, 31, 3))
    sigma = 1.7
    out = smooth_chroma(torch.from_numpy(img), sigma).numpy()
    w = np.array([0.299, 0.587, 0.114])
    y = img @ w
    k = 2 * max(1, int(round(3 * sigma))) + 1
    chroma = cv2.GaussianBlur(img - y[..., None], (k, k), sigma, borderType=cv2.BORDER_REFLECT_101)
    np.testing.assert_allclose(out, y[..., None] + chroma, atol=1e-12)
    np.testing.assert_allclose(out @ w, y, atol=1e-12)
    assert np.abs(out - img).max() > 0.05  # the chroma did move
