"""The stylize controls a user reaches for: --stroke-scale (the painting's working size relative to the view),
--strength (style against content) and --keep-colors (the scene's own colours), and the background rule (the
style terms see the render only where the un-stylized scene was). Oracles: closed forms of the sizes and
weights, the photos themselves, and a float64 blend; one in-process CLI run checks that the flags reach the run's
resolved config.yaml."""
import math

import pytest
import torch
import yaml

from _demo_helpers import StubFeatures, demo_stylize_inputs
from tlvg_warp.distributed import Dist
from tlvg_warp.stylize.config import config_from_dict
from tlvg_warp.stylize.pipeline import build_run, over_background, prepare

W, H, VIEWS = 32, 24, 3


@pytest.fixture(scope="module")
def demo():
    return demo_stylize_inputs(VIEWS, W, H, 8)[1]


def _cfg(**over):
    return config_from_dict({"iterations": 6, "device": "cpu", "background": [1.0, 1.0, 1.0], **over}).validate()


def _targets(inp, cfg):
    return prepare(inp, cfg, StubFeatures(), torch.device("cpu"), (1.0, 1.0, 1.0))


@pytest.mark.parametrize("vgg_scale", [0.5, 1.0])
def test_stroke_scale_sizes_the_painting_relative_to_the_view(demo, vgg_scale):
    """style_height 0: the painting's working height is stroke_scale x the view height as VGG sees it."""
    heights = {}
    for k in (1.0, 2.0, 3.0):
        tg = _targets(demo, _cfg(style_height=0, stroke_scale=k, vgg_scale=vgg_scale))
        heights[k] = tg.style_work.shape[0]
        assert heights[k] == max(16, round(H * vgg_scale * k))
    ph, pw = demo.style.shape[:2]  # the aspect ratio is kept
    assert tg.style_work.shape[1] == max(1, round(pw * heights[3.0] / ph))
    # a fixed style_height is scaled too, so --stroke-scale acts on every config
    assert _targets(demo, _cfg(style_height=40, stroke_scale=2.0)).style_work.shape[0] == 80


def test_strength_scales_the_style_terms_and_nothing_else(demo):
    from tlvg_warp.stylize.pipeline import Stylize

    base = {"loss.w_style_color": 0.5, "loss.w_style_coarse": 0.75, "loss.w_chroma_tv": 0.25, "loss.w_stroke": 0.3,
            "loss.w_detail": 0.2, "loss.w_orient": 0.6}
    w = {}
    for s in (1.0, 2.5):
        cfg = _cfg(**base, **{"loss.strength": s})
        tg = _targets(demo, cfg)
        w[s] = Stylize(10, cfg, tg, StubFeatures()).weights(3)
    for term, v in w[1.0].items():
        scaled = ("style", "style_color", "style_coarse", "stroke", "detail")
        want = v * 2.5 ** 3 if term in scaled else v  # strength cubed; the flow terms and the rest as set
        assert w[2.5][term] == pytest.approx(want, rel=1e-12), term
    assert w[1.0]["style"] == 2.0 and w[1.0]["style_color"] == 0.5  # the built-in weights, unscaled at 1
    assert w[1.0]["style_coarse"] == 0.75


def test_keep_colors_keeps_the_photos_colours(demo):
    cfg = _cfg(keep_colors=True, stroke_jitter_mode="palette", **{"loss.luminance_only": False,
                                                                 "loss.w_style_color": 1.0})
    assert cfg.loss.luminance_only and cfg.loss.w_style_color == 0  # the style may shape luminance only
    assert cfg.stroke_jitter_mode == "luminance"  # and the jitter tone only, not the painting's colours
    tg = _targets(demo, cfg)
    for rec, photo in zip(tg.recolored, demo.photos):  # pre-process and Lab targets: the photos themselves
        assert torch.equal(rec, photo.to(rec))
    m, t = tg.palette.m, tg.palette.t
    assert torch.equal(m, torch.eye(3, dtype=m.dtype)) and not t.any()
    run = build_run(demo, cfg, tg, StubFeatures(), torch.device("cpu"), Dist(), None)
    g0 = demo.gaussians.with_sh_degree(0)  # no palette applied to the starting colours either
    assert torch.equal(run.params.sh_dc.detach().reshape(-1, 3), g0.sh[:, 0].to(run.params.sh_dc).reshape(-1, 3))
    # without it, the targets are recoloured to the painting's palette
    tg_pal = _targets(demo, _cfg())
    assert max(float((a - b).abs().max()) for a, b in zip(tg_pal.recolored, demo.photos)) > 0.05


