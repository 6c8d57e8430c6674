"""The stylization (SPEC §3): three phases of the one training loop (train/loop.py), one Adam across them.

    inp = StylizeInputs(gaussians, cameras, names, photos, style, background)
    result = run_stylize(inp, StylizeConfig(), out_dir)

Every step renders ONE training view (``views_per_step``), drawn at random without replacement per epoch.
1. ``Fit("pre")``: the photos recolored to the painting's palette (``palette_map``, once), fit with
   0.8·L1 + 0.2·(1−SSIM), density control on (``density.phases``).
2. ``Stylize``: style (FAST on luminance by default) + content + inverse depth + TV + opacity/scale anchors
   + Lab chroma (0.2 → 0.05) + flow alignment + anisotropy; xyz unlocked with its exponential decay, the
   tangential hook after every Adam step of this phase (and of no other), density control under the budget.
3. ``Fit("post")``: every view rendered and recolored once more; colors and rotations fit to them (positions,
   scales and opacities get no gradient, so they keep their values).

Per-view targets are computed once (``prepare``): recolored photos, VGG features of the photos, the
un-stylized scene's inverse depth; each phase makes its own at its start (the stroke fields of Stylize, the
post targets) and keeps them in its state, so a resumed run continues with the same ones.

Decisions (beyond the spec, documented):
- keep_sh False (default): the whole run works at SH degree 0 (the input's view-dependent bands are
  dropped at the start), so stylized.ply is exactly what was optimized.
- The content loss compares RGB VGG features of the render with those of the original photo, also when the
  style loss is luminance-only (SPEC §3, as ARF-Plus: only the style term is decoupled); both renders go
  through VGG in one batch. The RGB-loss ablation changes the style term's input only.
- The "matched" target field of a view is built from the FAST/NNFM cell match of that view's render at the
  start of stylize and then held fixed (a target that moved with the render would chase itself). The match
  is on luminance features whatever the style term's input, so the RGB-loss ablation keeps the same fields.
- The opacity / scale anchors are tensors tracked by density control: a clone or split child is anchored at
  its own value when it is born.
- A term whose weight is 0 over the whole phase is not computed (it logs 0): abcgs.yaml runs no Lab or
  flow terms at all.
- geometry.lock_xyz locks positions during stylize only (the pre-process is a photometric fit).
"""
from __future__ import annotations

import dataclasses
import sys
import time
import warnings
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import torch

from .. import runs
from ..distributed import Dist
from ..errors import InputError
from ..renderer import render
from ..train.init import scene_extent
from ..train.loop import Diverged, Fit, Phase, Run, View, train
from ..train.optim import FIELDS, GaussianParams, colour_floor_hook, tangential_hook
from ..train.refine import refine_to_radius
from ..train.session import Session, density_control, new_run, optimizer
from ..types import SH_C0, Gaussians
from .config import PHASES, StylizeConfig, config_yaml

CHECKPOINT_FORMAT = "tlvg_warp.stylize.v1"
STYLIZE_TERMS = ("style", "style_coarse", "style_deep", "style_gram", "style_swd", "style_color", "color_swd",
                 "content", "depth", "tv", "chroma_tv", "palette", "detail", "tone_hold", "stroke", "coverage",
                 "silhouette", "opacity_reg", "scale_reg", "lab", "orient", "align", "aniso")
LOG_TERMS = ("loss", "fit", *STYLIZE_TERMS)  # the log's columns
NORM_EPS = 1e-24  # inside sqrt of the anchor norms: a finite (zero) gradient when nothing has moved yet
COARSE = 0.5  # the coarse style term's working size against the style term's (loss.w_style_coarse)
REFINE_UNCAPPED = 2.0  # the refinement's Gaussian count limit (x the input) when density control has no budget
POST_TRAINABLE = ("quats", "sh_dc", "sh_rest")  # the post-process fits colors and rotations only
RUN_FILES = ("checkpoint.pt", "stylized.ply", "metrics.json", "log.jsonl", "config.yaml", "sources.json")


class StylizeDiverged(Diverged):
    """The loss or the parameters became non-finite; the last good state was saved."""


@dataclass
class StylizeInputs:
    gaussians: Gaussians  # the un-stylized scene
    cameras: list  # Camera per view, at the working resolution
    names: list  # view names
    photos: list  # [H,W,3] float32 in [0,1] per view
    style: torch.Tensor  # the painting [h,w,3] float32 in [0,1]
    background: tuple = (0.0, 0.0, 0.0)  # render background
    sources: dict = field(default_factory=dict)  # where the inputs came from (recorded for --resume)

    def check(self) -> None:
        if len(self.cameras) < 1:
            raise InputError("the dataset has no views")
        if len(self.cameras) != len(self.photos) or len(self.names) != len(self.cameras):
            raise InputError(f"{len(self.cameras)} cameras but {len(self.photos)} photos")
        for cam, ph, nm in zip(self.cameras, self.photos, self.names):
            if tuple(ph.shape) != (cam.height, cam.width, 3):
                raise InputError(f"photo {nm} is {tuple(ph.shape)}, its camera says {cam.height}x{cam.width}")
        if self.gaussians.num == 0:
            raise InputError("the scene has no Gaussians")
        g = self.gaussians
        finite = torch.ones(g.num, dtype=torch.bool, device=g.device)
        for f in g.FIELDS:
            finite &= torch.isfinite(getattr(g, f)).reshape(g.num, -1).all(1)
        bad = int((~finite).sum())
        if bad == g.num:
            raise InputError(f"all {bad} Gaussians of the scene have non-finite parameters")
        if bad:  # a few broken splats (a bad export, an upstream NaN) are dropped rather than poisoning the run
            warnings.warn(f"dropping {bad} of {g.num} Gaussians with non-finite parameters")
            self.gaussians = g.subset(finite)


