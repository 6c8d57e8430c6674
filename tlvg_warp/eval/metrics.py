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

from ..losses.stroke_field import stroke_field, structure_tensor
from .quick import pixel_grid, reproject  # noqa: F401  (re-exported: the reprojection oracle is tested there)

ALPHA_MIN = 0.5  # covered pixel (SPEC §4 holes: alpha >= 0.5)
# Occlusion test of the un-stylized depth: neighbouring views agree to < 1 % on the demo and real scenes;
# an occluder in front differs by far more than 3 %.
DEPTH_REL_TOL = 0.03
KS = (1, 5)  # SPEC §4 view offsets
GRAM_LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3")
CONTENT_LAYERS = ("relu3_3", "relu4_3")
HF_SIGMA = 2.0  # px: "high frequency" = what a Gaussian blur of σ 2 px removes (brush texture, not shapes)
# Stroke statistics (target-free): structure tensors of the luminance at these Gaussian scales, in pixels of the
# image resized to STROKE_HEIGHT rows (so a scale is a fixed fraction of the image height whatever its size);
# each scale's tensor is integrated over twice its scale. 1-8 px at 256 rows spans a fine dab to a long sweep.
STROKE_SCALES = (1.0, 2.0, 4.0, 8.0)
STROKE_HEIGHT = 256
STROKE_QUANTILES = np.linspace(0.02, 0.98, 49)  # distributions compared at these percentiles (1-D Wasserstein)
# Weight of the energy term (decades of log10 energy) against the coherence term (0..1): measured on photos and
# paintings, a decade of energy spread is worth ~4x a coherence spread; this weight makes the two comparable.
STROKE_ENERGY_WEIGHT = 0.25
STROKE_EPS = 1e-3  # in units of the standardized luminance's squared gradient: flat pixels do not blow up log10
TONE_QUANTILES = np.linspace(0.01, 0.99, 99)  # luminance distributions compared at these percentiles
# Chroma distributions (Lab a,b) are compared along these directions of the a,b plane, each at TONE_QUANTILES: a
# sliced Wasserstein distance, so a blend of two hues (blue and yellow read as one teal) is far from a painting made of
# both, wherever on the canvas each sits
COLOUR_ANGLES = np.arange(16) * np.pi / 16
BOOTSTRAP = 2000  # resamples; the interval's own Monte Carlo error is ~1 % of its width
NNFM_CHUNK = 4096  # render cells per product in style_nnfm
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
    Metric("flow_energy", "Flow alignment weighted by the render's own gradient energy (common field)",
           "Σ e·c*·a·cos 2(φ−φ*) / Σ e·c*, e = λ1+λ2, a = anisotropy, −1…1", True, pretrained=True),
    Metric("stroke_scales", "Stroke statistics distance to the painting (oriented energy at 4 scales)",
           "mean 1-D Wasserstein of coherence + ¼ log10 anisotropic energy", False),
    Metric("style_gram", "Style distance, Gram (relu1_2, 2_2, 3_3, 4_3)", "relative Frobenius norm", False,
           pretrained=True),
    Metric("style_gram_inside", "Style distance, Gram over the feature cells inside the scene (the un-stylized "
           "coverage, its outline excluded, as detail_inside)", "relative Frobenius norm", False, pretrained=True),
    Metric("style_nnfm", "Style distance, nearest-neighbour features (relu3)", "mean 1 − cos, 0…2", False,
           pretrained=True),
    Metric("style_nnfm_inside", "Style distance, nearest-neighbour features over the relu3 cells inside the scene "
           "(as style_gram_inside)", "mean 1 − cos, 0…2", False, pretrained=True),
    Metric("content", "Content distance to the photos (relu3_3, relu4_3, RGB)", "relative MSE", False,
           pretrained=True),
    Metric("consistency_k1", "Multi-view error, neighbouring views (k = 1)", "RMSE of RGB in 0…1", False),
    Metric("consistency_k5", "Multi-view error, views 5 apart (k = 5)", "RMSE of RGB in 0…1", False),
    Metric("detail", "Detail: high-frequency luminance energy vs the painting's", "ratio (1 = painting)", True),
    Metric("detail_inside", "Detail inside the scene: as detail, over the pixels the un-stylized scene covers, "
           "its outline excluded", "ratio (1 = painting)", True),
    Metric("tone_inside", "Tone distance inside the scene: the luminance distribution of the pixels the "
           "un-stylized scene covers (its outline excluded, as detail_inside) against the painting's",
           "1-D Wasserstein of luminance, 0…1", False),
    Metric("colour_inside", "Colour distance inside the scene: the Lab a,b chroma of the pixels the un-stylized "
           "scene covers (its outline excluded, as detail_inside) against the painting's, sliced over 16 directions",
           "sliced 1-D Wasserstein of Lab a,b, Lab units", False),
    Metric("holes_1x", "Holes at training size", "fraction of covered pixels", False),
    Metric("holes_2x", "Holes at 2x resolution", "fraction of covered pixels", False),
    Metric("spill", "Spill: painted where the un-stylized scene is empty (splats frayed or strayed)",
           "fraction of the view", False),
    Metric("chroma_noise", "Chroma noise: high-frequency Lab a,b energy vs the recolored photos",
           "ratio (1 = photos)", False),
    Metric("gaussians", "Gaussians", "count", False, per_view=False),
    Metric("bytes", "Size of stylized.ply", "bytes", False, per_view=False),
    Metric("wall_time_s", "Wall time of the run", "seconds", False, per_view=False),
)}