def test_tone_palette_recolours_the_targets_and_the_gaussians(demo):
    """palette_map tone: the targets and the starting Gaussians take the tone map (not ARF's), and every view's
    uncovered background stays the photo's."""
    from tlvg_warp.losses.palette import TonePalette

    cfg = _cfg(palette_map="tone")
    tg = _targets(demo, cfg)
    assert isinstance(tg.palette, TonePalette)
    # the map's photo statistics come from the covered pixels: it is the one tone_palette makes with the coverage
    from tlvg_warp.losses.palette import tone_palette

    photos = [p.to(torch.float32) for p in demo.photos]
    masked = tone_palette(photos, tg.style_work, coverage=tg.coverage)
    torch.testing.assert_close(tg.palette.knots, masked.knots)
    assert not torch.allclose(tone_palette(photos, tg.style_work).knots, masked.knots)  # the demo's background counts
    covered = 0
    for rec, photo, cov in zip(tg.recolored, demo.photos, tg.coverage):
        photo = photo.to(rec)
        want = cov * tg.palette.apply(photo) + (1 - cov) * photo  # the tone map where covered, the photo elsewhere
        torch.testing.assert_close(rec, want, atol=1e-5, rtol=0)
        covered += int((cov > 0.5).sum())
        assert float((rec - photo).abs()[cov[..., 0] > 0.99].max()) > 0.05  # and the map changes what is covered
    assert covered > 0
    run = build_run(demo, cfg, tg, StubFeatures(), torch.device("cpu"), Dist(), None)
    g0 = demo.gaussians.with_sh_degree(0)
    want_dc = tg.palette.recolor_sh(g0.sh.to(run.params.sh_dc))[:, 0]
    torch.testing.assert_close(run.params.sh_dc.detach().reshape(-1, 3), want_dc.reshape(-1, 3))


def test_palette_floor_reaches_the_transfer(demo):
    """palette_floor: the targets' ARF map is the one color_transfer makes with that floor, not the plain one."""
    from tlvg_warp.losses.color import color_transfer

    tg = _targets(demo, _cfg(palette_floor=0.004))
    photos = [p.to(torch.float32) for p in demo.photos]
    want = color_transfer(photos, tg.style_work, 0.004)[1]
    plain = color_transfer(photos, tg.style_work)[1]
    torch.testing.assert_close(tg.palette.m, want)
    assert float((want - plain).abs().max()) > 1e-4  # the floor changes the demo's map


def test_palette_where_covered_takes_the_statistics_under_the_scene(demo):
    """palette_where covered: the targets' ARF map is color_transfer's with the un-stylized alpha as weights; the
    demo's white background would otherwise move it; an unknown value is a config error."""
    from tlvg_warp.errors import InputError
    from tlvg_warp.losses.color import color_transfer

    tg = _targets(demo, _cfg(palette_floor=0.004, palette_where="covered"))
    photos = [p.to(torch.float32) for p in demo.photos]
    want = color_transfer(photos, tg.style_work, 0.004, tg.coverage)[1]
    pooled = color_transfer(photos, tg.style_work, 0.004)[1]
    torch.testing.assert_close(tg.palette.m, want)
    assert min(float(c.mean()) for c in tg.coverage) < 0.9  # the premise: the demo's views show background
    assert float((want - pooled).abs().max()) > 1e-3
    with pytest.raises(InputError, match="palette_where"):
        _cfg(palette_where="object")


