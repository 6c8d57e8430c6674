"""The one training loop (tlvg_warp/train/loop.py) on tiny CPU cases:
- each phase's terms against oracles computed here, with a stub feature network (average pooling: its
  features are known in closed form) instead of VGG;
- views_per_step: the loss of a batched step is the mean of its views' losses (oracle: the photometric loss of
  each view rendered here), and a 1-rank run with 2 views per step equals a 2-rank run with 1 view per step
  (two threads joined by an in-process stand-in of torch.distributed, so the collectives are exercised);
- the performance rule: nothing in a step reads a tensor on the host (item, tolist, bool, float, cpu, nonzero)
  except where the schedule says (density control's steps) — the log and the non-finite check are read at
  the log flush only;
- the hook list of a phase acts in that phase only, and a phase's trainable groups are the only ones moving.
The SIGKILL + resume test is in tests/test_loop_resume.py."""
from __future__ import annotations

import math
import sys
import threading
from dataclasses import dataclass

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from tlvg_warp import render
from _demo_helpers import StubFeatures, demo_stylize_inputs
from tlvg_warp.stylize.config import config_from_dict as stylize_config
from tlvg_warp.losses import flow_alignment_score, painting_stroke_energies, resize_style
from tlvg_warp.losses.palette import painting_colours
from tlvg_warp.losses.sliced import random_directions
from tlvg_warp.stylize.pipeline import STYLIZE_TERMS, build_run, over_background, prepare
from tlvg_warp.train.density import DensityStrategy
from tlvg_warp.train.loop import Fit, LoopSettings, Phase, Run, View, train
from tlvg_warp.train.reconstruct import config_from_dict as fit_config
from tlvg_warp.train.reconstruct import fit_scene

W, H, VIEWS, SUBSAMPLE = 32, 24, 4, 8
TERM_TOL = 1e-5  # float32 terms against float64 oracles of the same quantities
BATCH_TOL = 2e-5  # 2 ranks x 1 view vs 1 rank x 2 views: the same sums in another order (float32)


@pytest.fixture(scope="module")
def demo():
    return demo_stylize_inputs(VIEWS, W, H, SUBSAMPLE)[1]


def _stylize_run(inp, net, **over):
    from tlvg_warp.distributed import Dist

    cfg = stylize_config({"iterations": 6, "device": "cpu", "style_height": 64, "vgg_scale": 1.0,
                          "background": list(inp.background), **over}).validate()
    tg = prepare(inp, cfg, net, torch.device("cpu"), inp.background)
    return build_run(inp, cfg, tg, net, torch.device("cpu"), Dist(), None), cfg, tg


def _view(run, vi):
    g = run.params.gaussians()
    cam = run.cams[vi]
    return View(vi, cam, run.background, render(g, cam, run.background, return_weights=True), g)


def _shown(demo, run, view) -> tuple:
    """(image, coverage) in float64: what the stylize terms see of ``view``'s render, the render over the run's
    background where the un-stylized scene (rendered here again) was empty ([H,W,3], [H,W,1])."""
    with torch.no_grad():
        ro0 = render(demo.gaussians, view.cam, run.background)
    cov = ro0.alpha.double().clamp(0, 1)[..., None]
    return cov * view.out.color.detach().double() + (1 - cov) * torch.tensor(run.background, dtype=torch.float64), cov


