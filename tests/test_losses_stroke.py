"""Stroke field: synthetic stripes at known angles, noise, torch vs OpenCV twin, view mappings, the flow
score, and the LIC picture."""
import math

import numpy as np
import pytest
import torch

from tlvg_warp.losses import (field_at_cells, field_picture, flow_alignment_score, flow_alignment_score_torch,
                              luminance, map_field_canvas, map_field_matched, matched_view_field, render_orientation,
                              stroke_field)
from tlvg_warp.losses.graphs import GraphedFn

ANGLE_TOL_DEG = 1.0  # Scharr's residual anisotropy bends 30°/60° stripes by ~0.14°; 1° is still tight
LIC_TOL_DEG = 5.0  # LIC streaks are noise averaged over 31 px: their own orientation is estimated, not exact
TWIN_TOL = 1e-5  # the OpenCV path is float32 (~1e-7 relative) and c, d are O(1)
SCORE_TOL = 0.02  # the whole image is scored: near its edges the padding bends both fields (~-0.993 measured)
BORDER = 16  # stripes end at the image edge; reflect-101 padding bends the field there


def stripes(deg, h=96, w=128, period=8.0):
    t = math.radians(deg)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    y = 0.5 + 0.4 * np.sin(2 * np.pi * (-xx * math.sin(t) + yy * math.cos(t)) / period)  # constant along t
    return np.repeat(y[..., None], 3, -1).astype(np.float32)


def ang_err_deg(theta, deg):
    d = (theta - math.radians(deg) + math.pi / 2) % math.pi - math.pi / 2  # orientation: mod 180°
    return np.degrees(np.abs(d))


@pytest.mark.parametrize("deg", [0, 30, 60, 90, 135, -20])
def test_stripes_direction_along_the_stripes(deg):
    th, c, d = stroke_field(stripes(deg))
    inner = (slice(BORDER, -BORDER),) * 2
    assert ang_err_deg(th[inner], deg).max() < ANGLE_TOL_DEG
    assert c[inner].min() > 0.99
    t = math.radians(deg)
    assert np.abs(d[inner] - c[inner][..., None] * np.array([math.cos(2 * t), math.sin(2 * t)])).max() < 0.02


def test_noise_has_low_coherence_and_flat_has_none():
    noise = np.random.default_rng(0).random((96, 128, 3)).astype(np.float32)
    assert stroke_field(noise)[1].mean() < 0.15  # ~0.07 measured; stripes give ~1
    _, c, d = stroke_field(np.full((32, 32, 3), 0.4, np.float32))
    assert c.max() < 1e-6 and np.abs(d).max() < 1e-6


def test_torch_twin_matches_opencv_and_is_differentiable():
    rng = np.random.default_rng(1)
    img = 0.6 * stripes(25, 64, 80) + 0.4 * rng.random((64, 80, 3)).astype(np.float32)
    img[:, :20] = 0.3  # a flat patch: gradients there must stay finite
    th, c, d = stroke_field(img)
    x = torch.from_numpy(img).double().requires_grad_(True)
    th2, c2, d2 = render_orientation(x)
    assert np.abs(c2.detach().numpy() - c).max() < TWIN_TOL
    assert np.abs(d2.detach().numpy() - d).max() < TWIN_TOL
    strong = c > 0.1  # θ is only defined where there is orientation
    assert np.abs(np.sin(th2.detach().numpy()[strong] - th[strong])).max() < 1e-3  # sin: θ ≡ θ ± π
    (d2.sum() + c2.sum()).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    tb = render_orientation(x.detach().permute(2, 0, 1).unsqueeze(0).repeat(2, 1, 1, 1))  # [B,3,H,W] layout
    assert tb[2].shape == (2, 64, 80, 2) and torch.allclose(tb[2][1], d2.detach())


def test_flow_alignment_score():
    for deg in (10, 45):
        img = stripes(deg)
        _, _, d = stroke_field(img)
        assert flow_alignment_score(img, d) == pytest.approx(1.0, abs=1e-6)
        _, _, d_rot = stroke_field(stripes(deg + 90))
        assert flow_alignment_score(img, d_rot) == pytest.approx(-1.0, abs=SCORE_TOL)
        assert flow_alignment_score_torch(torch.from_numpy(img).double(), torch.from_numpy(d_rot)).item() \
            == pytest.approx(flow_alignment_score(img, d_rot), abs=1e-4)
    _, _, d45 = stroke_field(stripes(45))
    assert abs(flow_alignment_score(stripes(0), d45)) < 0.05  # 45° apart: cos 90° = 0
    assert flow_alignment_score(np.full((40, 40, 3), 0.5, np.float32), d45[:40, :40]) == 0.0  # flat: no NaN


def test_canvas_mapping_of_constant_field_is_constant():
    t, c0 = math.radians(35), 0.8
    d = np.broadcast_to(c0 * np.array([math.cos(2 * t), math.sin(2 * t)], np.float32), (50, 70, 2)).copy()
    for H, W in [(30, 41), (120, 200)]:
        th, c, dd = map_field_canvas(d, H, W)
        assert th.shape == (H, W) and dd.shape == (H, W, 2)
        assert np.abs(th - t).max() < 1e-5 and np.abs(c - c0).max() < 1e-5
    th_t, _, _ = map_field_canvas(torch.from_numpy(d), 30, 41)
    assert isinstance(th_t, torch.Tensor) and float((th_t - t).abs().max()) < 1e-5