# The anchors scored beside every run with the same ruler (evaluate builds them itself): the un-stylized scene's
# renders, and the painting pasted in screen space over every view.
UNSTYLIZED, STICKER = "no stylization", "sticker"
ANCHORS = (UNSTYLIZED, STICKER)
# Which anchor each metric exists to beat: a run wins a metric only where its interval also beats this anchor.
#   flow / style / strokes / detail say "it paints": doing nothing (the un-stylized scene) must lose on them;
#   content / multi-view / chroma noise say "it is still the scene, seen in 3D, with clean colour": the painting
#   pasted on the screen (right style, no scene, no 3D) must lose on them.
#   holes: no anchor (both are hole-free by construction; holes compare the run with the un-stylized coverage).
ANCHOR_TO_BEAT = {
    "flow_alignment": UNSTYLIZED,
    "flow_energy": UNSTYLIZED,
    "stroke_scales": UNSTYLIZED,
    "style_gram": UNSTYLIZED,
    "style_gram_inside": UNSTYLIZED,
    "style_nnfm": UNSTYLIZED,
    "style_nnfm_inside": UNSTYLIZED,
    "detail": UNSTYLIZED,
    "detail_inside": UNSTYLIZED,
    "tone_inside": UNSTYLIZED,
    "colour_inside": UNSTYLIZED,
    "content": STICKER,
    "consistency_k1": STICKER,
    "consistency_k5": STICKER,
    "chroma_noise": STICKER,
    "holes_1x": None,
    "holes_2x": None,
    "spill": None,  # likewise: the un-stylized scene spills nothing by construction, a sticker covers every pixel
}


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


def flow_energy(render, field) -> float:
    """Σ e·c*·cos 2(φ−φ*)·a / Σ e·c* of one view, where the render's structure tensor has energy e = λ1+λ2 and
    anisotropy a = (λ1−λ2)/(λ1+λ2): the share of the render's visible gradient energy that runs across the
    painting's strokes (along them, as strokes do), weighted by the reference field's coherence c*. Unlike
    ``flow_alignment`` it weighs a pixel by how much contrast it has: faint streaks in a flat passage count as
    little as they show. NaN when the weights vanish."""
    r = _np(render)
    jxx, jxy, jyy = (j.astype(np.float64) for j in structure_tensor(r))
    t = field_at_pixels(_np(field), *r.shape[:2]).astype(np.float64)  # [H,W,2], length c*
    # the doubled-angle vector of the stroke direction, times λ1−λ2: −(Jxx−Jyy, 2Jxy) (stroke_field's convention)
    num = (-(jxx - jyy) * t[..., 0] - 2.0 * jxy * t[..., 1]).sum()
    den = ((jxx + jyy) * np.linalg.norm(t, axis=-1)).sum()
    return float(num / den) if den > 1e-12 else math.nan


