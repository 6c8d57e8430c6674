"""SPEC §4 metrics: one ruler for every run.

Every per-view metric of a stylized run is a function of that run's renders and of references (eval/refs.py)
built from the un-stylized scene, the views and the painting only. Nothing here reads what a run stored about
its own targets, and nothing depends on which other runs are scored. ``METRICS`` declares each metric's
words, unit and direction; ``interval`` (bootstrap over views) and ``paired`` (bootstrap of the paired
difference) turn per-view values into summaries and verdicts. All per-pixel work is vectorized.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from .quick import pixel_grid, reproject  # noqa: F401  (re-exported: the reprojection oracle is tested there)

ALPHA_MIN = 0.5  # covered pixel (SPEC §4 holes: alpha >= 0.5)
# Occlusion test of the un-stylized depth: neighbouring views agree to < 1 % on the demo and real scenes;
# an occluder in front differs by far more than 3 %.
DEPTH_REL_TOL = 0.03
KS = (1, 5)  # SPEC §4 view offsets
GRAM_LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3")
CONTENT_LAYERS = ("relu3_3", "relu4_3")
HF_SIGMA = 2.0  # px: "high frequency" = what a Gaussian blur of σ 2 px removes (brush texture, not shapes)
QUANTILES = np.linspace(0.0, 1.0, 101)  # coherence distributions compared at percentiles (1-D Wasserstein)
BOOTSTRAP = 2000  # resamples; the interval's own Monte Carlo error is ~1 % of its width
SEED = 0  # fixed: a run's interval never depends on what else is scored


@dataclass(frozen=True)
class Metric:
    key: str
    words: str
    unit: str
    higher_better: bool
    pretrained: bool = False  # needs pretrained VGG features: "not measured" with random weights
    per_view: bool = True  # False: one number per run (counts, bytes, times): no interval

    @property
    def direction(self) -> str:
        return "higher is better" if self.higher_better else "lower is better"


METRICS = {m.key: m for m in (
    Metric("flow_alignment", "Flow alignment with the painting's strokes (common field)",
           "coherence-weighted mean cos 2(φ−φ*), −1…1", True, pretrained=True),
    Metric("stroke_stats", "Stroke statistics distance to the painting",
           "1-D Wasserstein of structure-tensor coherence, 0…1", False),
    Metric("style_gram", "Style distance, Gram (relu1_2, 2_2, 3_3, 4_3)", "relative Frobenius norm", False,
           pretrained=True),
    Metric("style_nnfm", "Style distance, nearest-neighbour features (relu3)", "mean 1 − cos, 0…2", False,
           pretrained=True),
    Metric("content", "Content distance to the photos (relu3_3, relu4_3, RGB)", "relative MSE", False,
           pretrained=True),
    Metric("consistency_k1", "Multi-view error, neighbouring views (k = 1)", "RMSE of RGB in 0…1", False),
    Metric("consistency_k5", "Multi-view error, views 5 apart (k = 5)", "RMSE of RGB in 0…1", False),
    Metric("detail", "Detail: high-frequency luminance energy vs the painting's", "ratio (1 = painting)", True),
    Metric("holes_1x", "Holes at training size", "fraction of covered pixels", False),
    Metric("holes_2x", "Holes at 2x resolution", "fraction of covered pixels", False),
    Metric("chroma_noise", "Chroma noise: high-frequency Lab a,b energy vs the recolored photos",
           "ratio (1 = photos)", False),
    Metric("gaussians", "Gaussians", "count", False, per_view=False),
    Metric("bytes", "Size of stylized.ply", "bytes", False, per_view=False),
    Metric("wall_time_s", "Wall time of the run", "seconds", False, per_view=False),
)}


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def resize_to_height(img: np.ndarray, height: int) -> np.ndarray:
    """[H,W,C] float resized to ``height`` rows, aspect kept (INTER_AREA shrinking, linear growing)."""
    h, w = img.shape[:2]
    size = (max(1, round(w * height / h)), height)
    interp = cv2.INTER_AREA if height < h else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(img, np.float32), size, interpolation=interp)


# ---------------------------------------------------------------- strokes
def field_at_pixels(field: np.ndarray, h: int, w: int) -> np.ndarray:
    """The reference doubled-angle field [h',w',2] at the render's pixels [h,w,2] (same pixel, same place)."""
    if field.shape[:2] == (h, w):
        return field
    return cv2.resize(np.ascontiguousarray(field, np.float32), (w, h), interpolation=cv2.INTER_LINEAR)


def render_field(img: np.ndarray) -> np.ndarray:
    """The render's own doubled-angle field [H,W,2] (length = coherence), SPEC §3 structure tensor."""
    from ..losses.stroke_field import stroke_field

    return stroke_field(img)[2]