def test_palette_smooth_and_focus_reach_the_targets_map(demo):
    """palette_smooth and palette_focus go from the config to the targets' sliced map: its table is sliced_palette's
    with the same widths over the covered pixels, and the focus changes it (the demo's map)."""
    from tlvg_warp.losses.palette import sliced_palette

    base = {"palette_map": "sliced", "palette_where": "covered", "palette_smooth": 0.05}
    plain, focused = (_targets(demo, _cfg(**base, palette_focus=f)) for f in (0.0, 0.2))
    photos = [p.to(torch.float32) for p in demo.photos]
    want = sliced_palette(photos, focused.style_work, focused.coverage, smooth=0.05, focus=0.2).lut
    torch.testing.assert_close(focused.palette.lut, want)
    assert float((focused.palette.lut - plain.palette.lut).abs().max()) > 1e-3


def test_over_background_blends_by_the_unstylized_alpha():
    torch.manual_seed(0)
    img = torch.rand(5, 7, 3, dtype=torch.float64)
    cov = torch.rand(5, 7, 1, dtype=torch.float64)
    cov[0, 0], cov[0, 1] = 1.0, 0.0
    bg = (0.2, 0.4, 0.9)
    out = over_background(img, cov, bg)
    want = cov * img + (1 - cov) * torch.tensor(bg, dtype=torch.float64)
    assert torch.allclose(out, want, atol=1e-15)
    assert torch.equal(out[0, 0], img[0, 0]) and torch.allclose(out[0, 1], torch.tensor(bg, dtype=torch.float64))
    photo = torch.rand(5, 7, 3, dtype=torch.float64)  # an image as the background (the recoloured targets)
    assert torch.allclose(over_background(img, cov, photo), cov * img + (1 - cov) * photo, atol=1e-15)


def test_recoloured_targets_keep_the_empty_background(demo):
    """Where the un-stylized scene leaves the view empty, the pre-process target is the photo's background, not
    the painting's palette (a recoloured white background would make the fit grow splats to paint it)."""
    from tlvg_warp import render
    from tlvg_warp.losses import color_transfer

    tg = _targets(demo, _cfg())
    palette = color_transfer([p.float() for p in demo.photos], tg.style_work)[0]  # the whole-image transfer
    for i, (rec, photo) in enumerate(zip(tg.recolored, demo.photos)):
        with torch.no_grad():
            cov = render(demo.gaussians, demo.cameras[i], (1.0, 1.0, 1.0)).alpha.clamp(0, 1).double()[..., None]
        want = cov * palette[i].double() + (1 - cov) * photo.double()
        assert torch.allclose(rec.double(), want, atol=1e-5)
        empty = cov[..., 0] < 1e-6
        assert empty.any() and torch.allclose(rec[empty].double(), photo.double()[empty], atol=1e-6)
        assert float((rec.double() - photo.double()).abs().max()) > 0.05  # covered pixels do change


def test_flags_reach_the_resolved_config(tmp_path):
    from tlvg_warp import cli

    out = tmp_path / "run"
    rc = cli.main(["stylize", "--out", str(out), "--iterations", "1", "--downscale", "4", "--vgg-weights", "random",
                   "--quiet", "--strength", "0.5", "--stroke-scale", "3", "--keep-colors", "--set", "web_formats=false",
                   "--set", "orbit_frames=2"])
    assert rc == 0
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["stroke_scale"] == 3.0 and cfg["keep_colors"] is True and cfg["loss"]["strength"] == 0.5
    assert cfg["loss"]["luminance_only"] is True and math.isclose(cfg["loss"]["w_style_color"], 0.0)


