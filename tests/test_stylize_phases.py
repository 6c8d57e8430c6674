"""What each phase of the stylization does (SPEC §3), on the tiny demo with a random VGG:
- the tangential hook acts in the Stylize phase only: with it on (λ=1) or off (λ=0) a pre-process-only run
  ends with bit-identical parameters (plain Adam), a stylize-only run does not;
- geometry.max_travel bounds each splat's path over the stylize phase by that many of its own footprint widths;
- the content term is RGB whatever the style term's input: tlvg.yaml and its RGB-loss ablation, on the same
  first stylize step (same Gaussians, same view), log the same content value and different style values, and
  carry the same stroke fields. Oracle for the content value: content_loss on RGB features computed here."""
from pathlib import Path

import pytest
import torch

from _demo_helpers import demo_stylize_inputs
from tlvg_warp.stylize import load_config, run_stylize

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
W, H, VIEWS, SUBSAMPLE = 48, 36, 4, 4


@pytest.fixture(scope="module")
def inputs():
    return demo_stylize_inputs(VIEWS, W, H, SUBSAMPLE)[1]


_VGG = []


def _run(inputs, name="tlvg.yaml", *over):
    from tlvg_warp.losses import load_vgg

    if not _VGG:
        _VGG.append(load_vgg("random"))
    cfg = load_config(CONFIGS / name, ["device=cpu", "vgg_weights=random", "log_every=1", *over])
    return run_stylize(inputs, cfg, None, progress=False, quiet=True, vgg=_VGG[0])


@pytest.mark.parametrize("phases, hook_acts", [("[4, 0, 0]", False), ("[0, 0, 4]", False), ("[0, 4, 0]", True)])
def test_tangential_hook_acts_in_stylize_only(inputs, phases, hook_acts):
    on = _run(inputs, "tlvg.yaml", "iterations=4", f"phases={phases}", "geometry.tangential_lambda=1.0")
    off = _run(inputs, "tlvg.yaml", "iterations=4", f"phases={phases}", "geometry.tangential_lambda=0.0")
    same = torch.equal(on.gaussians.means, off.gaussians.means)
    assert same != hook_acts
    if phases == "[4, 0, 0]":  # positions did move in the pre-process, as plain Adam moves them
        assert not torch.equal(on.gaussians.means, inputs.gaussians.means)
        for f in on.gaussians.FIELDS:
            assert torch.equal(getattr(on.gaussians, f), getattr(off.gaussians, f)), f


def test_content_is_alike_and_rgb_ablation_changes_only_the_style_term(inputs):
    lum = _run(inputs, "tlvg.yaml", "iterations=1", "phases=[0, 1, 0]")
    rgb = _run(inputs, "ablation_rgb_loss.yaml", "iterations=1", "phases=[0, 1, 0]")
    a, b = lum.log[0], rgb.log[0]
    assert a["view"] == b["view"]
    assert a["content"] == pytest.approx(b["content"], rel=1e-6) and b["content"] > 0  # luminance content in both
    assert a["style"] != b["style"]  # the style term's input differs
    # the paper's colour preservation is the luminance style loss with the Lab statistics: the ablation drops the
    # Lab term and changes nothing else (neither has a second, RGB colour style term)
    assert b["lab"] == 0 < a["lab"] and a["style_color"] == b["style_color"] == 0
    for t in ("depth", "tv", "chroma_tv", "align", "aniso", "opacity_reg", "scale_reg"):
        assert a[t] == b[t], t
    for fa, fb in zip(lum.fields, rgb.fields):  # the stroke-field match is the same
        assert torch.equal(fa, fb)


def test_post_process_freezes_geometry(inputs):
    """The post-process fits colours and rotations only: positions, scales and opacities keep their values."""
    r = _run(inputs, "tlvg.yaml", "iterations=4", "phases=[0, 0, 4]", "palette_init=false")
    g0 = inputs.gaussians
    for f in ("means", "log_scales", "opacity_logits"):
        assert torch.equal(getattr(r.gaussians, f), getattr(g0, f)), f
    assert r.gaussians.num == g0.num
    assert not torch.equal(r.gaussians.sh, g0.sh) and not torch.equal(r.gaussians.quats, g0.quats)