# --- each phase's terms ----------------------------------------------------------------------------------------
def test_stylize_terms_against_closed_forms(demo):
    net = StubFeatures()
    run, cfg, tg = _stylize_run(demo, net, **{"loss.w_style_color": 0.5, "loss.w_chroma_tv": 0.3,
                                              "loss.w_style_gram": 0.7, "loss.w_coverage": 0.9,
                                              "loss.w_silhouette": 0.6, "loss.w_detail": 0.4,
                                              "loss.w_orient": 0.5, "loss.w_stroke": 0.8,
                                              "loss.w_palette_snap": 0.35, "loss.w_style_swd": 0.45,
                                              "loss.w_color_swd": 0.55, "loss.swd_projections": 5,
                                              "loss.color_swd_projections": 4, "loss.w_style_coarse": 0.65,
                                              "loss.w_tone_hold": 0.45})
    sty = run.phase("stylize")
    sty.setup(run)
    with torch.no_grad():  # move the parameters off their anchors so the anchor terms are not trivial
        run.params.opacity_logits += 0.25
        run.params.log_scales -= 0.125
        run.params.opacity_logits[::2] -= 3.0  # half of the splats fade: the coverage hinge is not zero
    net.calls.clear()
    view = _view(run, 2)
    # the detail hinge's oracle: luminance high-pass energy by OpenCV's blur (13 taps, σ 2, reflected border), over
    # the pixels the un-stylized scene covered
    def hp_energy(lum, w=None):
        hp2 = (lum - cv2.GaussianBlur(lum, (13, 13), 2.0, borderType=cv2.BORDER_REFLECT_101)) ** 2
        return float(hp2.mean()) if w is None else float((hp2 * w).sum() / w.sum())

    cov2 = tg.coverage[2].double()
    shown = over_background(view.out.color.detach().double(), cov2, run.background).numpy()
    e_oracle = hp_energy(shown @ np.array([0.299, 0.587, 0.114]), cov2[..., 0].numpy())
    setup_target = sty.detail_target
    setup_stroke = sty.stroke_target
    # the stroke hinge's oracle: OpenCV's σ 1 blur and Scharr (float64, reflected border), the gradient projected on
    # the view's field direction and its normal, weighted by the field's coherence x the coverage
    fld = sty.fields[2][..., :2].double().numpy()
    th, c_f = 0.5 * np.arctan2(fld[..., 1], fld[..., 0]), np.linalg.norm(fld, axis=-1)
    lum = cv2.GaussianBlur(shown @ np.array([0.299, 0.587, 0.114]), (9, 9), 1.0, borderType=cv2.BORDER_REFLECT_101)
    gx = cv2.Scharr(lum, cv2.CV_64F, 1, 0, borderType=cv2.BORDER_REFLECT_101)
    gy = cv2.Scharr(lum, cv2.CV_64F, 0, 1, borderType=cv2.BORDER_REFLECT_101)
    wf = c_f * cov2[..., 0].numpy()
    e_across = float((wf * (gy * np.cos(th) - gx * np.sin(th)) ** 2).sum() / wf.sum())
    e_along = float((wf * (gx * np.cos(th) + gy * np.sin(th)) ** 2).sum() / wf.sum())
    sty.stroke_target = (3.0 * e_across, 0.5 * e_along)  # both halves active
    sty.field_terms = sty.make_field_terms()  # setup baked the painting's targets into the call
    stroke = (1 - 1 / 3.0) ** 2 + (2.0 - 1) ** 2
    # the demo's painting at 64 rows has less detail than the render (the hinge would be 0): a target of 2.5x the
    # OpenCV energy makes it active, and the term then equals (1 - E/(2.5 E_opencv))^2 only if its E is OpenCV's
    sty.detail_target = 2.5 * e_oracle
    terms = sty.terms(run, view)
    # every term, in the summation order, but the deep style term (not beside the coarse one: its own test below)
    assert tuple(terms) == tuple(t for t in STYLIZE_TERMS if t != "style_deep")
    with torch.no_grad():  # the terms see the render over the background where the un-stylized scene was empty
        ro0 = render(demo.gaussians, run.cams[2], run.background)
    cov = ro0.alpha.double().clamp(0, 1)[..., None]
    bgc = torch.tensor(run.background, dtype=torch.float64)
    img = cov * view.out.color.detach().double() + (1 - cov) * bgc
    # the style term saw luminance (R = G = B), the content term RGB, in one batch
    batch, coarse = net.calls  # [2,3,H,W], then the coarse style term's pass of the luminance alone [1,3,H,W]
    y = (img * torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)).sum(-1)
    assert torch.allclose(batch[0].double(), y.expand(3, -1, -1), atol=1e-6)
    assert torch.equal(coarse[0], batch[0])
    assert torch.allclose(batch[1].double(), img.permute(2, 0, 1), atol=1e-6)
    pool = lambda x: F.avg_pool2d(x.permute(2, 0, 1)[None], 4).reshape(3, -1)  # noqa: E731
    photo = demo.photos[2].double()
    content = ((pool(img) - pool(photo)) ** 2).mean()
    inv = lambda d: torch.where(d > 0, 1 / d.clamp_min(1e-6), torch.zeros_like(d))  # noqa: E731
    d0 = ro0.depth.double()
    depth = ((inv(view.out.depth.detach().double()) - inv(d0)) ** 2).mean()
    tv = ((img[1:] - img[:-1]) ** 2).mean() + ((img[:, 1:] - img[:, :-1]) ** 2).mean()
    n = run.params.num
    chroma = img - y[..., None]
    chroma_tv = ((chroma[1:] - chroma[:-1]) ** 2).mean() + ((chroma[:, 1:] - chroma[:, :-1]) ** 2).mean()
    # the snap term: every pixel against every painting colour, float64, the nearest's chroma distance, by coverage
    assert torch.equal(tg.colours.cpu(), painting_colours(tg.style_work, cfg.loss.palette_colours, cfg.seed))
    cols = tg.colours.double().cpu()
    near = cols[((img[:, :, None, :] - cols) ** 2).sum(-1).argmin(-1)]  # [H,W,3]
    dchroma = (img - near) - ((img - near) * torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)).sum(-1,
                                                                                                  keepdim=True)
    snap = ((dchroma ** 2).sum(-1) * cov[..., 0]).sum() / cov[..., 0].sum()
    a_y = pool(y[..., None].expand(-1, -1, 3))
    s_y = tg.style_feats.double()
    gram = (((a_y @ a_y.T) / a_y.shape[1] - (s_y @ s_y.T) / s_y.shape[1]) ** 2).mean()
    # the sliced Wasserstein terms: the covered cells' (4x4 blocks with mean coverage >= 0.5) luminance features and
    # the covered pixels' colours, each projected on the call's directions, sorted and met at the painting's
    # mid-rank quantiles, over the painting's mean per-dimension variance (numpy float64)
    def swd(x, y, seed, count):
        d = random_directions(x.shape[1], count, seed, "cpu").double().numpy()
        px, py = np.sort(x @ d, axis=0), np.sort(y @ d, axis=0)
        rows = np.floor((np.arange(len(px)) + 0.5) * len(py) / len(px)).astype(int)
        return ((px - py[rows]) ** 2).mean() / y.var(axis=0).mean()

    cov_np = cov[..., 0].numpy()
    cell_cov = cov_np[:H // 4 * 4, :W // 4 * 4].reshape(H // 4, 4, W // 4, 4).mean(axis=(1, 3)).reshape(-1)
    style_swd = swd(a_y.numpy().T[cell_cov >= 0.5], s_y.numpy().T, cfg.seed * 1_000_003, 5)
    color_swd = swd(img.numpy().reshape(-1, 3)[cov_np.reshape(-1) >= 0.5],
                    tg.style_work.double().numpy().reshape(-1, 3), (cfg.seed + 1) * 1_000_003, 4)
    assert 0 < (cell_cov >= 0.5).sum() < cell_cov.size  # the empty background is left out, something is kept
    hinge = (ro0.alpha.double().clamp(0, 1) - view.out.alpha.detach().double()).clamp_min(0).mean()
    assert float(hinge) > 1e-3
    grown = (view.out.alpha.detach().double() - ro0.alpha.double().clamp(0, 1)).clamp_min(0).mean()
    assert float(grown) > 1e-6  # the other half grew (+0.25): the silhouette hinge is not zero either
    # the target setup computed: the painting's energy at the views' height
    paint = resize_style(tg.style_work.numpy(), int(np.median([c.height for c in run.cams]))).astype(np.float64)
    e_star = hp_energy(paint @ np.array([0.299, 0.587, 0.114]))
    assert setup_target == pytest.approx(e_star, rel=1e-6)
    assert setup_stroke == pytest.approx(painting_stroke_energies(tg.style_work.numpy(), paint.shape[0]), rel=1e-12)
    e = hp_energy(y.numpy(), cov[..., 0].numpy())  # the test's own composite of the render
    detail = max(0.0, 1.0 - e / (2.5 * e_oracle)) ** 2
    assert detail > 0.1  # active
    # the tone hold: the covered mean luminance of the render against that of the view's recoloured photo
    luma = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    wc = cov[..., 0]
    tone = ((y * wc).sum() / wc.sum() - ((tg.recolored[2].double() @ luma) * wc).sum() / wc.sum()) ** 2
    assert float(tone) > 1e-6  # the render is off its target's tone here: the term is not trivially zero
    opac = torch.full((run.params.num,), 0.25 ** 2, dtype=torch.float64)
    opac[::2] = (0.25 - 3.0) ** 2
    want = {"style_swd": style_swd, "color_swd": color_swd, "content": content, "depth": depth, "tv": tv,
            "chroma_tv": chroma_tv, "palette": snap, "style_gram": gram, "tone_hold": tone,
            "detail": detail, "stroke": stroke, "coverage": hinge, "silhouette": grown, "opacity_reg": math.sqrt(float(opac.sum())), "scale_reg": math.sqrt(3 * n * 0.125 ** 2)}
    for k, v in want.items():
        assert float(terms[k].detach()) == pytest.approx(float(v), rel=TERM_TOL, abs=1e-9), k
    # the orientation term: 1 - the alignment OpenCV's structure tensor (float32) measures against the view's field
    orient = 1.0 - flow_alignment_score(img.numpy().astype(np.float32), sty.fields[2][..., :2].numpy())
    assert float(terms["orient"].detach()) == pytest.approx(orient, abs=2e-3)
    assert all(torch.isfinite(t) and t.requires_grad for t in terms.values())
    # the weight schedule: Lab linear over the phase, the others constant (Python floats: no tensor ops)
    w0, w_last = sty.weights(0), sty.weights(sty.steps - 1)
    assert (w0["lab"], w_last["lab"]) == pytest.approx((cfg.loss.w_lab_start, cfg.loss.w_lab_end), abs=1e-12)
    assert all(isinstance(v, float) for v in w0.values()) and w0["style"] == cfg.loss.w_style


def test_tone_hold_is_a_hinge_beyond_its_margin(demo):
    """loss.tone_margin: (|Ȳ − Ȳ_target| − m)² beyond the margin, 0 (and no gradient) within it; the drift measured
    here in float64 from the render over the background and the view's recoloured photo, both over the coverage."""
    luma = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    found = {}
    for margin in (0.0, None, 1.0, "mirrored"):  # None: half the measured drift; mirrored: the same, target moved
        m = 0.5 * abs(found[0.0][0]) if margin in (None, "mirrored") else margin
        run, cfg, tg = _stylize_run(demo, StubFeatures(), **{"loss.w_tone_hold": 1.0, "loss.tone_margin": m})
        sty = run.phase("stylize")
        sty.setup(run)
        view = _view(run, 1)
        img, cov = _shown(demo, run, view)
        wc = cov[..., 0]
        drift = float((((img @ luma) - tg.recolored[1].double() @ luma) * wc).sum() / wc.sum())
        if margin == "mirrored":  # the target as far on the other side: the render now darker than its target
            sty.tone_targets[1] = sty.tone_targets[1] + 2 * drift
            drift = -drift
        term = sty.terms(run, view)["tone_hold"]
        grad = torch.autograd.grad(term, view.out.color)[0]  # [H,W,3]: the pull on the render's colour
        found[margin] = (drift, m, term, grad)
    drift = found[0.0][0]
    assert abs(drift) > 0.02  # the demo's render is off its colour target's tone: the hinge has something to hold
    for margin, (d, m, term, _) in found.items():
        assert float(term.detach()) == pytest.approx(max(0.0, abs(d) - m) ** 2, rel=TERM_TOL, abs=1e-12), margin
    assert float(found[None][2].detach()) > 0 and float(found[1.0][2].detach()) == 0.0
    # beyond the margin the pull is back toward the target (a lighter render is pushed darker), within it none
    pull = float(found[None][3].sum())
    assert pull != 0 and math.copysign(1, pull) == math.copysign(1, drift)
    assert torch.count_nonzero(found[1.0][3]) == 0
    assert float(found["mirrored"][3].sum()) * pull < 0  # a darker render is pulled lighter


def test_tone_hold_per_cell_holds_each_cells_covered_mean(demo):
    """loss.tone_cells: the hinge per cell of a grid (rows x round(rows * W / H) columns, each pixel in the cell
    of its integer position), each cell's covered mean luminance against its recoloured photo's, weighted by the
    cell's covered fraction; checked against a float64 loop over the cells. A render that keeps the view's mean
    but swaps its light and dark masses passes the one-cell hold and not the per-cell one."""
    from tlvg_warp.stylize.pipeline import cell_tones, tone_hold_loss

    luma = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    rows = 3
    run, cfg, tg = _stylize_run(demo, StubFeatures(), **{"loss.w_tone_hold": 1.0, "loss.tone_margin": 0.01,
                                                        "loss.tone_cells": rows})
    sty = run.phase("stylize")
    sty.setup(run)
    view = _view(run, 1)
    img, cov = _shown(demo, run, view)
    h, w = cov.shape[:2]
    cols = max(1, round(rows * w / h))
    y, yt, wc = img @ luma, tg.recolored[1].double() @ luma, cov[..., 0]
    num = den = 0.0
    for i in range(rows):
        for j in range(cols):
            ri = [r for r in range(h) if r * rows // h == i]
            cj = [c for c in range(w) if c * cols // w == j]
            k = wc[ri][:, cj]
            if float(k.sum()) == 0:
                continue
            m, t = float((y[ri][:, cj] * k).sum() / k.sum()), float((yt[ri][:, cj] * k).sum() / k.sum())
            weight = float(k.sum()) / (len(ri) * len(cj))
            num += weight * max(0.0, abs(m - t) - 0.01) ** 2
            den += weight
    term = sty.terms(run, view)["tone_hold"]
    assert num > 0  # the demo's render is off its target somewhere: the hold has something to hold
    assert float(term.detach()) == pytest.approx(num / den, rel=TERM_TOL, abs=1e-12)
    assert term.requires_grad
    # light and dark masses swapped, the mean kept: one cell sees nothing, the grid sees the swap
    left = torch.zeros(8, 16, 1, dtype=torch.float64)  # 2 rows of cells: 2 x 4 cells of 4 x 4 pixels
    left[:, :8] = 0.8
    left[:, 8:] = 0.2
    swapped, full = left.flip(1), torch.ones(8, 16, 1, dtype=torch.float64)
    one = tone_hold_loss(swapped, full, cell_tones(left, full, 0)[0], 0.02, 0)
    grid = tone_hold_loss(swapped, full, cell_tones(left, full, 2)[0], 0.02, 2)
    assert float(one) == 0.0 and float(grid) == pytest.approx((0.6 - 0.02) ** 2)
    # more rows than the view has pixels: one pixel a cell, no empty cell (an empty one's weight would be 0/0)
    y = swapped.clone().requires_grad_(True)
    tones, weight = cell_tones(y, full, 100)
    assert tones.shape == (8, 16) and torch.equal(tones.detach(), swapped[..., 0]) and torch.all(weight == 1)
    loss = tone_hold_loss(y, full, cell_tones(left, full, 100)[0], 0.02, 100)
    assert float(loss.detach()) == pytest.approx((0.6 - 0.02) ** 2)
    assert torch.isfinite(torch.autograd.grad(loss, y)[0]).all()


class OctaveStub(StubFeatures):
    """The stub with a scale: average pooling over blocks of 4 / scale pixels, so features at half the scale are
    the image's 8x8 block means (a closed form for the coarse style term). ``scales`` keeps the scales asked for."""

    def __init__(self):
        super().__init__()
        self.scales = []

    def forward(self, img, scale=1.0):
        self.scales.append(scale)
        x = img.permute(2, 0, 1).unsqueeze(0) if img.dim() == 3 else img
        self.calls.append(x.detach())
        return F.avg_pool2d(x.float(), round(4 / scale))


def _blocks(img: np.ndarray, n: int) -> np.ndarray:
    """[H,W,3] -> [3, cells]: the means of its n x n blocks (rows, then columns; a partial block left out)."""
    h, w = img.shape[0] // n, img.shape[1] // n
    return img[:h * n, :w * n].reshape(h, n, w, n, 3).mean(axis=(1, 3)).reshape(-1, 3).T


def _nnfm(a: np.ndarray, s: np.ndarray) -> float:
    """ARF's NNFM by brute force: per render cell the smallest cosine distance to a painting cell, averaged."""
    an, sn = a / np.linalg.norm(a, axis=0), s / np.linalg.norm(s, axis=0)
    return float((1 - an.T @ sn).min(axis=1).mean())


def test_coarse_style_term_matches_both_at_half_the_working_size(demo):
    """loss.w_style_coarse: a second NNFM term between the render and the painting each at half the style term's
    working size (float64 oracle: 8x8 block means where the style term sees 4x4 ones), through the packed features
    of one terms call, with a gradient; the painting's coarse features are its own, not the fine ones again."""
    net = OctaveStub()
    run, cfg, tg = _stylize_run(demo, net, **{"loss.luminance_only": False, "loss.style_loss": "nnfm",
                                              "loss.w_style_coarse": 0.5})
    sty = run.phase("stylize")
    sty.setup(run)
    net.calls.clear(), net.scales.clear()
    view = _view(run, 1)
    terms = sty.terms(run, view)
    assert net.scales == [cfg.vgg_scale, cfg.vgg_scale * 0.5]  # the step's pass, then the coarse one
    img, cov = _shown(demo, run, view)
    paint = tg.style_work.double().numpy()
    fine, coarse = _nnfm(_blocks(img.numpy(), 4), _blocks(paint, 4)), _nnfm(_blocks(img.numpy(), 8), _blocks(paint, 8))
    assert abs(fine - coarse) > 0.5 * min(fine, coarse) > 0  # the octaves differ here: the checks tell them apart
    assert float(terms["style"].detach()) == pytest.approx(fine, rel=TERM_TOL, abs=1e-7)
    assert float(terms["style_coarse"].detach()) == pytest.approx(coarse, rel=TERM_TOL, abs=1e-7)
    assert terms["style_coarse"].requires_grad
    assert sty.weights(0)["style_coarse"] == 0.5 * cfg.loss.strength ** 3


class DeepStub(StubFeatures):
    """The stub with a conv4 block of its own: ``deep_features`` gives the 8x8 block means of the image and of its
    square (6 channels, so the term's channel count is the painting's, not the style term's 3)."""

    def deep_features(self, img, scale=1.0):
        x = (img.permute(2, 0, 1).unsqueeze(0) if img.dim() == 3 else img).float()
        return F.avg_pool2d(torch.cat([x, x * x], 1), 8)

    def features_of(self, images, scale=1.0, deep=False):  # as VGG16Features: the first image's deep features last
        out = super().features_of(images, scale)
        return out + [self.deep_features(images[0]).reshape(6, -1)] if deep else out


def _blocks6(img: np.ndarray, n: int) -> np.ndarray:
    return np.concatenate([_blocks(img, n), _blocks(img * img, n)], 0)  # [6, cells]


def _deep_run(demo, **extra):
    """A stylize run on the stub with a conv4 block (the deep term at 0.7) and one terms call on view 1: the run,
    its config, stylize phase, targets and terms, and in float64 what the terms see and the painting ([H,W,3] each)."""
    run, cfg, tg = _stylize_run(demo, DeepStub(), **{"loss.luminance_only": False, "loss.style_loss": "nnfm",
                                                     "loss.w_style_deep": 0.7, **extra})
    sty = run.phase("stylize")
    sty.setup(run)
    view = _view(run, 1)
    terms = sty.terms(run, view)
    img, _ = _shown(demo, run, view)
    return run, cfg, sty, tg, terms, img.numpy(), tg.style_work.double().numpy()


def test_deep_style_term_matches_the_conv4_features(demo):
    """loss.w_style_deep: a second NNFM term on the network's deep features of the style term's input and the
    painting (float64 oracle: 8x8 block means of the image and its square, 6 channels), through the packed features
    of one terms call, with a gradient and its own weight; it may not run beside the coarse term."""
    from tlvg_warp.config_io import ConfigError

    run, cfg, sty, tg, terms, img, paint = _deep_run(demo)
    assert tuple(tg.style_feats_deep.shape[:1]) == (6,)
    fine, deep = _nnfm(_blocks(img, 4), _blocks(paint, 4)), _nnfm(_blocks6(img, 8), _blocks6(paint, 8))
    assert abs(fine - deep) > 0.1 * min(fine, deep) > 0  # the two differ here: the checks tell them apart
    assert float(terms["style"].detach()) == pytest.approx(fine, rel=TERM_TOL, abs=1e-7)
    assert float(terms["style_deep"].detach()) == pytest.approx(deep, rel=TERM_TOL, abs=1e-7)
    assert terms["style_deep"].requires_grad
    assert "style_deep" not in sty.image_names  # its match is cached per view: outside the graphed terms
    assert sty.weights(0)["style_deep"] == 0.7 * cfg.loss.strength ** 3
    with pytest.raises(ConfigError, match="w_style_deep"):
        stylize_config({"loss.w_style_deep": 1.0, "loss.w_style_coarse": 1.0}).validate()


def _layered_gram(a: np.ndarray, s: np.ndarray, layers: int = 3) -> float:
    """Per layer (equal row blocks) ||G - G_p|| / ||G_p|| (Frobenius) of the cell-normalized Gram matrices, averaged."""
    def g(x):
        return x @ x.T / x.shape[1]
    return float(np.mean([np.sqrt(((g(x) - g(y)) ** 2).sum() / (g(y) ** 2).sum())
                          for x, y in zip(np.split(a, layers), np.split(s, layers))]))


def test_deep_gram_term_compares_each_conv4_layers_gram_matrix(demo):
    """loss.deep_loss gram: the deep term is each layer's Gram distance (three equal channel blocks of the deep
    features, float64 oracle on the stub's 8x8 block means), not the NNFM of the same features, and it carries a
    gradient to the splats' colours (the loss's own gradient: tests/test_losses_style.py)."""
    run, cfg, sty, tg, terms, img, paint = _deep_run(demo, **{"loss.deep_loss": "gram"})
    a, s = _blocks6(img, 8), _blocks6(paint, 8)
    want = _layered_gram(a, s)
    assert abs(want - _nnfm(a, s)) > 0.1 * want > 0  # the Gram and the NNFM of these features differ
    assert float(terms["style_deep"].detach()) == pytest.approx(want, rel=TERM_TOL, abs=1e-7)
    assert sty.image_names[-1] == "style_deep"  # read off the render alone: among the terms a CUDA graph replays
    (g,) = torch.autograd.grad(terms["style_deep"], run.params.sh_dc)
    assert torch.isfinite(g).all() and float(g.abs().sum()) > 0


def test_field_canvas_mixes_the_matched_and_the_canvas_fields(demo):
    """loss.field_canvas f: each view's target field is (1 - f) x the matched field + f x the painting's field laid
    over the view (doubled-angle vectors, float64 oracle from the two runs at the ends), its third channel the
    mixed vector's length; at f = 1 with the matched mapping it is the canvas field."""
    fields = {}
    for name, over in (("matched", {}), ("canvas", {"loss.field_mapping": "canvas"}),
                       ("mixed", {"loss.field_canvas": 0.25}), ("all", {"loss.field_canvas": 1.0})):
        run, _, _ = _stylize_run(demo, StubFeatures(), **{"loss.field_source": "unstylized", **over})
        sty = run.phase("stylize")
        sty.setup(run)
        fields[name] = [f.double() for f in sty.fields]
    for m, c, x, a in zip(fields["matched"], fields["canvas"], fields["mixed"], fields["all"]):
        assert float((m[..., :2] - c[..., :2]).abs().mean()) > 0.05  # the two ends differ on the demo
        want = 0.75 * m[..., :2] + 0.25 * c[..., :2]
        assert torch.allclose(x[..., :2], want, atol=1e-6)
        assert torch.allclose(x[..., 2], want.norm(dim=-1), atol=1e-6)
        assert torch.allclose(a, c, atol=1e-6)


def test_normalized_content_is_the_mse_over_the_photo_features_mean_square(demo):
    """loss.content_norm: the content term is the raw feature MSE divided by that view's photo features' mean
    square (float64 oracle from the stub's pooled pixels), so a scene's texture no longer sets its weight."""
    net = StubFeatures()
    run, cfg, tg = _stylize_run(demo, net, **{"loss.content_norm": True})
    sty = run.phase("stylize")
    sty.setup(run)
    view = _view(run, 1)
    terms = sty.terms(run, view)
    img, cov = _shown(demo, run, view)
    pool = lambda x: F.avg_pool2d(x.permute(2, 0, 1)[None], 4).reshape(3, -1)  # noqa: E731
    photo = pool(demo.photos[1].double())
    want = ((pool(img) - photo) ** 2).mean() / (photo ** 2).mean()
    assert float(terms["content"].detach()) == pytest.approx(float(want), rel=TERM_TOL)
    raw, _, _ = _stylize_run(demo, net)
    raw_sty = raw.phase("stylize")
    raw_sty.setup(raw)
    raw_c = float(raw_sty.terms(raw, _view(raw, 1))["content"].detach())
    assert raw_c == pytest.approx(float(want * (photo ** 2).mean()), rel=TERM_TOL)  # the scale is not 1 here
    assert abs(float((photo ** 2).mean()) - 1) > 0.05


def test_content_on_luminance_compares_luminance_features_in_one_pass(demo):
    """loss.content_on luminance: the content term is the feature MSE of the render's luminance against the photo's
    (float64 oracle from the stub's pooled pixels, Y = 0.299R + 0.587G + 0.114B on all three channels), and a step's
    feature pass holds one image instead of two (the style term's luminance pass serves both); with an RGB style term
    the pass holds the RGB image and its luminance, the content term reading the latter. Catches the RGB photo
    features compared with luminance render features, the second pass left in, the option ignored."""
    net = StubFeatures()
    run, cfg, tg = _stylize_run(demo, net, **{"loss.content_on": "luminance"})
    sty = run.phase("stylize")
    sty.setup(run)
    view = _view(run, 1)
    net.calls.clear()
    terms = sty.terms(run, view)
    assert [c.shape[0] for c in net.calls] == [1]
    img, cov = _shown(demo, run, view)
    luma = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    y = lambda x: (x @ luma)[..., None].expand(*x.shape[:-1], 3)  # noqa: E731
    pool = lambda x: F.avg_pool2d(x.permute(2, 0, 1)[None], 4).reshape(3, -1)  # noqa: E731
    want = ((pool(y(img)) - pool(y(demo.photos[1].double()))) ** 2).mean()
    assert float(terms["content"].detach()) == pytest.approx(float(want), rel=TERM_TOL)
    rgb, _, _ = _stylize_run(demo, net)
    rgb_sty = rgb.phase("stylize")
    rgb_sty.setup(rgb)
    net.calls.clear()
    rgb_c = float(rgb_sty.terms(rgb, _view(rgb, 1))["content"].detach())
    assert [c.shape[0] for c in net.calls] == [2] and abs(rgb_c - float(want)) > 1e-3 * float(want)
    # an RGB style term (the rgb_loss ablation) with luminance content: the render's RGB image and its luminance in
    # one batch, the content term on the luminance features
    abl, _, _ = _stylize_run(demo, net, **{"loss.content_on": "luminance", "loss.luminance_only": False})
    abl_sty = abl.phase("stylize")
    abl_sty.setup(abl)
    net.calls.clear()
    abl_c = float(abl_sty.terms(abl, _view(abl, 1))["content"].detach())
    assert [c.shape[0] for c in net.calls] == [2] and abl_c == pytest.approx(float(want), rel=TERM_TOL)


def test_palette_detail_reaches_the_pre_process_targets(demo):
    """palette_detail: the pre-process targets are the palette transfer with the painting's detail put back
    (match_detail against the painting as given), then the photo's background where the scene was empty; the
    Lab targets are those targets' statistics. Off, the targets are the plain transfer."""
    from tlvg_warp.losses import color_transfer, lab_chroma_stats, match_detail
    from tlvg_warp.stylize.pipeline import over_background

    net = StubFeatures()
    _, _, off = _stylize_run(demo, net)
    _, _, on = _stylize_run(demo, net, palette_detail=True)
    raw, _, _ = color_transfer(list(demo.photos), off.style_work)
    boosted, g = match_detail(raw, demo.style)
    assert g > 1.0  # the premise: the demo's painting carries more detail than its recolored photos
    for i, photo in enumerate(demo.photos):
        want = over_background(boosted[i], on.coverage[i], photo)
        assert torch.allclose(on.recolored[i], want, atol=1e-6), i
        assert not torch.allclose(off.recolored[i], on.recolored[i], atol=1e-3), i
    for got, r in zip(on.lab_stats, on.recolored):
        assert all(torch.allclose(a, b) for a, b in zip(got, lab_chroma_stats(r)))


def test_zero_weighted_terms_are_not_computed(demo):
    net = StubFeatures()
    run, _, _ = _stylize_run(demo, net, **{"loss.w_align": 0.0, "loss.w_aniso": 0.0, "loss.w_lab_start": 0.0,
                                           "loss.w_lab_end": 0.0, "loss.w_style": 0.0, "loss.w_content": 0.0})
    sty = run.phase("stylize")
    sty.setup(run)
    net.calls.clear()
    terms = sty.terms(run, _view(run, 0))
    assert set(terms) == {"depth", "tv", "opacity_reg", "scale_reg"} and not net.calls
    assert not sty.render_weights  # no flow terms: the render need not return Σ αT


def test_fit_terms_are_the_photometric_loss(demo):
    from tlvg_warp.losses import fit_loss

    run, _, tg = _stylize_run(demo, StubFeatures())
    pre, post = run.phase("pre"), run.phase("post")
    view = _view(run, 1)
    with torch.no_grad():
        fit = pre.terms(run, view)["fit"]
        want = float(fit_loss(view.out.color, tg.recolored[1]))
    assert float(fit) == pytest.approx(want, rel=1e-6)
    post.setup(run)  # the post targets: every view rendered and recolored
    assert len(post.targets) == VIEWS and post.state_dict()["targets"] is not None
    with torch.no_grad():
        fit = post.terms(run, view)["fit"]
        want = float(fit_loss(view.out.color, post.targets[1]))
    assert float(fit) == pytest.approx(want, rel=1e-6)
    assert set(post.trainable) == {"quats", "sh_dc", "sh_rest"}  # the post-process fits colors and rotations
    assert pre.state_dict()["targets"] is None  # given targets are not stored (the pre-process remakes them)


# --- the loop ---------------------------------------------------------------------------------------------------
class _Const(Phase):
    """A phase whose loss is the sum of the colors (any gradient will do) with a recording hook."""

    TERMS = ("sum",)

    def __init__(self, name, steps, seen, **kw):
        def hook(params, before):
            seen.append(name)
        super().__init__(name, steps, hooks=[(hook, ("means",))], **kw)

    def terms(self, run, view):
        return {"sum": view.out.color.mean()}


def _tiny_run(inp, phases, **settings):
    from tlvg_warp.train.density import DensityConfig, DensityControl
    from tlvg_warp.train.optim import GaussianOptimizer, GaussianParams, LearningRates

    params = GaussianParams(inp.gaussians.with_sh_degree(0))
    opt = GaussianOptimizer(params, LearningRates(), 1.0)
    dc = DensityControl(DensityConfig(phases=[]), params.num)
    return Run(params, opt, dc, phases, inp.cameras, LoopSettings(**settings), device="cpu",
               background=inp.background)


def test_hooks_and_trainable_groups_per_phase(demo):
    seen = []
    a = _Const("a", 3, seen, trainable=("sh_dc",))
    b = _Const("b", 2, seen)
    run = _tiny_run(demo, [a, b], log_every=100)
    g0 = run.params.detached()
    moved = {}

    def cb(step, r):
        if step == 3:
            g = r.params.detached()
            moved.update({f: not torch.equal(getattr(g, f), getattr(g0, f)) for f in g.FIELDS})
    train(run, progress=False, callback=cb)
    assert seen == ["a"] * 3 + ["b"] * 2  # each phase's hook runs in its own steps only
    assert moved == {"means": False, "quats": False, "log_scales": False, "opacity_logits": False, "sh": True}
    assert [r["phase"] for r in run.log] == ["a"] * 3 + ["b"] * 2 and run.counts["after_a"] == run.params.num


@pytest.mark.parametrize("fresh", [False, True])
def test_a_phase_with_fresh_moments_starts_adam_anew_for_its_groups(demo, fresh):
    """fresh_moments: the phase's trainable groups start with Adam's state cleared (their step count restarts at
    the phase), the others keep theirs; off, every group counts on across the phases."""
    seen = []
    run = _tiny_run(demo, [_Const("a", 3, seen), _Const("b", 2, seen, trainable=("sh_dc",), fresh_moments=fresh)],
                    log_every=100)
    train(run, progress=False)
    st = run.opt.adam.state
    assert int(st[run.params.sh_dc]["step"]) == (2 if fresh else 5)
    assert int(st[run.params.means]["step"]) == 3  # trained in a only, never cleared


def test_the_post_process_takes_fresh_moments_from_the_config(demo):
    for on in (False, True):
        run, cfg, _ = _stylize_run(demo, StubFeatures(), post_fresh_adam=on)
        post = [p for p in run.phases if p.name == "post"][0]
        assert post.fresh_moments is on and cfg.post_fresh_adam is on


def test_post_chroma_blur_smooths_the_post_targets_colour_and_keeps_their_luminance(demo):
    """post_chroma_blur: the post-process's targets (made from the same parameters) differ in colour and keep the
    luminance of the targets without it, pixel for pixel (the chroma blur keeps Y, the background blend is linear)."""
    w = torch.tensor([0.299, 0.587, 0.114])
    targets = {}
    for blur in (0.0, 0.1):
        run, _, _ = _stylize_run(demo, StubFeatures(), post_chroma_blur=blur)
        post = [p for p in run.phases if p.name == "post"][0]
        targets[blur] = [t.detach() for t in post.make_targets(run)]
    for a, b in zip(targets[0.0], targets[0.1]):
        assert torch.allclose(a @ w, b @ w, atol=1e-5)
        assert (a - b).abs().max() > 1e-3


def test_phase_end_hook_runs_once_after_each_phases_last_step(demo):
    """run.on_phase_end: called once per phase, after its last optimizer step (the step counter and the parameters
    are that step's, as a callback at that step sees them), its values kept in counts as <name>_after_<phase>."""
    seen = []
    run = _tiny_run(demo, [_Const("a", 3, seen), _Const("b", 2, seen)], log_every=100)
    calls, at_step = [], {}

    def on_end(r, phase):
        calls.append((phase.name, r.step))
        return {"dc": float(r.params.sh_dc.detach().sum())}

    def cb(step, r):
        at_step[step] = float(r.params.sh_dc.detach().sum())
    run.on_phase_end = on_end
    train(run, progress=False, callback=cb)
    assert calls == [("a", 3), ("b", 5)]
    assert run.counts["dc_after_a"] == at_step[3] and run.counts["dc_after_b"] == at_step[5]
    assert at_step[3] != at_step[2]  # the parameters move each step: a value from another step would differ


def test_batched_step_loss_is_the_mean_of_its_views(demo):
    from tlvg_warp.losses import fit_loss

    photos = [p.float() for p in demo.photos]
    fit = Fit("fit", 3, photos)
    run = _tiny_run(demo, [fit], log_every=1, views_per_step=2)
    g0 = run.params.detached()
    train(run, progress=False)
    first = run.log[0]
    assert len(first["view"]) == 2
    with torch.no_grad():
        want = sum(float(fit_loss(render(g0, demo.cameras[v], demo.background).color, photos[v]))
                   for v in first["view"]) / 2
    assert first["loss"] == pytest.approx(want, rel=1e-5)
    # an epoch of 4 views is two steps: each view once
    assert sorted(run.log[0]["view"] + run.log[1]["view"]) == list(range(VIEWS))


# --- two ranks in one process -----------------------------------------------------------------------------------
class _Group:
    """Ranks as threads that take turns: a rank computes while holding ``turn`` and lets go of it only inside a
    collective (Warp's tape is process-wide state: two renders at once would share it)."""

    def __init__(self, world):
        self.barrier, self.slots = threading.Barrier(world, timeout=120), [None] * world
        self.turn = threading.Lock()


@dataclass
class ThreadDist:
    """The ``Dist`` API for ranks that are threads of this process (the collectives reduce in rank order)."""

    rank: int
    world: int
    group: _Group
    device: str = "cpu"
    local_rank: int = 0

    @property
    def is_main(self):
        return self.rank == 0

    def _exchange(self, obj):
        g = self.group
        g.slots[self.rank] = obj
        g.turn.release()
        try:
            g.barrier.wait()
            out = list(g.slots)
            g.barrier.wait()
        finally:
            g.turn.acquire()
        return out

    def _reduce_(self, tensors, op):
        present = [t for t in tensors if t is not None]
        by_dtype = {}
        for t in present:
            by_dtype.setdefault(t.dtype, []).append(t)
        for group in by_dtype.values():
            flat = torch.cat([t.detach().reshape(-1) for t in group])
            total = op(self._exchange(flat.clone()))
            off = 0
            for t in group:
                with torch.no_grad():
                    t.copy_(total[off:off + t.numel()].view_as(t))
                off += t.numel()

    def all_reduce_sum_(self, tensors):
        self._reduce_(tensors, lambda xs: sum(xs[1:], xs[0]))

    def all_reduce_mean_(self, tensors):
        self._reduce_(tensors, lambda xs: sum(xs[1:], xs[0]) / len(xs))

    def all_reduce_max_(self, tensors):
        self._reduce_(tensors, lambda xs: torch.stack(xs).amax(0))

    def broadcast_object(self, obj, src=0):
        return self._exchange(obj)[src]

    def barrier(self):
        self._exchange(None)

    def rank_slice(self, items):
        return list(items)[self.rank::self.world]


class _Synthetic:
    """Photos rendered from the demo's Gaussians, for fit_scene (with density control on)."""

    def __init__(self, inp):
        self.cameras, self.names, self.points = inp.cameras, list(inp.names), None
        self.background = inp.background
        self._imgs = [p.float() for p in inp.photos]

    def image(self, i):
        return self._imgs[i]


def test_one_rank_two_views_equals_two_ranks_one_view(demo):
    ds = _Synthetic(demo)
    over = {"iterations": 12, "device": "cpu", "holdout_every": 0, "sh_degree": 0, "log_every": 4,
            "density.start": 4, "density.interval": 4, "density.max_gaussians": 0, "lr.means": 1e-3}
    g1, m1 = fit_scene(ds, fit_config({**over, "views_per_step": 2}).validate(), None, demo.gaussians, progress=False)
    assert any(e["cloned"] + e["split"] for e in m1["densify_events"])  # density control acted
    # and the stage timer timed each of those steps (rare work: timed whenever it runs, not when sampled)
    assert m1["time_split"]["rare_events"] == {"density": len(m1["densify_events"])}
    group, out = _Group(2), {}

    def rank(r):
        with group.turn:
            out[r] = fit_scene(ds, fit_config(over).validate(), None, demo.gaussians, progress=False,
                               dist=ThreadDist(r, 2, group))

    threads = [threading.Thread(target=rank, args=(r,)) for r in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    (g2, m2), (g2b, _) = out[0], out[1]
    assert m2["densify_events"] == m1["densify_events"]  # every rank decided as the single process did
    for f in g1.FIELDS:
        assert torch.equal(getattr(g2, f), getattr(g2b, f)), f  # the ranks agree exactly
        assert torch.allclose(getattr(g2, f), getattr(g1, f), atol=BATCH_TOL), f
    assert [s for s, _ in m2["loss_history"]] == [s for s, _ in m1["loss_history"]] == [4, 8, 12]
    assert [v for _, v in m2["loss_history"]] == pytest.approx([v for _, v in m1["loss_history"]], rel=1e-4)


# --- the performance rule ---------------------------------------------------------------------------------------
HOST_READS = ("item", "tolist", "cpu", "numpy", "__bool__", "__float__", "__int__", "__index__", "nonzero")
OWN = ("tlvg_warp/train/", "tlvg_warp/stylize/")
HOST_RNG = ("next_batch", "background")  # the view order and random backgrounds: a CPU generator by design


def _mark_steps(monkeypatch, inside: dict) -> None:
    """While the loop runs a step, ``inside["step"]`` holds its number (None between steps)."""
    from tlvg_warp.train import loop as L

    real_step = L._Loop.step

    def step(self, phase, k, s):
        inside["step"] = s
        try:
            return real_step(self, phase, k, s)
        finally:
            inside["step"] = None
    monkeypatch.setattr(L._Loop, "step", step)


def test_no_host_reads_in_a_step_outside_the_schedule(demo, monkeypatch):
    """Counted: calls of host-reading tensor methods made from the loop's own code (train/, stylize/) while a
    step runs. Allowed: density control's densify steps (its decisions are data-dependent) and nothing else;
    the log flush, the non-finite check and the snapshot happen between steps."""
    reads, inside = [], {"step": None}
    for name in HOST_READS:
        orig = getattr(torch.Tensor, name)

        def wrapped(self, *a, _orig=orig, _name=name, **k):
            if inside["step"] is not None:
                f = sys._getframe(1)
                path = f.f_code.co_filename.replace("\\", "/")
                if any(o in path for o in OWN) and f.f_code.co_name not in HOST_RNG:
                    reads.append((inside["step"], _name, f.f_code.co_name))
            return _orig(self, *a, **k)
        monkeypatch.setattr(torch.Tensor, name, wrapped)
    _mark_steps(monkeypatch, inside)
    run, _, _ = _stylize_run(demo, StubFeatures(), **{"iterations": 12, "log_every": 4, "density.interval": 2,
                                                      "loss.w_style_swd": 1.0, "loss.w_color_swd": 1.0})
    train(run, progress=False)
    outside = [r for r in reads if r[2] not in ("densify_and_prune", "prune_mask", "_apply", "fit_budget")]
    assert outside == [], outside
    assert any(r[2] == "densify_and_prune" for r in reads)  # the counter works: densify steps do read


def test_no_copy_from_the_host_on_every_step(demo, monkeypatch):
    """A tensor built from host data inside a step is a copy that waits for the GPU (torch syncs the stream for a
    copy from pageable memory). Counted: torch.tensor / as_tensor / Tensor.new_tensor called from the loop's own
    code (train/, stylize/, losses/) while a step runs. A constant made once and kept (the background, a phase's
    weight table) is allowed on one step per phase; a copy made on every step of a phase is not."""
    calls, inside = [], {"step": None}
    own = (*OWN, "tlvg_warp/losses/")

    def counted(orig):
        def wrapped(*a, **k):
            if inside["step"] is not None:
                f = sys._getframe(1)
                if any(o in f.f_code.co_filename.replace("\\", "/") for o in own) and f.f_code.co_name not in HOST_RNG:
                    calls.append((inside["step"], f.f_code.co_name))
            return orig(*a, **k)
        return wrapped
    monkeypatch.setattr(torch, "tensor", counted(torch.tensor))
    monkeypatch.setattr(torch, "as_tensor", counted(torch.as_tensor))
    monkeypatch.setattr(torch.Tensor, "new_tensor", counted(torch.Tensor.new_tensor))
    _mark_steps(monkeypatch, inside)
    run, _, _ = _stylize_run(demo, StubFeatures(), **{"iterations": 12, "log_every": 4, "density.interval": 2})
    assert run.phase("stylize").steps >= 6  # enough steps that a per-step copy shows
    train(run, progress=False)
    steps_of: dict = {}
    for s, fn in calls:
        steps_of.setdefault(fn, set()).add(s)
    assert calls, "the counter saw nothing (the weight tables are built inside the first step of each phase)"
    per_step = {fn: sorted(s) for fn, s in steps_of.items() if len(s) > len(run.phases)}
    assert per_step == {}, per_step


class _Scheduled(Phase):
    TERMS = ("a", "b", "c", "d")

    def weights(self, k):
        return {"a": 0.5 + k, "c": 0.0, "d": 2.0 if k % 2 else 0.0}  # b: weight 1 by default; c: 0 on every step


def test_weight_table_is_the_weighted_sum_in_value_and_gradient():
    """The loop's Σ weight·term (one dot product against the phase's weights put on the device once) against
    ``weighted_sum`` (the plain sum, term by term) on every step of a schedule: a weight changing per step, one
    left at 1, one 0 throughout (no gradient reaches it), one 0 on every other step. Catches a step's row read off
    by one, terms matched to the wrong weights, a term that is 0 throughout still differentiated."""
    from tlvg_warp.train.loop import WeightTable, weighted_sum

    phase = _Scheduled("p", 5)
    table = WeightTable(phase)
    gen = torch.Generator().manual_seed(3)
    for k in range(phase.steps):
        x = torch.randn(4, generator=gen, dtype=torch.float64, requires_grad=True)
        terms = {n: (x[i] * (i + 1)) ** 2 for i, n in enumerate(phase.TERMS)}
        got = table.loss(terms, k)
        (g_got,) = torch.autograd.grad(got, x)
        want = weighted_sum({n: (x[i] * (i + 1)) ** 2 for i, n in enumerate(phase.TERMS)}, phase.weights(k))
        (g_want,) = torch.autograd.grad(want, x)
        assert got.dtype == torch.float64
        assert abs(float(got.detach()) - float(want.detach())) <= 1e-12 * max(1.0, abs(float(want.detach()))), k
        assert torch.allclose(g_got, g_want, rtol=1e-12, atol=0), k
        assert float(g_got[2]) == 0.0
    live, _, alone = next(iter(table.tables.values()))
    assert live == [0, 1, 3] and not alone  # c, 0 on every step, is not in the sum
    one = WeightTable(Phase("fit", 3))  # one term of weight 1 throughout: the loss is that term itself
    t = torch.tensor(2.5, requires_grad=True)
    assert one.loss({"fit": t}, 1) is t


def test_stage_timer_spreads_rare_work_over_every_step(monkeypatch):
    """A fake clock: every step spends 1 ms in "a"; steps 100, 111 (a sampled one) and 200 also 50 ms in density
    (rare work). The split must say a = 1 ms and density = 3 x 50 / 200 = 0.75 ms per step. Catches rare work
    averaged over the samples (as the loop did: every fifth sample was a densify step, 20x its share; here 5 ms),
    rare work counted only when sampled (0.25 ms) or counted twice on a sampled step (1.0 ms)."""
    import tlvg_warp.runs as runs_mod

    clock = [0.0]
    monkeypatch.setattr(runs_mod.time, "perf_counter", lambda: clock[0])
    t = runs_mod.StageTimer(torch.device("cpu"), ("a", "density"), every=20)
    for step in range(1, 201):
        t.begin(step)
        clock[0] += 1e-3
        t.mark("a")
        if step % 100 == 0 or step == 111:
            start = t.timed()
            clock[0] += 50e-3
            t.done("density", start)
        t.end()
    s = t.summary()
    assert s["samples"] == 10 and s["rare_events"] == {"density": 3}
    assert s["ms_per_iteration"]["a"] == pytest.approx(1.0)
    assert s["ms_per_iteration"]["density"] == pytest.approx(0.75)


# --- density control is a strategy the loop talks to --------------------------------------------------------------
class PruneHalfOnce(DensityStrategy):
    """A strategy of its own (not a fork of DensityControl): at its phase's step 2 it keeps the more opaque half
    of the Gaussians, and it records what the loop asked of it."""

    def __init__(self):
        super().__init__()
        self.calls = []

    def begin_phase(self, num):
        self.calls.append(("begin", num))

    def accumulating(self, s):
        return True

    def accumulate(self, out, width, height, grad_scale=1.0):
        self.calls.append(("accumulate", int(out.radii.shape[0])))

    def acts_at(self, s, n=None):
        return s == 2

    def step(self, opt, s, n=None, tag=None):
        self.calls.append(("step", s))
        if s != 2:
            return None
        o = opt.params.opacity_logits.detach()
        keep = o >= o.median()
        opt.rebuild(keep, None)
        for k, t in self.tracked.items():
            self.tracked[k] = t[keep]
        ev = {"pruned": int((~keep).sum()), "num": opt.params.num, **(tag or {})}
        self.events.append(ev)
        return ev


def test_a_new_density_strategy_is_a_class_the_loop_drives(demo):
    from tlvg_warp.train.optim import GaussianOptimizer, GaussianParams, LearningRates

    photos = [p.float() for p in demo.photos]
    params = GaussianParams(demo.gaussians.with_sh_degree(0))
    opt = GaussianOptimizer(params, LearningRates(), 1.0)
    strategy = PruneHalfOnce()
    assert isinstance(strategy, DensityStrategy)
    n0 = params.num
    strategy.track("anchor", torch.arange(n0, dtype=torch.float32))
    run = Run(params, opt, strategy, [Fit("fit", 4, photos, density=True)], demo.cameras, LoopSettings(log_every=1),
              device="cpu", background=demo.background)
    train(run, progress=False)
    ev = strategy.events[0]
    assert 0 < ev["pruned"] <= n0 // 2 and run.params.num == n0 - ev["pruned"]  # the strategy's decision, applied
    assert strategy.tracked["anchor"].shape[0] == run.params.num  # its own per-Gaussian tensors followed it
    kinds = [c[0] for c in strategy.calls]
    assert kinds[0] == "begin" and kinds.count("accumulate") == 4 and kinds.count("step") == 4
    assert strategy.events and strategy.events[0]["step"] == 2 and strategy.events[0]["phase"] == "fit"
    assert all(math.isfinite(r["loss"]) for r in run.log)
    # the base class is the strategy that never changes the Gaussians
    base_params = GaussianParams(demo.gaussians.with_sh_degree(0))
    run = Run(base_params, GaussianOptimizer(base_params, LearningRates(), 1.0), DensityStrategy(),
              [Fit("fit", 3, photos, density=True)], demo.cameras, LoopSettings(log_every=1), device="cpu",
              background=demo.background)
    train(run, progress=False)
    assert run.params.num == n0


def test_a_resumed_stylize_phase_draws_the_directions_an_uninterrupted_one_would(demo):
    """The sliced Wasserstein terms draw new directions on every call; the phase's state carries how many were
    drawn, so the first call after a resume equals the uninterrupted run's next call (and not its first)."""
    over = {"loss.w_style_swd": 1.0, "loss.w_color_swd": 1.0}
    net = StubFeatures()
    a, _, _ = _stylize_run(demo, net, **over)
    sty_a = a.phase("stylize")
    sty_a.setup(a)
    first = [float(sty_a.terms(a, _view(a, 1))[k].detach()) for k in ("style_swd", "color_swd")]
    saved = sty_a.state_dict()
    nxt = [float(sty_a.terms(a, _view(a, 1))[k].detach()) for k in ("style_swd", "color_swd")]
    b, _, _ = _stylize_run(demo, net, **over)
    sty_b = b.phase("stylize")
    sty_b.load_state_dict(saved)
    sty_b.setup(b)
    resumed = [float(sty_b.terms(b, _view(b, 1))[k].detach()) for k in ("style_swd", "color_swd")]
    assert resumed == pytest.approx(nxt, rel=1e-6) and all(abs(x - y) > 1e-9 for x, y in zip(first, nxt))


def test_the_chroma_colour_term_compares_rgb_minus_luminance_and_ignores_a_grey_shift(demo):
    """loss.color_swd_space chroma: the colour term is the sliced Wasserstein distance between the covered pixels'
    and the painting's RGB minus Y (numpy float64 oracle), so brightening the render by a grey offset leaves it
    unchanged while the rgb form moves."""
    def term(space, shift):
        net = StubFeatures()
        run, cfg, tg = _stylize_run(demo, net, **{"loss.w_color_swd": 1.0, "loss.color_swd_projections": 6,
                                                  "loss.color_swd_space": space})
        sty = run.phase("stylize")
        sty.setup(run)
        view = _view(run, 2)
        view.out.color = view.out.color + shift
        return float(sty.terms(run, view)["color_swd"].detach()), run, cfg, tg, view

    got, run, cfg, tg, view = term("chroma", 0.0)
    img, cov = _shown(demo, run, view)
    luma = np.array([0.299, 0.587, 0.114])
    chroma = lambda x: x - (x @ luma)[:, None]  # noqa: E731
    x = chroma(img.numpy().reshape(-1, 3)[cov.numpy().reshape(-1) >= 0.5])
    y = chroma(tg.style_work.double().numpy().reshape(-1, 3))
    d = random_directions(3, 6, (cfg.seed + 1) * 1_000_003, "cpu").double().numpy()
    px, py = np.sort(x @ d, axis=0), np.sort(y @ d, axis=0)
    rows = np.floor((np.arange(len(px)) + 0.5) * len(py) / len(px)).astype(int)
    want = ((px - py[rows]) ** 2).mean() / y.var(axis=0).mean()
    assert got == pytest.approx(want, rel=TERM_TOL)
    assert term("chroma", 0.05)[0] == pytest.approx(got, rel=1e-4)  # a grey offset has no chroma
    assert abs(term("rgb", 0.05)[0] - term("rgb", 0.0)[0]) > 1e-3 * term("rgb", 0.0)[0]


def test_renders_sized_from_each_views_last_count_train_the_same_scene(demo):
    """The loop with an IntersectionBudget (``render_headroom`` > 1 on a GPU) against the same run counting every
    render exactly: the same parameters bit for bit after a stylize run that visits each view six times; each view's
    first render counts exactly, the later ones are sized (a change of the number of Gaussians, which sends a
    render back to counting, is tested with the raster)."""
    from tlvg_warp.raster import IntersectionBudget

    runs = []
    for budget in (None, IntersectionBudget(1.25)):
        run, _, _ = _stylize_run(demo, StubFeatures(), iterations=24, phases=[8, 8, 8])
        assert run.budget is None  # the CPU counts exactly whatever the headroom
        run.budget = budget
        train(run, progress=False, quiet=True)
        runs.append(run)
    exact, sized = (r.params.detached() for r in runs)
    for f in exact.FIELDS:
        assert torch.equal(getattr(exact, f), getattr(sized, f)), f
    counts = runs[1].render_counts()
    assert counts == {"exact": VIEWS, "sized": 24 - VIEWS, "over_capacity": 0}
    assert runs[0].render_counts() is None