def test_keep_colors_keeps_the_renders_colours_on_a_real_run(demo):
    """A short real stylization (random VGG: colour is what is measured, not style): with --keep-colors the renders'
    mean Lab chroma stays at the photos'; without it, the palette transfer moves it toward the painting's.
    Oracle: OpenCV's Lab conversion of the written renders and of the photos."""
    import cv2
    import numpy as np

    from tlvg_warp.losses import load_vgg
    from tlvg_warp.stylize import run_stylize

    vgg = load_vgg("random")

    def ab_mean(img):
        lab = cv2.cvtColor(np.clip(np.asarray(img, np.float32), 0, 1), cv2.COLOR_RGB2Lab)
        return lab[..., 1:].reshape(-1, 2).mean(0)

    photos_ab = np.mean([ab_mean(p.numpy()) for p in demo.photos], 0)
    painting_ab = ab_mean(demo.style.numpy())
    shift = {}
    for keep in (False, True):
        cfg = _cfg(iterations=24, vgg_weights="random", keep_colors=keep, style_height=0)
        res = run_stylize(demo, cfg, None, progress=False, quiet=True, vgg=vgg)
        from tlvg_warp import render

        with torch.no_grad():
            ab = np.mean([ab_mean(render(res.gaussians, c, (1.0, 1.0, 1.0)).color.numpy()) for c in demo.cameras], 0)
        shift[keep] = float(np.linalg.norm(ab - photos_ab))
    gap = float(np.linalg.norm(painting_ab - photos_ab))
    assert gap > 5  # the painting's palette is far from the photos' (Lab units)
    assert shift[True] < 0.25 * shift[False] and shift[False] > 0.2 * gap, (shift, gap)


def test_gram_term_is_logged_and_switched_by_its_weight():
    """loss.w_style_gram adds the Gram texture term to the stylize loss; at 0 it is not computed at all."""
    import math

    from tlvg_warp.stylize.config import StylizeConfig
    from tlvg_warp.stylize.pipeline import StylizeInputs, run_stylize
    from tlvg_warp.types import Camera, Gaussians
    from tlvg_warp.renderer import render

    gen = torch.Generator().manual_seed(0)
    g = Gaussians.from_colors((torch.rand(60, 3, generator=gen) - 0.5), torch.rand(60, 3, generator=gen), 0.08,
                              opacity=0.8)
    cams = [Camera.look_at((0.2 * k, -3.0, 0.1), (0, 0, 0), width=40, height=32, fov_deg=50.0) for k in (0, 1)]
    photos = [render(g, c).color.detach().clamp(0, 1) for c in cams]
    style = torch.rand(32, 32, 3, generator=gen)
    seen = {}
    for w in (0.0, 2.0):
        cfg = StylizeConfig(iterations=3, phases=[0, 3, 0], vgg_weights="random", device="cpu", web_formats=False,
                            orbit_frames=0, comparison_views=0)
        cfg.loss.w_style_gram = w
        res = run_stylize(StylizeInputs(g, cams, ["a", "b"], photos, style), cfg, None, progress=False, quiet=True)
        seen[w] = [r.get("style_gram") for r in res.log if r.get("phase") == "stylize"]
    assert all(v in (None, 0, 0.0) for v in seen[0.0])
    vals = [v for v in seen[2.0] if v is not None]
    assert vals and all(math.isfinite(v) and v > 0 for v in vals)


@pytest.mark.parametrize("name,alpha,loss,grad", [
    # only alpha below the un-stylized scene's costs; covering more is free
    ("coverage_loss", [[0.25, 1.0], [1.0, 0.5]], 0.75 / 4, [[-0.25, 0.0], [0.0, 0.0]]),
    # the mirror: only alpha above the un-stylized scene's costs
    ("silhouette_loss", [[0.25, 1.0], [1.0, 0.75]], 1.25 / 4, [[0.0, 0.0], [0.25, 0.25]]),
])
def test_alpha_hinges_against_the_unstylized_coverage(name, alpha, loss, grad):
    """The coverage and silhouette hinges: closed forms on a known pattern, values and gradients."""
    from tlvg_warp.stylize import pipeline

    cov = torch.tensor([[1.0, 1.0], [0.0, 0.5]])[..., None]
    a = torch.tensor(alpha, requires_grad=True)
    out = getattr(pipeline, name)(a, cov)
    assert float(out) == pytest.approx(loss)
    out.backward()
    assert a.grad.tolist() == grad