def _stroke_tensors(img: np.ndarray, mask=None):
    """Per scale σ of STROKE_SCALES: (anisotropic energy λ1−λ2, energy λ1+λ2) at the pixels of ``mask``, of the
    image's luminance standardized to zero mean and unit variance over ``mask`` (contrast and brightness do not
    count; how the contrast is spread over scales and orientations does). Gradients are derivatives of a
    Gaussian of σ, times σ (scale-normalized); the tensor is integrated over 2σ."""
    y = luma(resize_to_height(np.asarray(img, np.float32)[..., :3], STROKE_HEIGHT))
    m = np.ones(y.shape, bool) if mask is None else (
        resize_to_height(np.asarray(mask, np.float32)[..., None], STROKE_HEIGHT) >= ALPHA_MIN)
    if m.sum() < 16:
        return None
    y = (y - y[m].mean()) / (y[m].std() + 1e-3)
    b = cv2.BORDER_REFLECT_101
    out = []
    for s in STROKE_SCALES:
        z = cv2.GaussianBlur(y, (0, 0), s, borderType=b)
        gx = cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=1, borderType=b) * (0.5 * s)  # central difference
        gy = cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=1, borderType=b) * (0.5 * s)
        jxx, jxy, jyy = (cv2.GaussianBlur(t, (0, 0), 2 * s, borderType=b) for t in (gx * gx, gx * gy, gy * gy))
        aniso = np.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2)
        out.append((aniso[m], (jxx + jyy)[m]))
    return out


def stroke_descriptor(img: np.ndarray, mask=None) -> dict | None:
    """Target-free statistics of strokes: per scale of STROKE_SCALES, the percentiles STROKE_QUANTILES of
    the coherence (λ1−λ2)/(λ1+λ2) and of log10 of the anisotropic energy λ1−λ2 over the pixels of ``mask``
    (alpha >= 0.5; None: all): {"coherence": [S,Q], "log_energy": [S,Q]}. None when under 16 pixels count."""
    t = _stroke_tensors(img, mask)
    if t is None:
        return None
    return {"coherence": np.stack([np.quantile(a / (e + STROKE_EPS), STROKE_QUANTILES) for a, e in t]),
            "log_energy": np.stack([np.quantile(np.log10(a + STROKE_EPS), STROKE_QUANTILES) for a, e in t])}


def stroke_distance(d: dict | None, painting_d: dict) -> float:
    """Mean over scales of the 1-D Wasserstein distance (mean gap of matching percentiles) of the coherence
    distributions plus STROKE_ENERGY_WEIGHT times that of the log10 anisotropic energy distributions: 0 for
    the painting itself. NaN when the view has no covered pixel."""
    if d is None:
        return math.nan
    return float(np.abs(d["coherence"] - painting_d["coherence"]).mean()
                 + STROKE_ENERGY_WEIGHT * np.abs(d["log_energy"] - painting_d["log_energy"]).mean())