def flow_alignment(render, field) -> float:
    """Σ c·c*·cos 2(φ−φ*) / Σ c·c* of one view: φ, c from the render's structure tensor, φ*, c* the common
    reference field [H,W,2] (doubled angle, length = coherence). A pixel counts as much as both fields are
    coherent there: a flat render patch or a direction-less part of the painting says nothing. NaN when the
    weights vanish (a flat render)."""
    r = _np(render)
    d = render_field(r).astype(np.float64)  # [H,W,2]
    t = field_at_pixels(_np(field), *r.shape[:2]).astype(np.float64)  # [H,W,2]
    den = (np.linalg.norm(d, axis=-1) * np.linalg.norm(t, axis=-1)).sum()
    return float((d * t).sum() / den) if den > 1e-12 else math.nan


def coherence_quantiles(img: np.ndarray) -> np.ndarray:
    from ..losses.stroke_field import stroke_field

    return np.quantile(stroke_field(img)[1], QUANTILES)  # [101]


def stroke_stats(render_eval: np.ndarray, painting_q: np.ndarray) -> float:
    """1-D Wasserstein distance between the coherence distributions of the render (at the evaluation height)
    and of the painting (quantiles ``painting_q``): the mean gap of matching percentiles."""
    return float(np.abs(coherence_quantiles(render_eval) - painting_q).mean())


def hf_energy(x: np.ndarray) -> float:
    """Mean squared residual of a σ HF_SIGMA Gaussian blur, over pixels and channels of [H,W] or [H,W,C]."""
    x = np.ascontiguousarray(x, np.float32)
    return float(((x - cv2.GaussianBlur(x, (0, 0), HF_SIGMA, borderType=cv2.BORDER_REFLECT_101)) ** 2).mean())


def luma(img: np.ndarray) -> np.ndarray:
    return img @ np.array((0.299, 0.587, 0.114), np.float32)  # [H,W]


def lab_ab(img: np.ndarray) -> np.ndarray:
    """Lab a,b [H,W,2] (sRGB, D65) of a float RGB image in [0,1]."""
    return cv2.cvtColor(np.clip(img, 0, 1).astype(np.float32), cv2.COLOR_RGB2Lab)[..., 1:]


# ---------------------------------------------------------------- VGG
VGG_LAYERS = tuple(dict.fromkeys(GRAM_LAYERS + ("relu3_1", "relu3_2") + CONTENT_LAYERS))


def vgg_feats(net, img: np.ndarray) -> dict:
    """One pass of an [H,W,3] image at its given size: {"grams": {layer: [C,C]}, "relu3": [768,N],
    "content": {layer: [1,C,h,w]}}."""
    dev = next(net.parameters()).device
    with torch.no_grad():
        f = net.layers(torch.from_numpy(np.ascontiguousarray(img, np.float32)).to(dev), VGG_LAYERS)
    grams = {}
    for k in GRAM_LAYERS:
        a = f[k].reshape(f[k].shape[1], -1).double()  # [C, N]
        grams[k] = a @ a.T / a.shape[1]
    r3 = torch.cat([f["relu3_1"], f["relu3_2"], f["relu3_3"]], 1)
    return {"grams": grams, "relu3": r3.reshape(r3.shape[1], -1), "content": {k: f[k] for k in CONTENT_LAYERS}}


def style_gram(grams: dict, painting_grams: dict) -> float:
    """Mean over layers of ‖G − G_p‖_F / ‖G_p‖_F (each layer counts the same whatever its magnitude)."""
    return float(np.mean([float((grams[k] - painting_grams[k]).norm() / painting_grams[k].norm().clamp_min(1e-12))
                          for k in GRAM_LAYERS]))


def style_nnfm(feats: torch.Tensor, painting_feats: torch.Tensor) -> float:
    """ARF's NNFM distance: mean over render cells of min over painting cells of 1 − cos."""
    a = F.normalize(feats.double(), dim=0)
    s = F.normalize(painting_feats.double(), dim=0)
    return float((1.0 - (a.T @ s).max(dim=1).values).mean())


def content(feats: dict, photo_feats: dict) -> float:
    """Mean over CONTENT_LAYERS of ‖f − f_photo‖² / ‖f_photo‖² (RGB, same evaluation size)."""
    return float(np.mean([float(((feats[k] - photo_feats[k]) ** 2).sum() / (photo_feats[k] ** 2).sum().clamp_min(1e-12))
                          for k in CONTENT_LAYERS]))