def test_silhouette_on_empty_pixels_counts_the_outline_alone():
    """silhouette_where "empty": only pixels the un-stylized scene leaves uncovered (alpha under 0.5) cost; a
    covered pixel whose alpha ends above its soft coverage is free, and where nothing is empty the term is 0."""
    from tlvg_warp.stylize.pipeline import silhouette_loss

    cov = torch.tensor([[0.97, 0.0], [0.4, 0.6]])[..., None]
    a = torch.tensor([[1.0, 0.5], [0.9, 0.7]], requires_grad=True)
    out = silhouette_loss(a, cov, "empty")  # (0.5 - 0) + (0.9 - 0.4) over 4 pixels; (0,0) and (1,1) are covered
    assert float(out) == pytest.approx(1.0 / 4)
    out.backward()
    assert a.grad.tolist() == [[0.0, 0.25], [0.25, 0.0]]
    assert float(silhouette_loss(a.detach(), cov, "all")) == pytest.approx((0.03 + 0.5 + 0.5 + 0.1) / 4)
    full = torch.full((3, 3, 1), 0.9)
    assert float(silhouette_loss(torch.ones(3, 3), full, "empty")) == 0.0  # a capture: covered everywhere


@pytest.mark.parametrize("source", ["stylize_start", "unstylized"])
def test_field_source_picks_the_render_the_field_is_matched_on(demo, monkeypatch, source):
    """loss.field_source: the painting's field is matched on the un-stylized scene's render of each view (the targets'
    originals) or on the render of the Gaussians as they are when stylize starts. With the splats darkened before
    the fields are made, the two differ, and each view's match sees the one asked for (a version that ignored the
    key, or matched view i on another view's render, fails)."""
    import tlvg_warp.losses as L
    from tlvg_warp.renderer import render

    seen, real = [], L.matched_view_field

    def recording(vgg, img, *a):
        seen.append(img.detach().clone())
        return real(vgg, img, *a)
    monkeypatch.setattr(L, "matched_view_field", recording)
    cfg = _cfg(**{"loss.field_source": source})
    tg = _targets(demo, cfg)
    run = build_run(demo, cfg, tg, StubFeatures(), torch.device("cpu"), Dist(), None)
    with torch.no_grad():
        run.params.sh_dc.mul_(0.25)
    fields = run.phase("stylize").make_fields(run)
    assert len(fields) == len(seen) == VIEWS
    g = run.params.gaussians()
    for i, cam in enumerate(run.cams):
        now = render(g, cam, run.background).color
        want = tg.originals[i] if source == "unstylized" else now
        other = now if source == "unstylized" else tg.originals[i]
        torch.testing.assert_close(seen[i], want.to(seen[i]))
        assert float((seen[i] - other.to(seen[i])).abs().max()) > 0.05


def test_the_fields_match_every_view_against_one_set_of_painting_columns(demo, monkeypatch):
    """make_fields normalizes the painting's features once for all views (they are the same painting), not once per
    view: each view's match is handed the same StyleFeatures, whose unit columns are built on its first use; the
    fields equal those of a match against the plain tensor (a version that rebuilt them per view, or matched a
    stale set, fails)."""
    import tlvg_warp.losses as L
    from tlvg_warp.losses import style as style_mod

    handed, real = [], L.matched_view_field

    def recording(vgg, img, painting, *a):
        handed.append(painting)
        return real(vgg, img, painting, *a)
    monkeypatch.setattr(L, "matched_view_field", recording)
    builds = []
    real_unit = style_mod._unit
    monkeypatch.setattr(style_mod, "_unit", lambda f: builds.append(f.shape) or real_unit(f))
    cfg = _cfg()
    tg = _targets(demo, cfg)
    run = build_run(demo, cfg, tg, StubFeatures(), torch.device("cpu"), Dist(), None)
    builds.clear()
    fields = run.phase("stylize").make_fields(run)
    ns = tg.match_feats.shape[1]
    assert len(handed) == VIEWS and all(p is handed[0] for p in handed)
    assert sum(1 for s in builds if s[1] == ns) == 1  # the painting's columns once; the views' own once each
    from tlvg_warp.stylize.pipeline import flow_field_tensor
    for i, f in enumerate(fields):  # the same fields as a match against the plain tensor, view by view
        src = tg.originals[i] if cfg.loss.field_source == "unstylized" else None
        if src is None:
            from tlvg_warp.renderer import render
            src = render(run.params.gaussians(), run.cams[i], run.background).color
        plain = real(StubFeatures(), src, tg.match_feats, tg.style_doubled_cells, cfg.vgg_scale)
        torch.testing.assert_close(f, flow_field_tensor(plain.float()))