# --- small utilities -------------------------------------------------------------------------------------------
def tv_loss(img: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of horizontal plus vertical neighbours of an [H,W,3] image."""
    return ((img[1:] - img[:-1]) ** 2).mean() + ((img[:, 1:] - img[:, :-1]) ** 2).mean()


LAB_TV_SCALE = 1 / 200  # Lab a*, b* to the scale of RGB's chroma residual: the two TVs agree within 2x on renders


def chroma_tv_loss(img: torch.Tensor, space: str = "rgb") -> torch.Tensor:
    """TV of the chroma residual ``img - Y`` (Y = 0.299R+0.587G+0.114B), or with ``space`` "lab" of Lab a*, b* x
    ``LAB_TV_SCALE``: strokes may vary luminance at any scale while colour stays in clean patches (the "muddy
    colour" the luminance-only style loss exists to avoid)."""
    from ..losses import chroma, rgb_to_lab  # lazy: imports Warp

    return tv_loss(chroma(img) if space == "rgb" else rgb_to_lab(img)[..., 1:] * LAB_TV_SCALE)


HOLE_ALPHA = 0.5  # a pixel is covered at alpha >= 0.5 (SPEC §4 holes; eval.metrics.ALPHA_MIN, a layer above)


def coverage_loss(alpha: torch.Tensor, coverage: torch.Tensor) -> torch.Tensor:
    """Mean over pixels of how far the render's alpha [H,W] falls below the un-stylized scene's [H,W,1]: a hinge, so
    only holes cost, never a splat that covers more."""
    return torch.relu(coverage[..., 0] - alpha).mean()


def silhouette_loss(alpha: torch.Tensor, coverage: torch.Tensor, where: str = "all") -> torch.Tensor:
    """Mean over pixels of how far the render's alpha [H,W] rises above the un-stylized scene's [H,W,1]: the mirror
    of ``coverage_loss``. Where the scene was empty (a Blender background) the style terms see the background, not
    the render, so nothing else stops splats from fraying outwards. ``where`` "empty" counts only the pixels the
    un-stylized scene leaves uncovered (alpha under ``HOLE_ALPHA``): the outline, not a covered pixel whose alpha
    ends a little above a soft 0.97."""
    over = torch.relu(alpha - coverage[..., 0])
    if where == "empty":
        over = over * (coverage[..., 0] < HOLE_ALPHA)
    return over.mean()


def covered_mean(y: torch.Tensor, coverage: torch.Tensor) -> torch.Tensor:
    """The mean of the luminance ``y`` [H,W,C] (its first channel: R = G = B) over the pixels the un-stylized scene
    covers, weighted by its alpha [H,W,1]: []."""
    return (y[..., :1] * coverage).sum() / coverage.sum().clamp_min(1e-12)


def tone_hinge(tone: torch.Tensor, target: torch.Tensor, margin: float) -> torch.Tensor:
    """(|Ȳ − Ȳ_target| − margin)² beyond the margin, 0 within it: the covered mean luminance may move with the
    strokes by up to ``margin`` from its colour target's, no further (a dark object stays dark)."""
    return torch.relu((tone - target).abs() - margin) ** 2


def cell_map(n: int, cells: int, like: torch.Tensor) -> torch.Tensor:
    """[n, cells] 0/1: pixel i in cell i * cells // n (comparisons only: nothing a CUDA graph's capture cannot
    record, no host read)."""
    i = torch.arange(n, device=like.device)[:, None] * cells // n
    return (i == torch.arange(cells, device=like.device)[None, :]).to(like.dtype)


def cell_tones(y: torch.Tensor, coverage: torch.Tensor, cells: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The covered mean luminance of ``y`` [H,W,C] (first channel) per cell of a grid ``cells`` rows high with
    square-ish cells (``round(cells * W / H)`` columns; each pixel in one cell; no more rows or columns than the view
    has pixels), weighted by the coverage [H,W,1]: (means [r,c], each cell's covered fraction [r,c]). ``cells`` 0:
    one cell, the whole view (``covered_mean``) with weight 1. Sums by two matrix products with 0/1 cell maps:
    deterministic, unlike a pooling's backward on CUDA."""
    if cells == 0:
        return covered_mean(y, coverage), coverage.new_ones(())
    h, w = coverage.shape[:2]
    rows = min(cells, h)  # no empty cell: a cell of no pixels has no mean (0/0 in its weight)
    cols = min(w, max(1, round(rows * w / h)))
    r = cell_map(h, rows, y).T  # [r,H]
    c = cell_map(w, cols, y)  # [W,c]
    area = (r.sum(1, keepdim=True) * c.sum(0, keepdim=True))  # [r,c] pixels per cell
    cov = r @ coverage[..., 0] @ c  # [r,c]
    return (r @ (y[..., 0] * coverage[..., 0]) @ c) / cov.clamp_min(1e-12), cov / area


def tone_hold_loss(y: torch.Tensor, coverage: torch.Tensor, target: torch.Tensor, margin: float,
                   cells: int = 0) -> torch.Tensor:
    """The tone hold: ``tone_hinge`` of each cell's covered mean luminance (``cell_tones``) against its colour
    target's (``target``: [] or [r,c]), averaged with the cells' covered fractions as weights. ``cells`` 0 holds the
    whole view's mean; more cells hold the light and dark masses of the view where they were (a dark track stays
    dark beside a light body) while strokes vary the luminance within each cell."""
    tones, weight = cell_tones(y, coverage, cells)
    return (tone_hinge(tones, target, margin) * weight).sum() / weight.sum().clamp_min(1e-12)


def detail_hinge(energy: torch.Tensor, target: float) -> torch.Tensor:
    """(1 - E/E*)² while the render's detail energy E is below the painting's E*, 0 above: detail is asked for up to
    the painting's level, never beyond (more would be noise)."""
    return torch.relu(1.0 - energy / max(target, 1e-12)) ** 2


def painting_detail(style_work: torch.Tensor, height: int) -> float:
    """The painting's luminance detail energy at ``height`` rows (the views' height), the detail hinge's target."""
    from ..losses import detail_energy, resize_style  # lazy: imports Warp

    p = torch.from_numpy(resize_style(style_work.detach().cpu().numpy(), height)).double()
    return float(detail_energy(p))


def painting_stroke(style_work: torch.Tensor, height: int, log_eps: float | None = None) -> tuple[float, float]:
    """The painting's luminance contrast (across, along) its own stroke field at ``height`` rows (the views' height),
    the stroke hinge's targets; of log luminance when ``log_eps`` is given."""
    from ..losses import painting_stroke_energies  # lazy: imports Warp

    return painting_stroke_energies(style_work.detach().cpu().numpy(), height, log_eps)


def stroke_log_eps(contrast: str) -> float | None:
    """The stroke hinge's log offset for loss.stroke_contrast ("log": STROKE_LOG_EPS; "linear": None)."""
    from ..losses.stroke_field import STROKE_LOG_EPS  # lazy: imports Warp

    return STROKE_LOG_EPS if contrast == "log" else None


def _shift_dc_(sh_dc: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Adds colour offsets ``delta`` [N,3] (colour units) to the DC band [N,1,3] in place; returns ``delta``."""
    with torch.no_grad():
        sh_dc.add_((delta / SH_C0).to(sh_dc)[:, None, :])
    return delta


def jitter_luminance_(sh_dc: torch.Tensor, amplitude: float, seed: int) -> torch.Tensor:
    """Moves every Gaussian's DC colour [N,1,3] by one N(0, amplitude²) offset, the same on R, G and B (so luminance
    moves by it and RGB minus luminance does not), in place; returns the offsets [N] in colour units."""
    gen = torch.Generator().manual_seed(int(seed))
    delta = torch.randn(sh_dc.shape[0], generator=gen, dtype=torch.float64) * amplitude  # [N]
    return _shift_dc_(sh_dc, delta[:, None].expand(-1, 3))[:, 0]


def block_mean(img: torch.Tensor, n: int) -> torch.Tensor:
    """[H,W,3] -> [H//n, W//n, 3]: the mean over n x n blocks (the edge rows and columns past a whole block
    dropped); n = 1 returns ``img`` itself. Differentiable."""
    if n == 1:
        return img
    out = torch.nn.functional.avg_pool2d(img.permute(2, 0, 1).unsqueeze(0), n)  # [1,3,h,w]
    return out[0].permute(1, 2, 0).contiguous()


def lab_block_px(height: int, block: float) -> int:
    """The Lab term's block edge in pixels for a view ``height`` pixels tall: ``block`` x height, at least 1."""
    return max(1, round(block * height))


def lab_blocks(coverage: list, block: float) -> list:
    """Per view the flat indices [P] of the Lab term's blocks (``block_mean`` of the view at ``lab_block_px``) that
    the un-stylized scene covers (block-mean alpha >= 0.5; ``coverage``: per view [H,W,1]), or None (every block)
    where it covers them all (a capture) or none (no statistics of an empty set): computed once, so the step gathers
    them without a host sync."""
    out = []
    for cov in coverage:
        covered = block_mean(cov, lab_block_px(cov.shape[0], block)).reshape(-1) >= 0.5  # [h*w]
        out.append(None if bool(covered.all()) or not bool(covered.any()) else torch.nonzero(covered)[:, 0])
    return out


def lab_input(img: torch.Tensor, block: float, index: torch.Tensor | None) -> torch.Tensor:
    """What the Lab term reads of a view [H,W,3]: its block means [h,w,3], or [P,3] of them at ``index``."""
    means = block_mean(img, lab_block_px(img.shape[0], block))
    return means if index is None else means.reshape(-1, 3).index_select(0, index)


def lab_targets(recolored: list, painting: torch.Tensor, sigma: str, block: float = 0.0,
                index: list | None = None) -> list:
    """Per view the Lab term's target (μ_a, μ_b, σ_a, σ_b) [4]: the recolored photo's statistics over the means of
    blocks ``block`` x its height on a side (0: per pixel), over the blocks ``index`` names (``lab_blocks``; None:
    all); with ``sigma`` "painting" each σ raised to at least the painting's [h,w,3] (over blocks of the first view's
    size in pixels: the painting's working size puts its strokes at the view's scale; the means stay the view's)."""
    from ..losses import lab_chroma_stats

    index = index or [None] * len(recolored)
    stats = [lab_chroma_stats(lab_input(r, block, i)) for r, i in zip(recolored, index)]
    if sigma == "photo":
        return stats
    n = lab_block_px(recolored[0].shape[0], block)
    floor = lab_chroma_stats(block_mean(painting.to(recolored[0]), n))[2:]  # [2] the painting's σ_a, σ_b
    return [torch.cat([st[:2], torch.maximum(st[2:], floor)]) for st in stats]


def jitter_palette_(sh_dc: torch.Tensor, painting: torch.Tensor, amount: float, seed: int) -> torch.Tensor:
    """Moves every Gaussian's DC colour [N,1,3] by ``amount`` x (one random pixel of ``painting`` [H,W,3] minus the
    painting's mean colour), in place; returns the offsets [N,3] in colour units."""
    gen = torch.Generator().manual_seed(int(seed))
    px = painting.detach().reshape(-1, 3).double().cpu()  # [P,3]
    pick = torch.randint(0, px.shape[0], (sh_dc.shape[0],), generator=gen)
    return _shift_dc_(sh_dc, amount * (px[pick] - px.mean(0)))


def jitter_palette_tone_(sh_dc: torch.Tensor, painting: torch.Tensor, amount: float, seed: int,
                         bins: int = 16) -> torch.Tensor:
    """Moves every Gaussian's DC colour [N,1,3] by ``amount`` x (one random pixel of ``painting`` [H,W,3] from the
    splat's tone band minus that band's mean colour), in place; returns the offsets [N,3] in colour units. The bands
    split the painting's pixels by luminance into ``bins`` of equal count; a splat falls in the band of its own
    luminance. So a splat keeps its tone and takes a hue the painting has at that tone (a bright floor flecks of its
    pale yellows and pale blues, not of its dark blue), where ``jitter_palette_`` draws from the whole painting."""
    from ..losses.color import LUMA  # lazy: the losses package imports Warp

    gen = torch.Generator().manual_seed(int(seed))
    px = painting.detach().reshape(-1, 3).double().cpu()  # [P,3]
    luma = torch.tensor(LUMA, dtype=torch.float64)
    order = torch.argsort(px @ luma)
    px = px[order]  # [P,3] by luminance
    lum = px @ luma  # [P] ascending
    bins = max(1, min(int(bins), px.shape[0]))
    edges = torch.linspace(0, px.shape[0], bins + 1, dtype=torch.float64).round().long()  # [bins+1]: band b's pixels
    # are px[edges[b]:edges[b+1]]
    sums = torch.cat([torch.zeros(1, 3, dtype=torch.float64), px.cumsum(0)])  # [P+1,3]
    means = (sums[edges[1:]] - sums[edges[:-1]]) / (edges[1:] - edges[:-1])[:, None]  # [bins,3]
    colour = 0.5 + SH_C0 * sh_dc.detach()[:, 0].double().cpu()  # [N,3]
    band = torch.searchsorted(lum[edges[1:-1]], (colour @ luma).contiguous(), right=True)  # [N] in [0, bins)
    count = edges[band + 1] - edges[band]  # [N]
    u = torch.rand(band.shape[0], generator=gen, dtype=torch.float64)  # [N]
    pick = edges[band] + (u * count).long().minimum(count - 1)  # [N] one pixel of each splat's band
    return _shift_dc_(sh_dc, amount * (px[pick] - means[band]))


def inverse_depth(depth: torch.Tensor) -> torch.Tensor:
    """1/z where something was rendered (depth > 0), 0 elsewhere."""
    return torch.where(depth > 0, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))


def anchor_norm(x: torch.Tensor, anchor: torch.Tensor) -> torch.Tensor:
    """‖x − anchor‖₂ with a zero (not NaN) gradient at x = anchor."""
    return torch.sqrt(((x - anchor) ** 2).sum() + NORM_EPS)


def flow_field_tensor(doubled: torch.Tensor) -> torch.Tensor:
    """[H,W,2] doubled-angle field -> [H,W,3] (c·cos2θ, c·sin2θ, c), the layout flow_terms takes."""
    return torch.cat([doubled, doubled.norm(dim=-1, keepdim=True)], -1).contiguous()


def flow_terms(g, cam, fld, weights):
    """The flow energies (paper eq. 1 + anisotropy), the Warp kernel of tlvg_warp.flow."""
    from ..flow import flow_terms as _flow_terms  # lazy: imports Warp

    return _flow_terms(g, cam, fld, weights)


# --- what the run needs once -------------------------------------------------------------------------------------
@dataclass
class Targets:
    """The painting and the per-view targets, computed once per run (``prepare``)."""

    style_work: torch.Tensor  # the painting at its working size [hs,ws,3] (CPU)
    style_field: tuple  # (θ, coherence, doubled) numpy at the working size
    style_feats: torch.Tensor  # [768, Ns'] the style term's target features (at most style_max_cells: thin_cells)
    style_feats_rgb: torch.Tensor | None  # [768, Ns'] RGB features of the painting (the colour style term), or None
    match_feats: torch.Tensor  # [768, Ns] luminance features, every cell: the field match (once per view)
    style_doubled_cells: torch.Tensor  # the painting's doubled-angle field at its feature cells
    recolored: list  # per view [H,W,3]: the photos in the painting's palette (pre-process and Lab targets)
    lab_stats: list  # per view: the Lab term's target statistics (``lab_targets``, once)
    palette: object  # that colour map (losses.palette: AffinePalette or TonePalette; its recolor_sh for Gaussians)
    photo_feats: list  # per view [768, Nc]: VGG features of the photo, RGB (or luminance: loss.content_on), for content
    inv_depth: list  # per view [H,W]: the un-stylized scene's inverse depth
    originals: list  # per view [H,W,3] (CPU): renders of the un-stylized scene
    coverage: list = field(default_factory=list)  # per view [H,W,1]: the un-stylized scene's alpha (on the device)
    content_scale: list = field(default_factory=list)  # per view: what the content MSE is multiplied by (1, or
    # 1 / the photo features' mean square with loss.content_norm)
    colours: torch.Tensor | None = None  # [K,3] on the device: the painting's dominant colours (the snap term's)
    lab_index: list = field(default_factory=list)  # per view: the Lab term's blocks (``lab_blocks``) or None: all
    style_feats_coarse: torch.Tensor | None = None  # [768, Ns/4] the style term's painting features one octave
    # coarser (loss.w_style_coarse), or None
    style_feats_deep: torch.Tensor | None = None  # [1536, Ns/4] the painting's conv4 features (loss.w_style_deep)


def cell_stride(h: int, w: int, max_cells: int) -> int:
    """The smallest stride s with every s-th row and column of an h x w grid at most ``max_cells`` cells (1 when
    the grid fits or ``max_cells`` is 0: no limit)."""
    s = 1
    while max_cells and (-(-h // s)) * (-(-w // s)) > max_cells:
        s += 1
    return s


def thin_cells(feats: torch.Tensor, max_cells: int) -> torch.Tensor:
    """[1,C,h,w] painting features -> [C, n]: every s-th row and column (``cell_stride``), flattened row-major, so the
    style match compares a view cell with at most ``max_cells`` painting cells (``style_max_cells``)."""
    s = cell_stride(feats.shape[-2], feats.shape[-1], max_cells)
    return feats[..., ::s, ::s].reshape(feats.shape[-3], -1).contiguous()  # [C, ceil(h/s) * ceil(w/s)]


def prepare(inp: StylizeInputs, cfg: StylizeConfig, vgg, device, bg) -> Targets:
    # lazy: imports Warp
    from ..losses import field_at_cells, flatten_feats, luminance, match_detail, resize_style, stroke_field
    from ..losses.palette import AffinePalette, dark_object_note, painting_colours, palette_transfer

    style_np = inp.style.detach().cpu().numpy().astype(np.float32)
    view_h = int(np.median([c.height for c in inp.cameras]))
    style_work = torch.from_numpy(resize_style(style_np, cfg.style_work_height(view_h))).contiguous()  # [hs,ws,3]
    with torch.no_grad():
        style_rgb = style_work.to(device)
        style_lum = luminance(style_rgb)
        sf_lum = vgg(style_lum, scale=1.0)  # [1,768,fh,fw]: the field match
        need_rgb = not cfg.loss.luminance_only or cfg.loss.w_style_color > 0
        sf_rgb = vgg(style_rgb, scale=1.0) if need_rgb else None
        sf = sf_lum if cfg.loss.luminance_only else sf_rgb
        # the coarse style term's: the same input at half the working size (the render's side: vgg_scale / 2)
        sf_coarse = (vgg(style_lum if cfg.loss.luminance_only else style_rgb, scale=COARSE)
                     if cfg.loss.w_style_coarse > 0 else None)
        # the deep style term's: the same input's conv4 block
        sf_deep = (vgg.deep_features(style_lum if cfg.loss.luminance_only else style_rgb)
                   if cfg.loss.w_style_deep > 0 else None)
    s_theta, s_coh, s_doubled = stroke_field(style_work.numpy())
    cells = torch.from_numpy(field_at_cells(s_doubled, tuple(sf_lum.shape[-2:]))).to(device)
    photos = [p.to(device=device, dtype=torch.float32).contiguous() for p in inp.photos]
    g_in = inp.gaussians.detach().to(device=device, dtype=torch.float32)
    inv_depth, photo_feats, originals, coverage = [], [], [], []
    with torch.no_grad():
        for photo, cam in zip(photos, inp.cameras):
            ro = render(g_in, cam, bg)
            inv_depth.append(inverse_depth(ro.depth))
            originals.append(ro.color.clamp(0, 1).cpu())
            coverage.append(ro.alpha.clamp(0, 1)[..., None].contiguous())
            content_in = luminance(photo) if cfg.loss.content_on == "luminance" else photo
            photo_feats.append(flatten_feats(vgg(content_in, scale=cfg.vgg_scale)))  # content: RGB or luminance
    if cfg.keep_colors:  # the scene's own colours: the photos are the pre-process and Lab targets as they are
        recolored, palette = photos, AffinePalette.identity()
    else:
        recolored, palette = palette_transfer(photos, style_work.to(device), cfg.palette_map, coverage=coverage,
                                              floor=cfg.palette_floor, where=cfg.palette_where,
                                              smooth=cfg.palette_smooth, focus=cfg.palette_focus)
        note = dark_object_note(photos, coverage, style_work, cfg.palette_map, cfg.palette_where)
        if note:
            print(note)
        if cfg.palette_detail:  # the painting's level of luminance detail back into the pre-process targets
            recolored, _ = match_detail(recolored, inp.style.to(device=device, dtype=torch.float32))
        # the background the scene does not cover stays the photo's (a Blender scene's white): a recoloured
        # background would make the fit grow splats to paint it
        recolored = [over_background(r, c, p) for r, c, p in zip(recolored, coverage, photos)]
    lab_index = lab_blocks(coverage, cfg.loss.lab_block) if cfg.loss.lab_where == "covered" else [None] * len(coverage)
    return Targets(style_work, (s_theta, s_coh, s_doubled), thin_cells(sf, cfg.style_max_cells),
                   None if sf_rgb is None else thin_cells(sf_rgb, cfg.style_max_cells),
                   flatten_feats(sf_lum).contiguous(), cells, recolored,
                   lab_targets(recolored, style_work, "photo" if cfg.keep_colors else cfg.loss.lab_sigma,
                               cfg.loss.lab_block, lab_index),
                   palette, photo_feats, inv_depth, originals, coverage,
                   [content_scale(f, cfg.loss.content_norm) for f in photo_feats],
                   painting_colours(style_work, cfg.loss.palette_colours, cfg.seed).to(device)
                   if cfg.loss.w_palette_snap > 0 and not cfg.keep_colors else None, lab_index=lab_index,
                   style_feats_coarse=None if sf_coarse is None else flatten_feats(sf_coarse).contiguous(),
                   style_feats_deep=None if sf_deep is None else flatten_feats(sf_deep).contiguous())


def content_scale(photo_feats: torch.Tensor, normalized: bool) -> float:
    """1, or 1 / the mean square of a view's photo features (read once per view, at the run's start)."""
    return 1.0 / max(float((photo_feats.double() ** 2).mean()), 1e-12) if normalized else 1.0


@torch.no_grad()
def holes_now(g: Gaussians, cams: list, coverage: list, background) -> float:
    """Fraction of the pixels the un-stylized scene covers (``coverage``: per view [H,W,1]) that ``g`` leaves
    uncovered, over every view: the evaluation's holes at training size, measured inside the run so that the
    metrics say which phase opened them."""
    lost = covered = 0
    for cam, cov in zip(cams, coverage):
        was = cov[..., 0] >= HOLE_ALPHA  # [H,W]
        lost = lost + (was & (render(g, cam, background, depth=False).alpha < HOLE_ALPHA)).sum()
        covered = covered + was.sum()
    return float(lost) / max(1, int(covered))  # one host sync per phase


def over_background(img: torch.Tensor, coverage: torch.Tensor, background) -> torch.Tensor:
    """``img`` where the un-stylized scene covers the view (alpha ``coverage`` [H,W,1]), ``background`` (an image
    or an RGB triple) where it does not. Real captures are covered everywhere: there it returns ``img``."""
    bg = background if torch.is_tensor(background) else _background_tensor(tuple(background), img.dtype, img.device)
    return coverage * img + (1.0 - coverage) * bg


_backgrounds: dict = {}  # (rgb, dtype, device) -> tensor: made once, since a copy from the host waits for the GPU


def _background_tensor(rgb: tuple, dtype, device) -> torch.Tensor:
    key = (rgb, dtype, str(device))
    t = _backgrounds.get(key)
    if t is None:
        t = _backgrounds[key] = torch.tensor(rgb, dtype=dtype, device=device)
    return t


# --- the Stylize phase -------------------------------------------------------------------------------------------
class Stylize(Phase):
    """The style, content, geometry and flow terms (SPEC §3) against targets made at its start: the opacity /
    scale anchors (tracked by density control) and the per-view stroke fields."""

    TERMS = STYLIZE_TERMS
    STAGES = ("vgg", "style", "terms", "flow")

    def __init__(self, steps: int, cfg: StylizeConfig, tg: Targets, vgg, **kw):
        super().__init__("stylize", steps, **kw)
        from ..losses import StyleLoss  # lazy: imports Warp
        from ..losses.sliced import SlicedWasserstein

        self.cfg, self.tg, self.vgg, w = cfg, tg, vgg, cfg.loss
        self.style_fn = StyleLoss(tg.style_feats, kind=w.style_loss, refresh_every=w.fast_refresh,
                                  cache=w.fast_cache)  # the painting's side computed once
        self.gram_fn = StyleLoss(tg.style_feats, kind="gram") if w.w_style_gram else None
        self.coarse_fn = None if tg.style_feats_coarse is None else StyleLoss(  # prepare makes them when it is on
            tg.style_feats_coarse, kind=w.style_loss, refresh_every=w.fast_refresh, cache=w.fast_cache)
        self.deep_fn = None if tg.style_feats_deep is None else StyleLoss(  # likewise
            tg.style_feats_deep, kind=w.style_loss if w.deep_loss == "same" else "gram_layers",
            refresh_every=w.fast_refresh, cache=w.fast_cache)
        self.color_fn = None if tg.style_feats_rgb is None else StyleLoss(  # prepare makes them when the term is on
            tg.style_feats_rgb, kind=w.style_loss, refresh_every=w.fast_refresh, cache=w.fast_cache)
        # the sliced Wasserstein terms: the painting's feature cells [Ns,768] and its pixels [M,3]
        self.swd_fn = SlicedWasserstein(tg.style_feats.T, w.swd_projections, cfg.seed) if w.w_style_swd else None
        self.color_swd_fn = SlicedWasserstein(
            self.colour_samples(tg.style_work.reshape(-1, 3).to(tg.style_feats.device)),  # [M,3]
            w.color_swd_projections, cfg.seed + 1) if w.w_color_swd else None
        self.covered = None  # per view: the pixels and VGG cells the un-stylized scene covered (find_covered)
        self.fields = None  # per view [H,W,3] on the device
        self.detail_target = None  # the painting's detail energy at the views' height (set up with the fields)
        self.stroke_target = None  # the painting's (E_across, E_along) at the views' height (the stroke hinge's)
        self.stroke_log_eps = stroke_log_eps(w.stroke_contrast)  # None: the hinge reads linear luminance
        self.tone_targets = None  # per view: the recoloured photo's mean luminance over the covered pixels (tone_hold)
        self.stroke_weights = None  # per view [H,W,1]: the pixels the stroke hinge weighs (make_stroke_weights)
        k = w.style_scale  # --strength
        self.const = {"style": w.w_style * k, "style_coarse": w.w_style_coarse * k,
                      "style_deep": w.w_style_deep * k,
                      "style_color": w.w_style_color * k,
                      "style_gram": w.w_style_gram * k,
                      "style_swd": w.w_style_swd * k, "color_swd": w.w_color_swd,
                      "content": w.w_content, "depth": w.w_depth, "tv": w.w_tv,
                      "chroma_tv": w.w_chroma_tv, "palette": w.w_palette_snap * (tg.colours is not None),
                      "detail": w.w_detail * k, "tone_hold": w.w_tone_hold,
                      "stroke": w.w_stroke * k, "coverage": w.w_coverage,
                      "silhouette": w.w_silhouette,
                      "opacity_reg": w.w_opacity_reg, "scale_reg": w.w_scale_reg, "align": w.w_align,
                      "aniso": w.w_aniso, "orient": w.w_orient}
        # a term weighted 0 over the whole phase is not computed at all
        self.on = {t: v != 0 for t, v in self.const.items()}
        self.on["lab"] = w.w_lab_start != 0 or w.w_lab_end != 0
        self.on["style_color"] = self.color_fn is not None and self.const["style_color"] != 0
        self.on["style_coarse"] = self.coarse_fn is not None and self.const["style_coarse"] != 0
        self.on["style_deep"] = self.deep_fn is not None and self.const["style_deep"] != 0
        self.vgg_on = (self.on["style"] or self.on["content"] or self.on["style_color"] or self.on["style_gram"]
                       or self.on["style_swd"] or self.on["style_coarse"] or self.on["style_deep"])
        self.render_weights = self.on["align"] or self.on["aniso"]
        self.field_terms = None  # the orientation and stroke terms as one call (made in setup, with the targets)
        self.terms_graph = None  # on CUDA: image_terms as one graph (made in setup)
        self.content_scales = None  # per view the content scale as a device scalar (image_terms' argument)
        self.over_bg = None  # the run's background, that image_terms composites over
        # the deep term as each conv4 layer's Gram distance reads the render alone (no match, no cache), so it is
        # computed inside image_terms, in the graph; "same" (the style term's kind, a cached match) stays outside
        self.deep_in_terms = self.on["style_deep"] and w.deep_loss == "gram"
        self.deep_grams = None  # the painting's per-layer conv4 Gram matrices (made in setup, outside any graph)
        self.image_names = ([t for t in self.IMAGE_TERMS if self.on[t]]  # image_terms' outputs, in order
                            + ["style_deep"] * self.deep_in_terms)

    def weights(self, k: int) -> dict:
        return dict(self.const, lab=self.cfg.loss.lab_weight(k, self.steps))

    def row(self, k: int) -> dict:
        return {"w_lab": round(self.cfg.loss.lab_weight(k, self.steps), 6)}

    def setup(self, run: Run) -> None:
        p = run.params
        run.density.track("opacity_logits", p.opacity_logits.detach().clone())  # the regularizer anchors
        run.density.track("log_scales", p.log_scales.detach().clone())
        view_h = int(np.median([c.height for c in run.cams]))
        if self.fields is None:  # once per run: a resumed run has its fields (and its jittered colours) saved
            self.fields = self.make_fields(run)
            self.jitter(p, view_h)
        if (self.on["style_swd"] or self.on["color_swd"]) and self.covered is None:
            self.find_covered()
        if self.on["detail"] and self.detail_target is None:
            self.detail_target = painting_detail(self.tg.style_work, view_h)
        if self.on["stroke"] and self.stroke_target is None:
            self.stroke_target = painting_stroke(self.tg.style_work, view_h, self.stroke_log_eps)
        if self.tone_targets is None:  # the colour target's tone per view, once (zeros where the hold is off)
            self.tone_targets = self.make_tone_targets()
        if self.stroke_weights is None:
            self.stroke_weights = self.make_stroke_weights()
        if (self.on["orient"] or self.on["stroke"]) and self.field_terms is None:
            self.field_terms = self.make_field_terms()
        self.over_bg = run.background
        if self.content_scales is None:
            self.content_scales = [torch.tensor(float(c), dtype=f.dtype, device=f.device)
                                   for c, f in zip(self.tg.content_scale, self.tg.photo_feats)]
        if self.deep_in_terms and self.deep_grams is None:  # computed here: a graph's capture would not run them
            self.deep_grams = [g.contiguous() for g in self.deep_fn.style.layer_grams(self.deep_fn.LAYERS)]
        if self.terms_graph is None:
            self.terms_graph = self.make_terms_graph()

    @torch.no_grad()
    def make_tone_targets(self) -> list:
        """Per view the recoloured photo's mean luminance over the pixels the un-stylized scene covers, as a device
        scalar, or per cell [r,c] with ``loss.tone_cells`` (image_terms' argument); zeros where the hold is off."""
        from ..losses import luminance  # lazy: imports Warp

        cov = self.tg.coverage
        if not self.on["tone_hold"]:
            return [torch.zeros((), dtype=c.dtype, device=c.device) for c in cov]
        cells = self.cfg.loss.tone_cells
        return [cell_tones(luminance(r.to(c)), c, cells)[0] for r, c in zip(self.tg.recolored, cov)]

    @torch.no_grad()
    def make_stroke_weights(self) -> list:
        """Per view the stroke hinge's weight [H,W,1]: the un-stylized scene's coverage, or with ``stroke_where``
        interior that coverage eroded by the gradients' reach (an object's outline does not meet the hinge's across
        half for its surface). Once per run: a view constant, like the coverage."""
        from ..losses.stroke_field import gradient_reach, interior_weight  # lazy: imports Warp

        cov = self.tg.coverage
        if self.cfg.loss.stroke_where != "interior":
            return list(cov)
        return [interior_weight(c, gradient_reach()).contiguous() for c in cov]

    def make_field_terms(self):
        """The orientation and stroke terms from one luminance-gradient pass: ~100 small torch ops forward and
        backward, so on CUDA one graph replay each way (orient_cuda_graphs)."""
        from ..losses import field_terms  # lazy: imports Warp
        from ..losses.graphs import GraphedFn

        fn = partial(field_terms, orient=self.on["orient"], along=self.cfg.loss.stroke_along,
                     stroke_target=self.stroke_target if self.on["stroke"] else None,
                     stroke_log_eps=self.stroke_log_eps)
        return GraphedFn(fn) if self.cfg.orient_cuda_graphs else fn

    def jitter(self, p: GaussianParams, view_h: int) -> None:
        """stroke_jitter: a tone (or, in palette mode, a colour of the painting) per splat, at the phase's start."""
        k, seed = self.cfg.stroke_jitter, self.cfg.seed
        if k > 0 and self.cfg.stroke_jitter_mode == "palette":
            jitter_palette_(p.sh_dc, self.tg.style_work, k, seed)
        elif k > 0 and self.cfg.stroke_jitter_mode == "palette_tone":
            jitter_palette_tone_(p.sh_dc, self.tg.style_work, k, seed)
        elif k > 0:  # the painting's stroke contrast at the views' height
            jitter_luminance_(p.sh_dc, k * painting_detail(self.tg.style_work, view_h) ** 0.5, seed)

    @torch.no_grad()
    def make_fields(self, run: Run) -> list:
        """Per view the target stroke field [H,W,3] from the current render ("matched") or the canvas."""
        # lazy: imports Warp
        from ..losses import map_field_canvas, matched_view_field
        from ..losses.style import StyleFeatures

        tg, out, w = self.tg, [], self.cfg.loss
        g = run.params.gaussians()
        painting = StyleFeatures(tg.match_feats)  # its unit columns made once for every view, not once per view
        painting_field = torch.from_numpy(tg.style_field[2]).to(run.device)  # [hs,ws,2] doubled angle
        for i, cam in enumerate(run.cams):
            canvas = None
            if w.field_mapping == "canvas" or w.field_canvas > 0:
                canvas = map_field_canvas(painting_field, cam.height, cam.width)[2]  # [H,W,2]
            if w.field_mapping == "canvas":
                d = canvas
            else:
                img = (tg.originals[i].to(run.device) if w.field_source == "unstylized"
                       else render(g, cam, run.background).color)
                d = matched_view_field(self.vgg, img, painting, tg.style_doubled_cells, self.cfg.vgg_scale)
                if canvas is not None:  # doubled-angle vectors mix as orientations do; coherence weighs each side
                    d = (1 - w.field_canvas) * d + w.field_canvas * canvas.to(d)
            out.append(flow_field_tensor(d.to(device=run.device, dtype=torch.float32)))
        return out

    # the terms read off the render alone (``image_terms`` computes those that are on)
    IMAGE_TERMS = ("content", "depth", "tv", "chroma_tv", "stroke", "coverage", "silhouette", "lab", "orient",
                   "tone_hold")
    # terms that read the render too but not in ``image_terms``: with one of them on, the terms stay eager
    EAGER_ONLY = ("style_gram", "style_swd", "style_color", "color_swd", "palette", "detail")

    def make_terms_graph(self):
        """On CUDA the render-only terms (``image_terms``) as one graph each way (``terms_cuda_graphs``): about a
        hundred small torch kernels a step, each launched by the host, become one replay. None where it does not
        apply (CPU, the option off, a term of EAGER_ONLY on, the Lab term on a subset of blocks)."""
        from ..losses.graphs import GraphedFn  # lazy: imports Warp

        if (not self.cfg.terms_cuda_graphs or any(self.on[t] for t in self.EAGER_ONLY)
                or any(i is not None for i in self.tg.lab_index) or not self.tg.coverage[0].is_cuda):
            return None
        return GraphedFn(partial(self.image_terms, in_graph=True), n_grad=3)

    def graphed_terms(self, args: tuple) -> torch.Tensor | None:
        """``image_terms`` replayed from its graph, or None (no graph: the caller runs it eagerly). A first capture
        that fails (a kernel the capture cannot record) says so once and leaves the run eager."""
        g = self.terms_graph
        if g is None:
            return None
        try:
            return g(*args)
        except RuntimeError as e:
            if g.graphs:  # captured before: a failure of its own, not the capture's
                raise
            warnings.warn(f"the stylize terms run eagerly: their CUDA graph could not be captured ({e})")
            self.terms_graph = None
            return None

    def image_terms(self, color, alpha, depth, coverage, field, stroke_weight, photo_feats, content_scale, inv_depth,
                    lab_stats, tone_target, in_graph: bool = False,
                    lab_index: torch.Tensor | None = None) -> torch.Tensor:
        """The terms read off the render alone and the VGG features the style terms match, packed: [T + F], the
        ``image_names`` terms, then (with VGG on) the style term's features [768, Nc] flat (the match reads
        and caches per view, so it stays outside), and with ``style_color`` the RGB ones after them. From the
        render's colour [H,W,3], alpha [H,W] and depth [H,W] and the view's constants: coverage [H,W,1], stroke
        field [H,W,2], the stroke hinge's weight [H,W,1] (``make_stroke_weights``), photo features [768,Nc],
        content scale [], inverse depth [H,W], Lab target statistics [4], the colour target's covered tone [] or per
        cell [r,c] (``tone_hold``, ``loss.tone_cells``; 0 where it is off). The deep term as Gram distances
        (``deep_in_terms``) is the last of the terms; its other kind's conv4 features [1536, Nc/4] come last.
        One tensor in terms of tensors only, so that on CUDA the call replays as one graph each way (``in_graph``:
        inside it the VGG pass and the field terms run as plain calls, not graphs of their own, and the Lab term
        through torch's kernels, not Warp's). The graph's output buffer is overwritten by the next view's replay:
        the loop reads the terms (logs them, runs the backward) within the step."""
        # lazy: imports Warp
        from ..losses import content_loss, gray_gradient, lab_chroma_loss, luminance
        from ..losses.color import lab_chroma_loss_torch
        from ..losses.style import layered_gram_loss

        on, out = self.on, []
        # the style and content terms see the render only where the scene was: pixels of an empty background
        # (a Blender scene's white) would otherwise pull splats out to paint them
        img = over_background(color, coverage, self.over_bg)
        # what the luminance-only terms see: the same image, its gradient along the grey axis with luminance_grad gray
        img_y = gray_gradient(img) if self.cfg.loss.luminance_grad == "gray" else img
        # one VGG batch per step, each input once: the style term's first (luminance with luminance_only, else RGB),
        # then the content term's (loss.content_on) and style_color's RGB where they differ from it
        style_in = "y" if self.cfg.loss.luminance_only else "rgb"
        content_in = "y" if self.cfg.loss.content_on == "luminance" else "rgb"
        need = [style_in] + [content_in] * on["content"] + ["rgb"] * on["style_color"]
        keys = list(dict.fromkeys(need)) if self.vgg_on else []
        kw = {"graphs": False} if in_graph else {}  # no graph of the pass's own inside this one
        inputs = {"y": luminance(img_y) if "y" in keys else None, "rgb": img}  # each once (the coarse pass reuses it)
        # with the deep term, the style term's input through the conv4 block too, continued from this pass's relu3
        deep_kw = {"deep": True} if on["style_deep"] else {}
        passed = self.vgg.features_of([inputs[k] for k in keys], self.cfg.vgg_scale, **kw, **deep_kw) if keys else []
        deep = passed.pop() if on["style_deep"] else None  # [1536, ~Nc/4]
        by_input = dict(zip(keys, passed))
        a, a_rgb = by_input.get(style_in), by_input.get("rgb")  # the style term's features; style_color's
        if on["content"]:
            out.append(content_loss(by_input[content_in], photo_feats) * content_scale)
        if on["depth"]:
            out.append(((inverse_depth(depth) - inv_depth) ** 2).mean())
        if on["tv"]:
            out.append(tv_loss(img))
        if on["chroma_tv"]:
            out.append(chroma_tv_loss(img, self.cfg.loss.chroma_tv_space))
        if on["orient"] or on["stroke"]:
            # orient: the render's own orientation against the view's stroke field; stroke: contrast across the
            # field up to the painting's, along it no more than it
            fn = self.field_terms
            orient, stroke = (getattr(fn, "fn", fn) if in_graph else fn)(img_y, field, stroke_weight).unbind()
            if on["stroke"]:
                out.append(stroke)
        if on["coverage"]:
            out.append(coverage_loss(alpha, coverage))
        if on["silhouette"]:
            out.append(silhouette_loss(alpha, coverage, self.cfg.loss.silhouette_where))
        if on["lab"]:
            lab_in = lab_input(img, self.cfg.loss.lab_block, lab_index)
            out.append(lab_chroma_loss_torch(lab_in, lab_stats) if in_graph
                       else lab_chroma_loss(lab_in, target_stats=lab_stats))
        if on["orient"]:
            out.append(orient)
        if on["tone_hold"]:  # the covered mean luminance (per cell with tone_cells) held within tone_margin of the
            # colour target's
            y = inputs["y"] if inputs["y"] is not None else luminance(img_y)
            out.append(tone_hold_loss(y, coverage, tone_target, self.cfg.loss.tone_margin, self.cfg.loss.tone_cells))
        if self.deep_in_terms:  # each conv4 layer's Gram distance to the painting's (image_names ends with it)
            out.append(layered_gram_loss(deep, self.deep_grams))
        feats = [] if a is None else [a.reshape(-1)] + ([a_rgb.reshape(-1)] if on["style_color"] else [])
        if on["style_coarse"]:  # the style term's input once more, one octave coarser (a pass of a quarter the cells)
            feats.append(self.vgg.features_of([inputs[style_in]], self.cfg.vgg_scale * COARSE, **kw)[0].reshape(-1))
        if on["style_deep"] and not self.deep_in_terms:  # (config: not with the coarse term)
            feats.append(deep.reshape(-1))
        return torch.cat([torch.stack(out) if out else img.new_zeros(0), *feats])

    def terms(self, run: Run, view: View) -> dict:
        tg, on, t, vi, o = self.tg, self.on, run.timer, view.index, view.out
        p, anchors = run.params, run.density.tracked
        args = (o.color, o.alpha, o.depth, tg.coverage[vi], self.fields[vi][..., :2], self.stroke_weights[vi],
                tg.photo_feats[vi], self.content_scales[vi], tg.inv_depth[vi], tg.lab_stats[vi], self.tone_targets[vi])
        packed = self.graphed_terms(args) if o.color.is_cuda and torch.is_grad_enabled() else None
        if packed is None:
            packed = self.image_terms(*args, lab_index=tg.lab_index[vi])
        n, c, nc = len(self.image_names), *tg.photo_feats[vi].shape
        found = dict(zip(self.image_names, packed[:n].unbind()))
        k = 1 + on["style_color"]
        feats = packed[n:n + k * c * nc].view(-1, c, nc)  # [1|2,768,Nc]: luminance (and RGB) features
        t.mark("vgg")
        if on["style"]:
            found["style"] = self.style_fn(feats[0], key=vi)  # the key: a view's match may be reused (fast_refresh)
        if on["style_coarse"]:  # [768, ~Nc/4] after them
            found["style_coarse"] = self.coarse_fn(packed[n + k * c * nc:].view(c, -1), key=vi)
        if on["style_deep"] and not self.deep_in_terms:  # [1536, ~Nc/4] after them (the coarse term is off)
            found["style_deep"] = self.deep_fn(packed[n + k * c * nc:].view(self.tg.style_feats_deep.shape[0], -1),
                                               key=vi)
        t.mark("style")
        if any(on[name] for name in self.EAGER_ONLY):
            found.update(self.eager_terms(run, view, feats))
        if on["opacity_reg"]:
            found["opacity_reg"] = anchor_norm(p.opacity_logits, anchors["opacity_logits"])
        if on["scale_reg"]:
            found["scale_reg"] = anchor_norm(p.log_scales, anchors["log_scales"])
        t.mark("terms")
        if self.render_weights:
            found["align"], found["aniso"] = flow_terms(view.gaussians, view.cam, self.fields[vi], view.out.weights)
        t.mark("flow")
        return {name: found[name] for name in STYLIZE_TERMS if name in found}  # the sum's order is the logged one

    def eager_terms(self, run: Run, view: View, feats: torch.Tensor) -> dict:
        """The EAGER_ONLY terms that are on, from the step's VGG features ``feats`` [1|2,768,Nc] and the render."""
        from ..losses import detail_energy  # lazy: imports Warp
        from ..losses.palette import palette_snap_loss

        tg, on, vi, out = self.tg, self.on, view.index, {}
        img = over_background(view.out.color, tg.coverage[vi], run.background)
        if on["style_gram"]:  # texture statistics over the whole view: strokes where matching finds none
            out["style_gram"] = self.gram_fn(feats[0])
        if on["style_swd"]:
            out["style_swd"] = self.swd_fn(self.covered_samples(feats[0], vi, feature_cells=True))
        if on["style_color"]:
            out["style_color"] = self.color_fn(feats[1], key=vi)
        if on["color_swd"]:
            out["color_swd"] = self.color_swd_fn(self.colour_samples(self.covered_samples(img, vi)))
        if on["palette"]:
            out["palette"] = palette_snap_loss(img, tg.colours, tg.coverage[vi])
        if on["detail"]:
            out["detail"] = detail_hinge(detail_energy(img, tg.coverage[vi]), self.detail_target)
        return out

    def find_covered(self) -> None:
        """Per view, the pixels and the VGG cells the un-stylized scene covered (alpha >= 0.5; a cell by its mean):
        the sliced Wasserstein terms compare only those with the painting, since a Blender scene's empty background
        is no part of its distribution. One host read per view, here at the phase's start, none in a step."""
        from ..losses import VGG16Features  # lazy: imports Warp

        def covered(cov):  # [h,w] -> indices of the covered entries (all of them if none is)
            flat = cov.reshape(-1)
            idx = torch.nonzero(flat >= HOLE_ALPHA)[:, 0]
            return idx if idx.numel() else torch.arange(flat.numel(), device=flat.device)

        self.covered = [{"pixels": covered(c[..., 0]),
                         "cells": covered(VGG16Features.cell_average(c[..., 0], self.cfg.vgg_scale))}
                        for c in self.tg.coverage]

    def covered_samples(self, x: torch.Tensor, vi: int, feature_cells: bool = False) -> torch.Tensor:
        """The rows of ``x`` where view ``vi``'s un-stylized scene was, [n,D]: ``x`` is the view's pixels [H,W,D],
        or with ``feature_cells`` its VGG features [D, cells] (``VGG16Features.cell_average`` gives their grid)."""
        x = x.T if feature_cells else x.reshape(-1, x.shape[-1])  # [rows, D]
        return x.index_select(0, self.covered[vi]["cells" if feature_cells else "pixels"])

    def colour_samples(self, x: torch.Tensor) -> torch.Tensor:
        """What the colour term compares of pixels [n,3]: their RGB, or (color_swd_space chroma) RGB minus Y."""
        if self.cfg.loss.color_swd_space == "chroma":
            from ..losses import chroma  # lazy: imports Warp

            return chroma(x)
        return x

    def flush_extra(self, run: Run, view: View) -> dict:
        from ..losses import flow_alignment_score_torch  # lazy: imports Warp

        with torch.no_grad():
            s = flow_alignment_score_torch(view.out.color.detach(), self.fields[view.index][..., :2])
        return {"flow_score": round(float(s), 5)}

    def state_dict(self) -> dict:
        return {"fields": [f.cpu() for f in self.fields] if self.fields is not None else None,
                "style_cache": self.style_fn.state_dict(),  # the reused FAST matches (loss.fast_refresh > 1)
                "color_cache": self.color_fn.state_dict() if self.color_fn is not None else None,
                "coarse_cache": self.coarse_fn.state_dict() if self.coarse_fn is not None else None,
                "deep_cache": self.deep_fn.state_dict() if self.deep_fn is not None else None,
                "swd_draws": [f.calls if f is not None else 0 for f in (self.swd_fn, self.color_swd_fn)]}

    def load_state_dict(self, sd: dict, device=None) -> None:
        if sd.get("fields") is not None:
            self.fields = [f.to(device) for f in sd["fields"]]
        if sd.get("style_cache") is not None:
            self.style_fn.load_state_dict(sd["style_cache"], device)
        if sd.get("color_cache") is not None and self.color_fn is not None:
            self.color_fn.load_state_dict(sd["color_cache"], device)
        if sd.get("coarse_cache") is not None and self.coarse_fn is not None:
            self.coarse_fn.load_state_dict(sd["coarse_cache"], device)
        if sd.get("deep_cache") is not None and self.deep_fn is not None:
            self.deep_fn.load_state_dict(sd["deep_cache"], device)
        for f, calls in zip((self.swd_fn, self.color_swd_fn), sd.get("swd_draws") or ()):
            if f is not None:
                f.calls = int(calls)


# --- the run ---------------------------------------------------------------------------------------------------
@dataclass
class StylizeResult:
    gaussians: Gaussians  # the stylized scene (SH degree 0 unless keep_sh)
    inputs: StylizeInputs
    config: StylizeConfig
    style_work: torch.Tensor  # the painting at its working size [hs,ws,3] (CPU)
    style_field: tuple  # (θ, coherence, doubled) numpy at the working size
    fields: list  # per-view target field [H,W,3] (CPU)
    log: list  # one dict per iteration
    metrics: dict  # timings, counts, VGG flag, ...
    vgg_random: bool = False
    vgg_source: str = ""
    originals: list = field(default_factory=list)  # renders of the un-stylized scene per view [H,W,3] (CPU)
    coverage: list = field(default_factory=list)  # per view [H,W] (CPU): the un-stylized scene's alpha


def load_checkpoint(path) -> dict:
    """A stylization checkpoint; one written before train/loop.py is brought to its layout."""
    ck = runs.read_checkpoint(path, CHECKPOINT_FORMAT, "stylize")
    if "phases" not in ck:
        d = dict(ck.get("density") or {})
        if ck.get("anchors") is not None:
            d["tracked"] = ck["anchors"]
        d.setdefault("rng", ck.get("split_rng"))
        d.setdefault("events", ck.get("densify_events", []))
        post = ck.get("post_targets")  # stored as uint8
        ck["density"] = d
        ck["phases"] = {"stylize": {"fields": ck.get("fields")},
                        "post": {"targets": None if post is None else [t.float() / 255.0 for t in post]}}
    return ck


def build_run(inp: StylizeInputs, cfg: StylizeConfig, tg: Targets, vgg, device, dist, out, *,
              fresh: bool = True) -> Run:
    """Parameters, one Adam, density control and the three phases. ``fresh``: a new run (not a resume, whose
    checkpoint brings its own Gaussians): the scene's coarse splats are refined to the stroke size first."""
    from ..losses.color import smooth_chroma
    from ..losses.palette import palette_transfer  # lazy: imports Warp

    cams = list(inp.cameras)
    bg = tuple(float(v) for v in cfg.background)
    n_pre, n_sty, n_post = cfg.phase_steps()
    g_in = inp.gaussians.detach().to(device=device, dtype=torch.float32)
    g_work = g_in if cfg.keep_sh else g_in.with_sh_degree(0)
    if cfg.palette_init and not cfg.keep_colors:  # the same colour map the pre-process targets went through, applied in closed form
        g_work = dataclasses.replace(g_work, sh=tg.palette.recolor_sh(g_work.sh))
    extent = scene_extent(cams)
    budget = cfg.density.budget(g_in.num)  # None without a budget
    refined = {}
    if fresh and cfg.refine_radius > 0:  # before the pre-process, which fits the children to the recoloured photos
        g_work, refined = refine_to_radius(g_work, cams, cfg.refine_radius * cfg.stroke_scale,
                                           budget or int(REFINE_UNCAPPED * g_in.num), background=bg, seed=cfg.seed)
        if dist is not None and dist.world > 1:  # Σ αT sums by float atomics: a near tie may order differently on each
            g_cpu, refined = dist.broadcast_object((g_work.to(device="cpu"), refined))  # GPU, and every rank must
            g_work = g_cpu.to(device=device)  # start from the same Gaussians: rank 0's refinement
    params = GaussianParams(g_work, g_work.sh_degree)
    opt = optimizer(params, cfg, extent)
    density = density_control(cfg, g_work.num, device, cams, extent=extent, n_views=len(cams), dist=dist,
                              start_num=g_in.num)

    def post_targets(run: Run) -> list:  # every view rendered and recolored once more
        with torch.no_grad():
            g = run.params.gaussians()
            rs = [render(g, cam, bg).color.clamp(0, 1) for cam in cams]
        if cfg.keep_colors:
            return rs
        # ARF's transfer whatever palette_map (a global re-match of the stylized views), over palette_where's pixels
        rec = palette_transfer(rs, tg.style_work.to(device), "arf", coverage=tg.coverage, floor=cfg.palette_floor,
                               where=cfg.palette_where)[0]
        if cfg.post_chroma_blur > 0:
            rec = [smooth_chroma(r, cfg.post_chroma_blur * r.shape[0]) for r in rec]
        return [over_background(r, c, x) for r, c, x in zip(rec, tg.coverage, rs)]

    dens = set(cfg.density.phases)
    geo = cfg.geometry
    cap = geo.max_travel / max(n_sty, 1)  # widths per step
    hook = [(tangential_hook(geo.tangential_lambda, cap), ("means",))] if geo.tangential_lambda > 0 or cap > 0 else []
    floor = [(colour_floor_hook(), ())] if cfg.colour_floor else []  # in every phase
    phases = [Fit("pre", n_pre, tg.recolored, density="pre" in dens, hooks=floor),
              Stylize(n_sty, cfg, tg, vgg, density="stylize" in dens, hooks=hook + floor,  # the tangential hook in
                      trainable=[f for f in FIELDS if not (cfg.geometry.lock_xyz and f == "means")]),  # Stylize only
              Fit("post", n_post, make_targets=post_targets, trainable=POST_TRAINABLE, density="post" in dens,
                  hooks=floor, fresh_moments=cfg.post_fresh_adam)]
    run = new_run(cfg, params, opt, density, phases, cams, device=device, background=bg, dist=dist, out=out,
                  fmt=CHECKPOINT_FORMAT, extra=lambda: {"config": dataclasses.asdict(cfg),
                                                        "names": list(inp.names), "sources": inp.sources})
    run.refined = refined  # what the stroke-size refinement did (metrics.json)
    run.on_phase_end = lambda r, _phase: {"holes": holes_now(r.params.gaussians(), cams, tg.coverage, bg)}
    return run


def run_stylize(inp: StylizeInputs, cfg: StylizeConfig, out_dir=None, *, resume=None, overwrite=False,
                progress=True, vgg=None, interrupt_at: int | None = None, quiet=False,
                on_progress=None, dist=None) -> StylizeResult:
    """Run the three phases. ``resume``: a run folder / checkpoint to continue. ``vgg``: a loaded feature
    network (default: load_vgg(cfg.vgg_weights)). ``interrupt_at``: behave as if Ctrl-C came after that
    step (tests). ``on_progress(step, gaussians)``: called at every log flush (every ``log_every`` steps and
    at the end of each phase) with the current Gaussians, detached (the live viewer, ``stylize --view``).
    ``dist``: a ``Dist`` (torchrun; default one process: only its main rank writes files).
    Raises KeyboardInterrupt after saving a checkpoint, StylizeDiverged on NaN."""
    from ..losses import load_vgg  # lazy: imports Warp

    t_start = time.perf_counter()
    cfg = cfg.validate()
    inp.check()
    dist = dist or Dist()
    if dist.world > 1 and cfg.loss.fast_refresh > 1:
        # a view's reused FAST projection lives on the rank that computed it, and a view is not rendered by the
        # same rank every time: N ranks equal one process with N views per step (and resume) only without reuse
        if dist.is_main:
            print(f"note: loss.fast_refresh {cfg.loss.fast_refresh} -> 1 on {dist.world} ranks (each rank would keep "
                  "its own FAST cache)", file=sys.stderr, flush=True)
        cfg = dataclasses.replace(cfg, loss=dataclasses.replace(cfg.loss, fast_refresh=1))
    if cfg.background is None:  # record the resolved background (evaluation re-renders with it)
        cfg = dataclasses.replace(cfg, background=[float(v) for v in inp.background])
    session = Session(cfg, dist)
    device = session.device
    torch.manual_seed(cfg.seed)
    session.open(out_dir, inp.names, resume=resume, overwrite=overwrite, read_checkpoint=load_checkpoint,
                 run_files=RUN_FILES, config_yaml=config_yaml)
    out, ck = session.out, session.checkpoint
    announce = vgg is None  # a caller that passes the network has already said where it came from
    split, t = {}, time.perf_counter()  # the setup's wall time by part (metrics: setup_split_s)
    vgg = (vgg if vgg is not None else load_vgg(cfg.vgg_weights, device)).to(device)
    if device.type == "cuda" and cfg.vgg_channels_last:
        vgg.set_precision(channels_last=True)
    if device.type == "cuda" and cfg.vgg_cuda_graphs:
        vgg.use_cuda_graphs(True)
    split["vgg"], t = time.perf_counter() - t, time.perf_counter()
    tg = prepare(inp, cfg, vgg, device, tuple(cfg.background))
    split["targets"], t = time.perf_counter() - t, time.perf_counter()
    run = build_run(inp, cfg, tg, vgg, device, dist, out, fresh=ck is None)
    split["build"] = time.perf_counter() - t
    start_step = session.resume(run)
    if not quiet and announce and vgg.is_random and dist.is_main:
        print("WARNING: VGG-16 is RANDOMLY initialized (not pretrained): the style/content losses are not "
              "meaningful; a smoke run only")
    train(run, progress=progress, quiet=quiet, on_flush=on_progress, interrupt_at=interrupt_at,
          diverged=StylizeDiverged, hint=" (continue with --resume {out} after lowering the learning rates or loss weights)")
    sty = run.phase("stylize")
    if sty.fields is None:  # no stylize step ran: the fields are still needed for the score
        sty.fields = sty.make_fields(run)

    final = run.params.detached()
    final = final if cfg.keep_sh else final.with_sh_degree(0)
    counts, n_in = run.counts, inp.gaussians.num
    before = counts.get("before_stylize", counts.get("after_pre", n_in))
    metrics = {
        **run.metrics(start_step), "phase_steps": dict(zip(PHASES, cfg.phase_steps())), "setup_time_s": None,
        "device": str(device), "gaussians_input": n_in, "gaussians_before_stylize": before,
        "gaussians_after_stylize": counts.get("after_stylize", before), "gaussians_final": final.num,
        "gaussian_budget": run.density.budget, "extent": run.opt.extent, "flow_terms": "warp kernel",
        "vgg_random": bool(vgg.is_random), "vgg_source": vgg.source, "refine": run.refined or None,
        "holes_by_phase": {p: counts[f"holes_after_{p}"] for p in PHASES if f"holes_after_{p}" in counts},
    }
    metrics["setup_time_s"] = round(time.perf_counter() - t_start - metrics["train_time_s"], 3)
    metrics["setup_split_s"] = {k: round(v, 3) for k, v in split.items()}
    from ..losses.palette import covered_mean_luminance  # lazy: imports Warp

    coverage = [c[..., 0].detach().cpu() for c in tg.coverage]  # [H,W] per view
    # the colour target's tone over the covered pixels: the outputs set the stylized renders' beside it
    metrics["tone_target"] = covered_mean_luminance(tg.recolored, tg.coverage)
    return StylizeResult(final, inp, cfg, tg.style_work, tg.style_field, [f.cpu() for f in sty.fields], run.log,
                         metrics, metrics["vgg_random"], vgg.source, tg.originals, coverage)


__all__ = ["StylizeInputs", "StylizeResult", "StylizeDiverged", "Stylize", "Targets", "prepare", "build_run",
           "run_stylize", "load_checkpoint", "tv_loss", "coverage_loss", "inverse_depth", "anchor_norm", "flow_field_tensor",
           "LOG_TERMS", "STYLIZE_TERMS", "PHASES"]
