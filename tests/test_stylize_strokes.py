"""The two stroke settings of the Stylize phase:
- ``stroke_jitter``: one luminance offset per Gaussian, the same on R, G and B (oracle: the DC colour formula
  c = 0.5 + SH_C0 * dc in float64; chroma = RGB minus luminance must not move), drawn at the phase's start;
- ``loss.w_orient``: 1 - the render's own alignment with the stroke field; descending it must raise the
  alignment that the OpenCV implementation (``flow_alignment_score``, written apart from the torch twin) measures."""
from pathlib import Path

import numpy as np
import pytest
import torch

from _demo_helpers import demo_stylize_inputs
from tlvg_warp.losses import flow_alignment_score, flow_alignment_score_torch
from tlvg_warp.stylize.pipeline import jitter_luminance_, jitter_palette_
from tlvg_warp.types import SH_C0

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
LUMA = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)


def test_jitter_moves_luminance_by_the_offsets_and_keeps_chroma():
    n, amp = 20000, 0.07
    dc = torch.randn(n, 1, 3, dtype=torch.float32) * 0.5
    before = 0.5 + SH_C0 * dc.double()[:, 0]  # [N,3] colours
    moved = dc.clone()
    delta = jitter_luminance_(moved, amp, seed=3)  # [N]
    after = 0.5 + SH_C0 * moved.double()[:, 0]
    assert torch.allclose((after - before) @ LUMA, delta, atol=1e-6)  # luminance moves by the offset
    chroma = lambda c: c - (c @ LUMA)[:, None]  # noqa: E731
    assert torch.allclose(chroma(after), chroma(before), atol=1e-6)  # chroma does not
    assert abs(float(delta.std()) / amp - 1) < 0.03 and abs(float(delta.mean())) < 3 * amp / n ** 0.5
    again = dc.clone()
    assert torch.equal(jitter_luminance_(again, amp, seed=3), delta) and torch.equal(again, moved)  # seeded
    assert not torch.equal(jitter_luminance_(dc.clone(), amp, seed=4), delta)


def test_palette_jitter_moves_each_colour_by_a_painting_pixel_minus_its_mean():
    """Oracle: every offset / amount + the painting's mean colour is one of the painting's pixels (float64), and the
    colours move by exactly the offsets."""
    painting = torch.tensor([[[0.1, 0.2, 0.9], [0.9, 0.8, 0.1]], [[0.5, 0.5, 0.5], [0.0, 0.0, 0.0]]])
    dc = torch.zeros(500, 1, 3)
    delta = jitter_palette_(dc, painting, 0.5, seed=1)  # [N,3]
    px = painting.reshape(-1, 3).double()
    picked = delta / 0.5 + px.mean(0)
    assert torch.cdist(picked, px).min(1).values.max() < 1e-9  # each a painting pixel
    assert len({tuple(r) for r in picked.round(decimals=6).tolist()}) == 4  # all four drawn
    assert torch.allclose(dc.double()[:, 0] * SH_C0, delta, atol=1e-6)