def sticker(painting: np.ndarray, h: int, w: int) -> np.ndarray:
    """The painting pasted in screen space over an h x w view: center-cropped to the view's aspect, resized."""
    p = np.asarray(painting, np.float32)[..., :3]
    ph, pw = p.shape[:2]
    if pw / ph > w / h:
        cw = max(1, round(ph * w / h))
        p = p[:, (pw - cw) // 2:(pw - cw) // 2 + cw]
    else:
        ch = max(1, round(pw * h / w))
        p = p[(ph - ch) // 2:(ph - ch) // 2 + ch]
    interp = cv2.INTER_AREA if p.shape[0] > h else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(p), (w, h), interpolation=interp)


def hf_energy(x: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean squared residual of a σ HF_SIGMA Gaussian blur, over pixels and channels of [H,W] or [H,W,C]; with
    ``mask`` ([H,W] bool) over the pixels it selects only (0 when it selects none)."""
    x = np.ascontiguousarray(x, np.float32)
    r2 = (x - cv2.GaussianBlur(x, (0, 0), HF_SIGMA, borderType=cv2.BORDER_REFLECT_101)) ** 2
    if mask is None:
        return float(r2.mean())
    return float(r2[mask].mean()) if mask.any() else 0.0


def detail(view: np.ndarray, painting_hf: float, inside: np.ndarray | None = None) -> float:
    """SPEC §4's detail: the luminance detail (:func:`hf_energy`) of ``view`` [H,W,3] at the evaluation size over the
    painting's ``painting_hf`` at the same height; with ``inside`` ([H,W] bool, :func:`interior`) the detail inside
    the scene."""
    return hf_energy(luma(view), inside) / max(painting_hf, 1e-12)


def interior(alpha: np.ndarray, shape: tuple) -> np.ndarray:
    """The pixels of an image of ``shape`` (h, w) inside the scene: the un-stylized alpha ([H,W] or [H,W,1] at
    training size) resized, >= ALPHA_MIN, eroded by the blur's reach (4 HF_SIGMA, the support of OpenCV's kernel
    for float images) so the outline against an empty background, which the blur residual sees as a strong edge,
    does not count as brushwork. The image border does not erode (a capture, covered everywhere, keeps every
    pixel). [h,w] bool."""
    a = np.ascontiguousarray(np.asarray(alpha, np.float32).reshape(alpha.shape[0], alpha.shape[1]))
    h, w = shape
    covered = (cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA) >= ALPHA_MIN).astype(np.uint8)
    r = int(round(4 * HF_SIGMA))
    return cv2.erode(covered, np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0  # border: OpenCV's default, no erosion


def tones(img: np.ndarray, inside: np.ndarray | None = None) -> np.ndarray:
    """The percentiles TONE_QUANTILES of the luminance of ``img`` [H,W,3] over the pixels of ``inside`` [H,W] (bool;
    every pixel when None or empty)."""
    y = luma(img)
    if inside is not None and inside.any():
        y = y[inside]
    return np.quantile(y, TONE_QUANTILES)


def tone_distance(view: np.ndarray, painting_tones: np.ndarray, inside: np.ndarray | None = None) -> float:
    """The 1-D Wasserstein distance (the mean gap of matching percentiles) between the luminance of ``view``'s
    pixels inside the scene and the painting's (``painting_tones``: :func:`tones` of the painting): a render
    paler, darker or flatter than the painting is farther, whatever its texture and hue."""
    return float(np.abs(tones(view, inside) - painting_tones).mean())


def colours(img: np.ndarray, inside: np.ndarray | None = None) -> np.ndarray:
    """[len(COLOUR_ANGLES), len(TONE_QUANTILES)]: the percentiles of the Lab a,b chroma of ``img`` [H,W,3] projected
    on each of COLOUR_ANGLES, over the pixels of ``inside`` [H,W] (bool; every pixel when None or empty)."""
    ab = lab_ab(img)
    ab = ab[inside] if inside is not None and inside.any() else ab.reshape(-1, 2)  # [P,2]
    return chroma_quantiles(ab)


def chroma_quantiles(ab: np.ndarray) -> np.ndarray:
    """:func:`colours` of chroma samples ``ab`` [P,2] (Lab a,b)."""
    directions = np.stack([np.cos(COLOUR_ANGLES), np.sin(COLOUR_ANGLES)])  # [2,K]
    return np.quantile(ab.astype(np.float64) @ directions, TONE_QUANTILES, axis=0).T  # [K,Q]


def colour_distance(view: np.ndarray, painting_colours: np.ndarray, inside: np.ndarray | None = None) -> float:
    """The sliced 1-D Wasserstein distance (the mean gap of matching percentiles along each direction of the a,b
    plane) between the chroma of ``view``'s pixels inside the scene and the painting's (``painting_colours``:
    :func:`colours` of the painting), in Lab units: the colour twin of :func:`tone_distance`. A render tinted one
    blended hue, or paler in chroma than the painting, is farther, whatever its texture; where on the canvas a hue
    sits does not count."""
    return float(np.abs(colours(view, inside) - painting_colours).mean())


def luma(img: np.ndarray) -> np.ndarray:
    return img @ np.array((0.299, 0.587, 0.114), np.float32)  # [H,W]


def lab_ab(img: np.ndarray) -> np.ndarray:
    """Lab a,b [H,W,2] (sRGB, D65) of a float RGB image in [0,1]."""
    return cv2.cvtColor(np.clip(img, 0, 1).astype(np.float32), cv2.COLOR_RGB2Lab)[..., 1:]


# ---------------------------------------------------------------- VGG
VGG_LAYERS = tuple(dict.fromkeys(GRAM_LAYERS + ("relu3_1", "relu3_2") + CONTENT_LAYERS))


VGG_BATCH = 8  # images per VGG pass in vgg_feats_batch (on a CPU a batch costs ~0.4x per image of single passes)


def cells_inside(mask: np.ndarray, h: int, w: int) -> np.ndarray:
    """The cells of an [h,w] feature map inside a pixel mask [H,W] (bool): those whose area is at least half
    inside (the mask's mean over the cell, OpenCV's area resize). [h*w] bool, row-major like the features."""
    m = cv2.resize(np.ascontiguousarray(mask, np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return (m >= 0.5).reshape(-1)


def _gram(a: torch.Tensor) -> torch.Tensor:
    return (a @ a.T / a.shape[1]).double()  # [C, N] -> [C, C]


def _feats_of(f: dict, b: int, mask: np.ndarray | None = None) -> dict:
    """One image's metric features from a batch's VGG maps; with ``mask`` (its pixels inside the scene) also the
    Gram matrices and the relu3 cells inside it ("grams_inside", "relu3_inside"; where no cell is inside, every
    cell counts)."""
    grams, inside = {}, {}
    for k in GRAM_LAYERS:
        a = f[k][b].reshape(f[k].shape[1], -1)  # [C, N]
        grams[k] = _gram(a)
        if mask is not None:
            inside[k] = _gram(_inside(a, mask, *f[k].shape[2:]))
    r3 = torch.cat([f["relu3_1"][b], f["relu3_2"][b], f["relu3_3"][b]], 0)  # [768, h, w]
    r3_flat = r3.reshape(r3.shape[0], -1)
    return {"grams": grams, "grams_inside": inside or None, "relu3": r3_flat,
            "relu3_inside": None if mask is None else _inside(r3_flat, mask, *r3.shape[1:]),
            "content": {k: f[k][b:b + 1].contiguous() for k in CONTENT_LAYERS}}


def _inside(a: torch.Tensor, mask: np.ndarray, h: int, w: int) -> torch.Tensor:
    """The columns of features [C, h*w] at the cells inside ``mask`` (``cells_inside``); all of them where none is."""
    keep = torch.from_numpy(cells_inside(mask, h, w)).to(a.device)
    return a[:, keep] if bool(keep.any()) else a


def vgg_feats(net, img: np.ndarray) -> dict:
    """One pass of an [H,W,3] image at its given size: {"grams": {layer: [C,C]}, "relu3": [768,N],
    "content": {layer: [1,C,h,w]}}."""
    return vgg_feats_batch(net, [img])[0]


def vgg_feats_batch(net, imgs, masks=None) -> list:
    """vgg_feats of several [H,W,3] images: same-size ones go through VGG together (VGG_BATCH at a time), and an
    image equal to an earlier one (a sticker is the same on every view) reuses its features. ``masks``: per image
    its pixels inside the scene ([H,W] bool), for the Gram matrices inside it (an image reuses another's features
    only where their masks agree too)."""
    dev = next(net.parameters()).device
    masks = list(masks) if masks is not None else [None] * len(imgs)
    out, seen, todo = [None] * len(imgs), {}, {}
    for i, im in enumerate(imgs):
        a = np.ascontiguousarray(im, np.float32)
        m = masks[i]
        key = (a.shape, hash(a.tobytes()), None if m is None else hash(np.packbits(m).tobytes()))
        if key in seen and np.array_equal(imgs[seen[key]], a) and (
                m is None or np.array_equal(masks[seen[key]], m)):
            continue
        seen[key] = i
        todo.setdefault(a.shape, []).append(i)
    for shape, idx in todo.items():
        for c in range(0, len(idx), VGG_BATCH):
            chunk = idx[c:c + VGG_BATCH]
            x = torch.from_numpy(np.stack([np.ascontiguousarray(imgs[i], np.float32) for i in chunk])).to(dev)
            with torch.no_grad():
                f = net.layers(x.permute(0, 3, 1, 2), VGG_LAYERS)
            for b, i in enumerate(chunk):
                out[i] = _feats_of(f, b, masks[i])
    for i, im in enumerate(imgs):
        if out[i] is None:
            a, m = np.ascontiguousarray(im, np.float32), masks[i]
            out[i] = out[seen[(a.shape, hash(a.tobytes()), None if m is None else hash(np.packbits(m).tobytes()))]]
    return out


def style_gram(grams: dict, painting_grams: dict) -> float:
    """Mean over layers of ‖G − G_p‖_F / ‖G_p‖_F (each layer counts the same whatever its magnitude)."""
    return float(np.mean([float((grams[k] - painting_grams[k]).norm() / painting_grams[k].norm().clamp_min(1e-12))
                          for k in GRAM_LAYERS]))


def style_nnfm(feats: torch.Tensor, painting_feats: torch.Tensor) -> float:
    """ARF's NNFM distance: mean over render cells of min over painting cells of 1 − cos. float32 products (a
    cosine needs no more) in chunks of render cells, so memory stays bounded at any size."""
    a = F.normalize(feats.float(), dim=0)
    s = F.normalize(painting_feats.float(), dim=0)
    best = torch.cat([(a[:, i:i + NNFM_CHUNK].T @ s).max(dim=1).values for i in range(0, a.shape[1], NNFM_CHUNK)])
    return float((1.0 - best.double()).mean())


def content(feats: dict, photo_feats: dict) -> float:
    """Mean over CONTENT_LAYERS of ‖f − f_photo‖² / ‖f_photo‖² (RGB, same evaluation size), summed in float64
    (the value does not depend on the features' memory layout)."""
    return float(np.mean([float(((feats[k].double() - photo_feats[k].double()) ** 2).sum()
                                / (photo_feats[k].double() ** 2).sum().clamp_min(1e-12)) for k in CONTENT_LAYERS]))


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


def spill(alpha, base_alpha) -> float:
    """Fraction of the view that the stylized scene covers where the un-stylized scene leaves it uncovered (an
    empty background): holes' mirror. A whole-view style distance rewards such paint (texture on white), the eye
    does not. Over the whole view, not over the empty pixels: a capture with a few uncovered pixels at its border
    would otherwise swing between 0 and 1."""
    a, b = _np(alpha), _np(base_alpha)
    return float(((b < ALPHA_MIN) & (a >= ALPHA_MIN)).mean())


# ---------------------------------------------------------------- statistics
def interval(values, seed: int = SEED, n: int = BOOTSTRAP, groups=None) -> dict:
    """Mean and 95% bootstrap percentile interval over views (NaN views dropped). Deterministic.

    ``groups`` (one label per value, e.g. the seed of a run's views pooled over seeds): a two-stage bootstrap,
    groups drawn with replacement and then views within each drawn group, so the interval also holds the spread
    between groups (runs of different seeds) instead of treating every (seed, view) item as independent."""
    vals = [math.nan if v is None else v for v in values]
    keep = np.isfinite(np.asarray(vals, np.float64))
    x = np.asarray(vals, np.float64)[keep]
    if x.size == 0:
        return {"mean": None, "lo": None, "hi": None, "n": 0}
    rng = np.random.default_rng(seed)
    if groups is None:
        means = x[rng.integers(0, x.size, (n, x.size))].mean(1)  # [n]
    else:
        means = _grouped_means(x, np.asarray(groups)[keep], rng, n)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return {"mean": float(x.mean()), "lo": float(lo), "hi": float(hi), "n": int(x.size)}


def _grouped_means(x: np.ndarray, groups: np.ndarray, rng, n: int) -> np.ndarray:
    """[n] resampled means: G group slots each take a random group, then a resample of that group's values (an
    independent one per slot); the mean gives each slot its group's weight in the data."""
    parts = [x[groups == g] for g in np.unique(groups)]  # G small (seeds): loops over groups, not values
    g_count = len(parts)
    pick = rng.integers(0, g_count, (n, g_count))  # [n, G] which group each slot takes
    total = np.zeros(n)
    weight = np.zeros(n)
    for slot in range(g_count):
        for g, xg in enumerate(parts):
            sel = pick[:, slot] == g
            inner = xg[rng.integers(0, xg.size, (n, xg.size))].mean(1)  # [n] a resample of group g
            total += np.where(sel, inner * xg.size, 0.0)
            weight += np.where(sel, xg.size, 0)
    return total / weight


def paired(a, b, metric: Metric, groups=None) -> dict:
    """A vs B on the same views: the mean paired difference a − b with its 95% bootstrap interval, and the
    verdict "a", "b" or "no difference" (when the interval contains 0). ``groups``: see :func:`interval`."""
    pa = np.asarray([math.nan if v is None else v for v in a], np.float64)
    pb = np.asarray([math.nan if v is None else v for v in b], np.float64)
    if pa.shape != pb.shape:
        raise ValueError(f"{metric.key}: {pa.size} vs {pb.size} views")
    ok = np.isfinite(pa) & np.isfinite(pb)
    ci = interval(pa[ok] - pb[ok], groups=None if groups is None else np.asarray(groups)[ok])
    if ci["n"] == 0:
        return {**ci, "better": None}
    if ci["lo"] <= 0.0 <= ci["hi"]:
        better = "no difference"
    else:
        better = "a" if (ci["mean"] > 0) == metric.higher_better else "b"
    return {**ci, "better": better}