def test_matched_mapping_carries_the_matched_style_direction():
    # style cells: left half strokes at 0°, right half at 90°; render cells matched to one or the other
    ds = np.zeros((4, 6, 2), np.float32)
    ds[:, :3] = [1, 0]  # θ = 0
    ds[:, 3:] = [-1, 0]  # θ = 90°
    cells = field_at_cells(ds, (4, 6))  # [24, 2]
    assert cells.shape == (24, 2)
    hc, wc = 3, 5
    left = torch.tensor([0, 1, 6, 7, 12])  # style cells with θ = 0
    right = left + 3
    top = torch.arange(hc * wc) < 5  # first render row -> right (90°), the rest -> left (0°)
    idx = torch.where(top[:, None], right.expand(hc * wc, 5), left.expand(hc * wc, 5))
    w = torch.full((hc * wc, 5), 0.2)
    th, c, d = map_field_matched(cells, idx, w, 30, 50, cell_shape=(hc, wc))
    assert th.shape == (30, 50) and d.shape == (30, 50, 2)
    assert abs(abs(float(th[2, 25])) - math.pi / 2) < 1e-5 and abs(float(th[-3, 25])) < 1e-5
    assert float(c.min()) >= 0 and abs(float(c[-3, 25]) - 1) < 1e-5
    with pytest.raises(ValueError):
        map_field_matched(cells, idx, w, 30, 50, cell_shape=(4, 4))


def test_view_field_matches_luminance_features_at_the_scale_and_carries_their_directions():
    """matched_view_field: a stub network records what it sees and gives every cell of the top render row the
    features of the painting's 90° cells, the other rows the 0° cells' (each direction held by K_CROSS identical
    painting cells, so the top-k is unambiguous). Oracle: the field is 90° at the top, 0° at the bottom, and the
    network saw the view's luminance at the scale asked for."""
    hc, wc, k = 3, 5, 5
    style = torch.zeros(2, 2 * k)  # [C, Ns]: cells 0..k-1 point along channel 0 (0°), cells k..2k-1 along channel 1
    style[0, :k], style[1, k:] = 1.0, 1.0
    cells = torch.tensor([[1.0, 0.0]] * k + [[-1.0, 0.0]] * k)  # doubled angles: 0° and 90°
    seen = {}

    def net(x, scale):
        seen["x"], seen["scale"] = x, scale
        f = torch.zeros(1, 2, hc, wc)
        f[0, 1, 0], f[0, 0, 1:] = 1.0, 1.0  # top row like the 90° cells, the rest like the 0° cells
        return f

    img = torch.rand(30, 50, 3)
    d = matched_view_field(net, img, style, cells, 0.7)
    assert d.shape == (30, 50, 2) and seen["scale"] == 0.7
    assert torch.allclose(seen["x"], luminance(img))
    assert torch.allclose(d[2, 25], torch.tensor([-1.0, 0.0]), atol=1e-5)  # 90°
    assert torch.allclose(d[-3, 25], torch.tensor([1.0, 0.0]), atol=1e-5)  # 0°


def test_lic_picture_follows_theta():
    h, w, deg = 96, 128, 30
    th = np.full((h, w), math.radians(deg), np.float32)
    pic = field_picture(np.full((h, w, 3), 0.5, np.float32), th, np.ones((h, w), np.float32))
    assert pic.shape == (h, w, 3) and pic.dtype == np.float32 and pic.min() >= 0 and pic.max() <= 1
    assert pic.std() > 0.02  # it draws something
    th2, c2, _ = stroke_field(pic)
    inner = (slice(BORDER, -BORDER),) * 2
    assert np.median(ang_err_deg(th2[inner], deg)) < LIC_TOL_DEG
    assert np.median(c2[inner]) > 0.5
    # a painting of another size is resized under the field
    assert field_picture(np.random.default_rng(0).random((40, 50, 3)), th, np.ones((h, w))).shape == (h, w, 3)


def _score_inputs(h, w, gen, dev):
    img = torch.rand(h, w, 3, device=dev, generator=gen)
    field = torch.nn.functional.normalize(torch.randn(h, w, 2, device=dev, generator=gen), dim=-1)
    return img, field


def test_graphed_score_runs_eagerly_off_cuda():
    """On the CPU (and without a gradient) ``GraphedFn`` is the function itself: no graph is captured (a version
    that tried would fail here, where CUDA graphs do not exist) and the value and gradient are the eager ones."""
    gen = torch.Generator().manual_seed(0)
    img, field = _score_inputs(20, 24, gen, "cpu")
    graphed = GraphedFn(flow_alignment_score_torch)
    x = img.clone().requires_grad_(True)
    s = graphed(x, field)
    s.backward()
    y = img.clone().requires_grad_(True)
    flow_alignment_score_torch(y, field).backward()
    assert torch.equal(s.detach(), flow_alignment_score_torch(img, field)) and torch.equal(x.grad, y.grad)
    assert not graphed.graphs


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_graphed_score_matches_eager_on_cuda():
    """The orientation term as replayed CUDA graphs gives the eager score and image gradient for renders AND target
    fields that change between calls (a graph that kept its first field, or returned a stale gradient, fails), one
    graph per shape."""
    dev = torch.device("cuda")
    gen = torch.Generator(device=dev).manual_seed(0)
    graphed = GraphedFn(flow_alignment_score_torch)
    for h, w in ((40, 56), (40, 56), (40, 56), (32, 30)):
        img, field = _score_inputs(h, w, gen, dev)
        out = []
        for fn in (flow_alignment_score_torch, graphed):
            x = img.clone().requires_grad_(True)
            s = fn(x, field)
            (3.0 * s).backward()
            out.append((s.detach().clone(), x.grad))
        (s0, g0), (s1, g1) = out
        assert torch.allclose(s0, s1, rtol=1e-5, atol=1e-6)
        assert torch.allclose(g0, g1, rtol=1e-4, atol=1e-4 * g0.abs().max())
    assert len(graphed.graphs) == 2