def test_palette_tone_jitter_draws_from_the_splats_own_tone_band():
    """Oracle (float64, numpy, written apart): the painting's pixels sorted by luminance and cut into bands of equal
    count; each offset / amount + its band's mean must be a pixel of the band that holds the splat's luminance. A
    painting of dark blues and bright yellows and whites: bright splats take yellow or white offsets only, so their
    luminance moves far less than under the global palette jitter, which also draws the dark blues."""
    from tlvg_warp.stylize.pipeline import jitter_palette_tone_

    rng = np.random.default_rng(0)
    dark = np.array([[0.05, 0.1, 0.4], [0.1, 0.15, 0.3]])
    bright = np.array([[0.95, 0.85, 0.2], [0.95, 0.95, 0.95]])
    px = np.concatenate([dark[rng.integers(0, 2, 300)], bright[rng.integers(0, 2, 300)]])  # [600,3]
    px += rng.normal(0, 0.01, px.shape)
    painting = torch.from_numpy(px.reshape(20, 30, 3)).float()
    colours = rng.uniform(0, 1, (4000, 3))  # [N,3] the splats' colours before
    dc = torch.from_numpy((colours - 0.5) / SH_C0).float()[:, None, :]  # [N,1,3]
    before = 0.5 + SH_C0 * dc.double()[:, 0].numpy()
    delta = jitter_palette_tone_(dc, painting, 0.5, seed=2, bins=4).numpy()  # [N,3]
    assert np.allclose(0.5 + SH_C0 * dc.double()[:, 0].numpy() - before, delta, atol=1e-6)  # moved by the offsets

    p64 = painting.double().reshape(-1, 3).numpy()
    lum = p64 @ LUMA.numpy()
    srt = p64[np.argsort(lum, kind="stable")]
    bands = np.array_split(srt, 4)  # 150 pixels each
    for i in range(0, 4000, 97):
        y = before[i] @ LUMA.numpy()
        b = int(np.searchsorted(np.array([bands[k][0] @ LUMA.numpy() for k in range(1, 4)]), y, side="right"))
        picked = delta[i] / 0.5 + bands[b].mean(0)
        assert np.abs(bands[b] - picked).sum(1).min() < 1e-6, (i, b)  # a pixel of the splat's own band
    bright_splat = before @ LUMA.numpy() > 0.7
    tone = (delta @ LUMA.numpy())[bright_splat]
    global_tone = (jitter_palette_(dc.clone(), painting, 0.5, seed=2).numpy() @ LUMA.numpy())[bright_splat]
    assert bright_splat.sum() > 100 and tone.std() < 0.15 * global_tone.std()


def test_stylize_jitters_luminance_at_the_phase_start():
    """With the colour learning rate at 0, the DC colours a run ends with differ from the same run without jitter by
    the offsets alone: equal on R, G, B, nonzero for every Gaussian, and absent when the jitter is off. (That it is
    drawn once, not again on resume: tests/test_loop_resume.py.)"""
    from tlvg_warp.losses import load_vgg
    from tlvg_warp.stylize import load_config, run_stylize

    inp = demo_stylize_inputs(3, 48, 36, 4)[1]
    vgg = load_vgg("random")
    over = ["device=cpu", "vgg_weights=random", "iterations=2", "phases=[0, 2, 0]", "lr.sh_dc=0",
            "density.phases=[]", "palette_init=false", "colour_floor=false"]  # the floor would clip offsets under 0
    runs = {j: run_stylize(inp, load_config(CONFIGS / "tlvg.yaml", [*over, f"stroke_jitter={j}"]), None,
                           progress=False, quiet=True, vgg=vgg) for j in (0, 1)}
    d = (runs[1].gaussians.sh[:, 0] - runs[0].gaussians.sh[:, 0]).double() * SH_C0  # [N,3] colour change
    assert torch.allclose(d[:, 0], d[:, 1], atol=1e-6) and torch.allclose(d[:, 0], d[:, 2], atol=1e-6)
    assert (d[:, 0].abs() > 0).all()
    assert torch.equal(runs[0].gaussians.sh[:, 0], inp.gaussians.sh[:, 0])  # lr 0, no jitter: untouched