def test_divergence_restores_the_last_good_state_and_resumes(inputs, tmp_path, monkeypatch):
    """A NaN loss mid-stylize: the run stops with StylizeDiverged, its checkpoint holds the last good state (the
    run state's one state_dict, restored), and --resume from it finishes."""
    import math

    from tlvg_warp.stylize import load_checkpoint, pipeline

    calls = []
    real_tv = pipeline.tv_loss

    def poisoned(img):
        calls.append(1)
        v = real_tv(img)
        return v * float("nan") if len(calls) == 3 else v

    monkeypatch.setattr(pipeline, "tv_loss", poisoned)
    out = tmp_path / "run"
    with pytest.raises(pipeline.StylizeDiverged, match="iteration 5"):
        _run_out(inputs, out)
    ck = load_checkpoint(out)
    assert ck["iteration"] == 4 and len(ck["log"]) == 4  # steps 1-2 pre, 3-4 stylize: the last good ones
    assert all(torch.isfinite(t).all() for t in ck["params"]["tensors"].values())
    monkeypatch.setattr(pipeline, "tv_loss", real_tv)
    res = _run_out(inputs, out, resume=out)
    assert res.metrics["resumed_from"] == 4 and [r["step"] for r in res.log] == list(range(1, 9))
    assert all(math.isfinite(r["loss"]) for r in res.log)


def _run_out(inputs, out, resume=None):
    cfg = load_config(CONFIGS / "tlvg.yaml", ["device=cpu", "vgg_weights=random", "log_every=1", "iterations=8",
                                              "phases=[2, 4, 2]"])
    return run_stylize(inputs, cfg, out, progress=False, quiet=True, vgg=_VGG[0] if _VGG else None, resume=resume)


def test_max_travel_bounds_each_splats_path_in_its_own_widths(inputs):
    """geometry.max_travel T over N stylize steps: each step at most T/N of the splat's footprint width (its middle
    scale), so with the scales held (lr.scales 0) no splat ends more than T widths from where stylize began (the
    triangle inequality over the steps). Without the limit the same run moves some splat further: the bound bites.
    Catches the cap not wired into the run's hook, a per-step cap not divided by the steps, a width that is not the
    splat's own. Density control and the stroke-size refinement are off so each splat keeps its row."""
    travel, steps = 0.3, 4
    common = ["iterations=4", f"phases=[0, {steps}, 0]", "density.phases=[]", "refine_radius=0", "lr.scales=0",
              "lr.means=0.05"]  # a large step, so that unlimited splats do travel further than 0.3 widths
    capped = _run(inputs, "tlvg.yaml", *common, f"geometry.max_travel={travel}")
    free = _run(inputs, "tlvg.yaml", *common, "geometry.max_travel=0")
    g0 = inputs.gaussians
    width = g0.log_scales.double().exp().median(dim=-1).values  # [N] the middle scale, as the hook takes it
    moved = lambda res: (res.gaussians.means.double() - g0.means.double()).norm(dim=-1) / width  # [N] in widths
    assert capped.gaussians.num == free.gaussians.num == g0.num
    assert torch.equal(capped.gaussians.log_scales, g0.log_scales)  # the widths did hold still
    assert float(moved(capped).max()) <= travel * (1 + 1e-3)  # float32 positions: a few ulps of |μ| per step
    assert float(moved(free).max()) > 2 * travel


def test_gray_luminance_gradient_changes_the_steps_not_the_losses(inputs):
    """loss.luminance_grad gray feeds the luminance-only terms the same image with its gradient along the grey axis:
    the first step's logged terms equal the luma run's (the same forward), the Gaussians after two steps do not (the
    option reaches the terms). Catches the option not wired, or wired into the value instead of the gradient."""
    common = ["iterations=2", "phases=[0, 2, 0]"]
    luma = _run(inputs, "tlvg.yaml", *common, "loss.luminance_grad=luma")
    gray = _run(inputs, "tlvg.yaml", *common, "loss.luminance_grad=gray")
    for t in ("style", "content", "stroke", "orient", "lab", "chroma_tv"):
        assert luma.log[0][t] == gray.log[0][t], t
    assert not torch.equal(luma.gaussians.sh, gray.gaussians.sh)


def test_colour_floor_keeps_every_channel_at_or_above_zero_in_every_phase(inputs):
    """colour_floor lifts SH-0 colours below 0 after each step of every phase: a run that pushes channels under 0
    without it (the oracle: SH_C0·dc + 0.5 of its result) ends with none under 0 with it. Catches the hook
    unwired, wired in one phase only, or flooring the coefficient at 0 instead of the colour."""
    from tlvg_warp.types import SH_C0

    common = ["iterations=9", "phases=[3, 3, 3]", "lr.sh_dc=0.2"]  # large colour steps: channels leave [0, 1]
    free = _run(inputs, "tlvg.yaml", *common, "colour_floor=false")
    floored = _run(inputs, "tlvg.yaml", *common, "colour_floor=true")
    colour = lambda r: SH_C0 * r.gaussians.sh[:, 0] + 0.5  # noqa: E731  [N,3]
    assert float(colour(free).min()) < -0.05  # the run does push channels under 0
    assert float(colour(floored).min()) >= 0.0
    assert float((colour(floored) < 1e-4).float().mean()) > 0  # ... and some sit on the floor