# ---------------------------------------------------------------- geometry
def sample_nearest(img: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """img [H,W] or [H,W,C] at pixel coordinates (u, v) [...] (pixel centers at +0.5), nearest, clamped."""
    h, w = img.shape[:2]
    j = (u - 0.5).round().long().clamp(0, w - 1)
    i = (v - 0.5).round().long().clamp(0, h - 1)
    return img[i, j]


def correspondences(base_i: dict, base_j: dict, cam_i, cam_j, rel_tol: float = DEPTH_REL_TOL):
    """Pixels of view i that the un-stylized scene shows in view j: (mask [H,W], u_j, v_j [H,W]).
    Covered in i, in front of j, inside j, covered there and not occluded (|z_j − D_j| <= rel_tol·z_j with
    nearest-pixel depth: a bilinear depth would blend across an occlusion edge)."""
    d = torch.as_tensor(base_i["depth"], dtype=torch.float64)
    uj, vj, zj = reproject(d, cam_i, cam_j)
    inside = (uj >= 0.5) & (uj <= cam_j.width - 0.5) & (vj >= 0.5) & (vj <= cam_j.height - 0.5)
    aj = torch.as_tensor(base_j["alpha"], dtype=torch.float64)
    dj = torch.as_tensor(base_j["depth"], dtype=torch.float64)
    mask = (torch.as_tensor(base_i["alpha"]) >= ALPHA_MIN) & (zj > cam_j.near) & inside
    mask &= (sample_nearest(aj, uj, vj) >= ALPHA_MIN) & ((zj - sample_nearest(dj, uj, vj)).abs() <= rel_tol * zj.abs())
    return mask, uj, vj


def pair_error(view_i: dict, view_j: dict, corr) -> float:
    """RMSE of stylized colors over the corresponding pixels; a pixel the stylized scene leaves uncovered in
    either view (alpha < 0.5) counts as full error (1 per channel) instead of being dropped. NaN when the
    un-stylized views share no pixel."""
    mask, uj, vj = corr
    if not bool(mask.any()):
        return math.nan
    ci = torch.as_tensor(view_i["color"], dtype=torch.float64)
    cj = torch.as_tensor(view_j["color"], dtype=torch.float64)
    h, w = cj.shape[:2]
    grid = torch.stack([2 * uj / w - 1, 2 * vj / h - 1], -1).unsqueeze(0)  # align_corners=False
    cs = F.grid_sample(cj.permute(2, 0, 1).unsqueeze(0), grid, mode="bilinear", padding_mode="border",
                       align_corners=False)[0].permute(1, 2, 0)  # [H,W,3]
    err = ((cs - ci) ** 2).mean(-1)  # [H,W]
    hole = (torch.as_tensor(view_i["alpha"]) < ALPHA_MIN) | (
        sample_nearest(torch.as_tensor(view_j["alpha"]), uj, vj) < ALPHA_MIN)
    err = torch.where(hole, torch.ones_like(err), err)
    return float(err[mask].mean().sqrt())


def holes(alpha, base_alpha) -> float:
    """Fraction of the pixels the un-stylized scene covers that the stylized scene leaves uncovered."""
    a, b = _np(alpha), _np(base_alpha)
    cov = b >= ALPHA_MIN
    return float((cov & (a < ALPHA_MIN)).sum() / max(1, cov.sum()))


# ---------------------------------------------------------------- statistics
def interval(values, seed: int = SEED, n: int = BOOTSTRAP) -> dict:
    """Mean and 95% bootstrap percentile interval over views (NaN views dropped). Deterministic."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], np.float64)
    if x.size == 0:
        return {"mean": None, "lo": None, "hi": None, "n": 0}
    means = x[np.random.default_rng(seed).integers(0, x.size, (n, x.size))].mean(1)  # [n]
    lo, hi = np.percentile(means, [2.5, 97.5])
    return {"mean": float(x.mean()), "lo": float(lo), "hi": float(hi), "n": int(x.size)}


def paired(a, b, metric: Metric) -> dict:
    """A vs B on the same views: the mean paired difference a − b with its 95% bootstrap interval, and the
    verdict "a", "b" or "no difference" (when the interval contains 0)."""
    pa = np.asarray([math.nan if v is None else v for v in a], np.float64)
    pb = np.asarray([math.nan if v is None else v for v in b], np.float64)
    if pa.shape != pb.shape:
        raise ValueError(f"{metric.key}: {pa.size} vs {pb.size} views")
    ok = np.isfinite(pa) & np.isfinite(pb)
    ci = interval(pa[ok] - pb[ok])
    if ci["n"] == 0:
        return {**ci, "better": None}
    if ci["lo"] <= 0.0 <= ci["hi"]:
        better = "no difference"
    else:
        better = "a" if (ci["mean"] > 0) == metric.higher_better else "b"
    return {**ci, "better": better}