def test_stylize_applies_the_palette_tone_jitter_it_is_set_to(monkeypatch):
    """``stroke_jitter_mode=palette_tone`` reaches the run: with the colour learning rate at 0 the DC colours a run
    ends with differ from its input by exactly the offsets ``jitter_palette_tone_`` returned (that function's own
    oracle is the test above), drawn once, and they are colours, not one tone on R, G and B."""
    import tlvg_warp.stylize.pipeline as pipeline
    from tlvg_warp.losses import load_vgg
    from tlvg_warp.stylize import load_config, run_stylize

    drawn = []
    real = pipeline.jitter_palette_tone_
    monkeypatch.setattr(pipeline, "jitter_palette_tone_", lambda *a, **k: drawn.append(real(*a, **k)) or drawn[-1])
    inp = demo_stylize_inputs(3, 48, 36, 4)[1]
    over = ["device=cpu", "vgg_weights=random", "iterations=2", "phases=[0, 2, 0]", "lr.sh_dc=0",
            "density.phases=[]", "palette_init=false", "colour_floor=false", "stroke_jitter=1",
            "stroke_jitter_mode=palette_tone"]
    out = run_stylize(inp, load_config(CONFIGS / "tlvg.yaml", over), None, progress=False, quiet=True,
                      vgg=load_vgg("random"))
    assert len(drawn) == 1
    d = (out.gaussians.sh[:, 0] - inp.gaussians.sh[:, 0]).double() * SH_C0  # [N,3] colour change
    assert torch.allclose(d, drawn[0].to(d), atol=1e-5)
    assert (d[:, 0] - d[:, 2]).abs().max() > 1e-3  # a hue moved, not a grey tone


def test_orient_term_descends_to_the_field():
    """Gradient descent on 1 - score moves a noise image toward the field's direction (30 degrees) as OpenCV
    measures it; the torch score of the start equals OpenCV's."""
    rng = np.random.default_rng(0)
    img = rng.random((48, 64, 3))
    theta = np.deg2rad(30.0)
    field = np.zeros((48, 64, 2), np.float32)
    field[...] = (np.cos(2 * theta), np.sin(2 * theta))
    x = torch.tensor(img, dtype=torch.float64, requires_grad=True)
    t = torch.from_numpy(field).double()
    start = flow_alignment_score(img.astype(np.float32), field)
    assert float(flow_alignment_score_torch(x.detach(), t)) == pytest.approx(start, abs=1e-3)
    opt = torch.optim.Adam([x], lr=0.01)
    for _ in range(60):
        opt.zero_grad()
        loss = 1.0 - flow_alignment_score_torch(x, t)
        loss.backward()
        opt.step()
    end = flow_alignment_score(x.detach().numpy().astype(np.float32), field)
    assert start < 0.3 and end > 0.6, (start, end)


def test_lab_sigma_painting_reaches_the_lab_term_of_a_run():
    """``loss.lab_sigma=painting`` changes the Lab term a run optimizes: at the first stylize step (same seed, same
    render) its value exceeds the ``photo`` run's, whose targets are the recolored views' own spreads (the demo's
    recolored still life has less b-spread than The Starry Night). Catches the option parsed but not wired into
    the targets, or applied under keep_colors, whose targets are the scene's own colours."""
    from tlvg_warp.losses import load_vgg
    from tlvg_warp.stylize import load_config, run_stylize

    inp = demo_stylize_inputs(3, 48, 36, 4)[1]
    vgg = load_vgg("random")
    over = ["device=cpu", "vgg_weights=random", "iterations=1", "phases=[0, 1, 0]", "density.phases=[]",
            "loss.w_lab_start=1", "loss.w_lab_end=1"]
    lab = {s: run_stylize(inp, load_config(CONFIGS / "tlvg.yaml", [*over, f"loss.lab_sigma={s}"]), None,
                          progress=False, quiet=True, vgg=vgg).log[0]["lab"] for s in ("photo", "painting")}
    assert lab["painting"] > lab["photo"] + 1.0  # Lab units: the raised spread is far from the render's
    kept = {s: run_stylize(inp, load_config(CONFIGS / "tlvg.yaml", [*over, "keep_colors=true", f"loss.lab_sigma={s}"]),
                           None, progress=False, quiet=True, vgg=vgg).log[0]["lab"] for s in ("photo", "painting")}
    assert kept["painting"] == pytest.approx(kept["photo"], rel=1e-6)  # keep_colors: the scene's own spread
