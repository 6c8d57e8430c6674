"""The painting's stroke direction field and what is built on it (SPEC §3 "Stroke direction field", §4).

Structure tensor of luminance: Gaussian pre-smoothing σ 1 px, Scharr gradients, tensor smoothed σ 3 px.
Angles are in pixel coordinates (x = column to the right, y = row downward, as SPEC §1's projected
means): the stroke direction is v = (cos θ, sin θ), θ in (−π/2, π/2], the eigenvector of the SMALLER
eigenvalue (along the brushstroke). Coherence c = ((λ1−λ2)/(λ1+λ2+ε))². The field is kept doubled-angle,
c·(cos 2θ, sin 2θ), so θ and θ+π agree and fields can be averaged and resized.
Two implementations with the same kernels and borders (reflect-101, OpenCV's default): numpy/OpenCV
(:func:`stroke_field`) and differentiable torch (:func:`render_orientation`).
The stroke hinge (loss.w_stroke) reads the same pre-blurred Scharr gradients across and along a target field:
:func:`stroke_energies` (torch), :func:`painting_stroke_energies` (the painting's targets, numpy/OpenCV float64),
:func:`stroke_hinge`.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from .color import luminance
from .style import match_style_cells
from .vgg import flatten_feats, resize_style

PRE_SIGMA = 1.0
TENSOR_SIGMA = 3.0
# Added to λ1+λ2 (units: Scharr gradient², Scharr = 32 x the per-pixel slope). 1e-4 is a slope of ~3e-4
# per pixel, far below one 8-bit step (1/255 -> gradient² ~0.016): flat areas get c ~ 0 instead of the
# direction of float round-off, while any visible texture keeps c ~ (λ1−λ2)/(λ1+λ2).
EPS_TRACE = 1e-4
# The stroke hinge's relative form (loss.stroke_contrast: log) reads log(Y + STROKE_LOG_EPS): a step dY counts as
# dY / (Y + 0.05), so a dark passage meets the painting's contrast with small steps. 0.05 is a deep shadow; below it a
# step counts as if at 0.05.
STROKE_LOG_EPS = 0.05
LUMA = (0.299, 0.587, 0.114)
_SCHARR_X = np.array([[-3, 0, 3], [-10, 0, 10], [-3, 0, 3]], np.float32)  # cv2.Scharr(dx=1), correlation


def _ksize(sigma: float) -> int:
    return 2 * math.ceil(4 * sigma) + 1  # OpenCV's automatic size for float images: 9 (σ 1), 25 (σ 3)


def _lum_np(image) -> np.ndarray:
    a = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    a = a.astype(np.float32)
    return a @ np.array(LUMA, np.float32) if a.ndim == 3 else a  # [H,W]


def _field_np(jxx, jxy, jyy):
    dx, dy = jxx - jyy, 2.0 * jxy  # (λ1−λ2)·(cos 2ψ, sin 2ψ), ψ = gradient (across-stroke) direction
    r = np.sqrt(dx * dx + dy * dy)
    c = (r / (jxx + jyy + EPS_TRACE)) ** 2
    theta = 0.5 * np.arctan2(-dy, -dx)  # θ = ψ + 90°: doubling flips the sign of the doubled vector
    scale = np.divide(c, r, out=np.zeros_like(r), where=r > 0)
    return theta.astype(np.float32), c.astype(np.float32), np.stack([-dx * scale, -dy * scale], -1).astype(np.float32)


def structure_tensor(image) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoothed structure tensor (Jxx, Jxy, Jyy) [H,W] each of an [H,W,3] or [H,W] float image."""
    y = _lum_np(image)
    k1, k3 = _ksize(PRE_SIGMA), _ksize(TENSOR_SIGMA)
    b = cv2.BORDER_REFLECT_101
    y = cv2.GaussianBlur(y, (k1, k1), PRE_SIGMA, borderType=b)
    gx = cv2.Scharr(y, cv2.CV_32F, 1, 0, borderType=b)
    gy = cv2.Scharr(y, cv2.CV_32F, 0, 1, borderType=b)
    blur = lambda z: cv2.GaussianBlur(z, (k3, k3), TENSOR_SIGMA, borderType=b)  # noqa: E731
    return blur(gx * gx), blur(gx * gy), blur(gy * gy)


def stroke_field(image):
    """(theta [H,W], coherence [H,W], doubled [H,W,2]) float32 numpy, from an [H,W,3] (or [H,W]) float image."""
    return _field_np(*structure_tensor(image))


def field_from_doubled(doubled):
    """θ = ½·atan2 and c = |d| of a doubled-angle field [...,2] (numpy or torch, same type back)."""
    if isinstance(doubled, torch.Tensor):
        return 0.5 * torch.atan2(doubled[..., 1], doubled[..., 0]), doubled.norm(dim=-1), doubled
    d = np.asarray(doubled, np.float32)
    return (0.5 * np.arctan2(d[..., 1], d[..., 0])).astype(np.float32), np.linalg.norm(d, axis=-1), d


# ---------------------------------------------------------------- torch, differentiable
_kcache: dict = {}


def _kernels(dtype, device):
    key = (dtype, str(device))
    if key not in _kcache:
        g1 = cv2.getGaussianKernel(_ksize(PRE_SIGMA), PRE_SIGMA, cv2.CV_64F).ravel()
        g3 = cv2.getGaussianKernel(_ksize(TENSOR_SIGMA), TENSOR_SIGMA, cv2.CV_64F).ravel()
        t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        # made once: a CUDA graph capture of render_orientation may not copy from the host
        _kcache[key] = (t(g1), t(g3), t(_SCHARR_X), t(LUMA).view(1, 3, 1, 1))
    return _kcache[key]


def _pad(x, ph, pw):
    h, w = x.shape[-2:]  # reflect-101 needs pad < size; tiny images fall back to edge replication
    return F.pad(x, (pw, pw, ph, ph), mode="reflect" if (ph < h and pw < w) else "replicate")


def _sep_blur(x, g):  # x [B,C,H,W], g [k]
    r, c = g.numel() // 2, x.shape[1]
    x = F.conv2d(_pad(x, 0, r), g.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(_pad(x, r, 0), g.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def _luma_gradients(x, log_eps: float | None = None):
    """Scharr gradients (gx, gy) [B,1,H,W] of the luminance of x [B,3,H,W], pre-blurred σ PRE_SIGMA (the kernels and
    borders of :func:`structure_tensor`); of log(max(Y, 0) + ``log_eps``) when given."""
    g1, _, sx, luma = _kernels(x.dtype, x.device)
    y = (x * luma).sum(1, keepdim=True)  # [B,1,H,W]
    if log_eps is not None:
        y = torch.log(y.clamp_min(0.0) + log_eps)
    y = _pad(_sep_blur(y, g1), 1, 1)
    return F.conv2d(y, sx.view(1, 1, 3, 3)), F.conv2d(y, sx.T.contiguous().view(1, 1, 3, 3))


def render_orientation(img: torch.Tensor):
    """Differentiable torch twin of :func:`stroke_field`. img [H,W,3] -> (θ [H,W], c [H,W], doubled [H,W,2]);
    [B,3,H,W] -> ([B,H,W], [B,H,W], [B,H,W,2])."""
    single = img.dim() == 3
    x = img.permute(2, 0, 1).unsqueeze(0) if single else img  # [B,3,H,W]
    theta, c, doubled = _orientation(*_luma_gradients(x))
    if single:
        return theta[0], c[0], doubled[0]
    return theta, c, doubled


def _orientation(gx, gy):
    """(θ, c, doubled) [B,H,W], [B,H,W], [B,H,W,2] from luminance gradients gx, gy [B,1,H,W]."""
    j = _sep_blur(torch.cat([gx * gx, gx * gy, gy * gy], 1), _kernels(gx.dtype, gx.device)[1])  # [B,3,H,W]
    jxx, jxy, jyy = j[:, 0], j[:, 1], j[:, 2]
    dx, dy = jxx - jyy, 2.0 * jxy
    r = torch.sqrt(dx * dx + dy * dy + 1e-30)  # tiny keeps sqrt's gradient finite at r = 0
    tr = jxx + jyy + EPS_TRACE
    c = (r / tr) ** 2
    doubled = torch.stack([-dx, -dy], -1) * (r / tr ** 2).unsqueeze(-1)  # c·(cos2θ, sin2θ) = −(dx,dy)·c/r
    theta = 0.5 * torch.atan2(-dy, -dx)
    return theta, c, doubled


# ---------------------------------------------------------------- mapping onto a view
def _resize2(d: np.ndarray, h: int, w: int) -> np.ndarray:
    shrink = h <= d.shape[0] and w <= d.shape[1]
    return cv2.resize(np.ascontiguousarray(d, np.float32), (w, h),
                      interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def map_field_canvas(doubled, H: int, W: int):
    """"canvas" mapping: the painting's doubled-angle field [h,w,2] stretched over the H x W view (components
    resized, INTER_AREA shrinking / INTER_LINEAR growing), then θ and c re-derived (c = |averaged vector|,
    so disagreeing strokes lower coherence). Returns (θ [H,W], c [H,W], doubled [H,W,2]); torch in, torch out."""
    if isinstance(doubled, torch.Tensor):
        d = torch.from_numpy(_resize2(doubled.detach().cpu().numpy(), H, W)).to(doubled.device)
        return field_from_doubled(d)
    return field_from_doubled(_resize2(doubled, H, W))


def field_at_cells(doubled, cell_shape) -> np.ndarray:
    """The style field [h,w,2] averaged onto the style's VGG cell grid (hs, ws) -> [hs*ws, 2], row-major like
    the columns of the style feature matrix."""
    d = doubled.detach().cpu().numpy() if isinstance(doubled, torch.Tensor) else doubled
    hs, ws = cell_shape
    return _resize2(d, hs, ws).reshape(-1, 2)


def map_field_matched(doubled_style_at_cells, idx: torch.Tensor, w: torch.Tensor, H: int, W: int, cell_shape):
    """"matched" mapping (default): each render VGG cell takes the w-weighted mean doubled-angle vector of its
    matched style cells (``idx``/``w`` [Nc,k] from :func:`match_style_cells` or FAST), the cell grid
    ``cell_shape`` = (hc, wc) with hc*wc = Nc is upsampled bilinearly to H x W, θ and c re-derived.
    Returns torch (θ [H,W], c [H,W], doubled [H,W,2]) on idx's device."""
    ds = torch.as_tensor(np.asarray(doubled_style_at_cells) if not isinstance(doubled_style_at_cells, torch.Tensor)
                         else doubled_style_at_cells, dtype=torch.float32, device=idx.device)  # [Ns,2]
    hc, wc = cell_shape
    if hc * wc != idx.shape[0]:
        raise ValueError(f"cell_shape {cell_shape} does not match {idx.shape[0]} matched cells")
    d = (ds[idx] * w.to(ds).unsqueeze(-1)).sum(1)  # [Nc,2]
    d = d.T.reshape(1, 2, hc, wc)
    d = F.interpolate(d, size=(H, W), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)  # [H,W,2]
    return field_from_doubled(d.contiguous())


# ---------------------------------------------------------------- evaluation (SPEC §4)


@torch.no_grad()
def matched_view_field(vgg, img: torch.Tensor, style_feats, style_cells, scale: float) -> torch.Tensor:
    """The painting's stroke field carried onto a view as training makes it [H,W,2] (doubled angle): luminance VGG
    features of ``img`` [H,W,3] at ``scale``, each cell's top-k painting cells (:func:`match_style_cells` against
    ``style_feats``), their doubled-angle vectors ``style_cells`` [Ns,2] averaged and upsampled."""
    f = vgg(luminance(img), scale=scale)  # [1,768,hc,wc]
    idx, w = match_style_cells(flatten_feats(f), style_feats)
    return map_field_matched(style_cells, idx, w, img.shape[0], img.shape[1], tuple(f.shape[-2:]))[2]


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def flow_alignment_score(render, target_doubled) -> float:
    """Flow-alignment score (SPEC §4) of a render [H,W,3] against a target doubled-angle field [H,W,2]:
    Σ w·cos 2(φ − φ*) / Σ w with φ from the render's own structure tensor (same parameters) and
    w = c_target · c_render. Weighting by both coherences counts a pixel only where the painting has a
    stroke direction AND the render has a measurable orientation (φ of a flat or isotropic patch is noise).
    Since d = c·(cos2φ, sin2φ), this is Σ d_render·d_target / Σ |d_render||d_target|. In [−1, 1];
    0.0 when the weights vanish (a flat render), so metrics never hold NaN."""
    _, _, d = stroke_field(_np(render))
    t = _np(target_doubled).astype(np.float32)
    num = float((d.astype(np.float64) * t).sum())
    den = float((np.linalg.norm(d, axis=-1).astype(np.float64) * np.linalg.norm(t, axis=-1)).sum())
    return float(np.clip(num / den, -1.0, 1.0)) if den > 1e-12 else 0.0  # clip: float round-off only


def flow_alignment_score_torch(render: torch.Tensor, target_doubled: torch.Tensor) -> torch.Tensor:
    """Same score from :func:`render_orientation` (stays on the device, differentiable); a 0-dim tensor."""
    _, _, d = render_orientation(render)
    return _alignment(d, target_doubled)


def _alignment(d: torch.Tensor, target_doubled: torch.Tensor) -> torch.Tensor:
    t = target_doubled.to(d)
    den = (d.norm(dim=-1) * t.norm(dim=-1)).sum()
    return ((d * t).sum() / den.clamp_min(1e-12)).clamp(-1.0, 1.0)


# ---------------------------------------------------------------- directional detail (the stroke hinge)
def _directional(gx, gy, u0, u1):
    """(across², along²): the squared luminance derivative across and along the unit stroke direction whose doubled
    angle is (u0, u1) = (cos 2θ, sin 2θ). (g·v)² = ½|g|² + ½(gx²−gy²)·cos 2θ + gx·gy·sin 2θ for v = (cos θ, sin θ),
    and the two add up to |g|²."""
    g2 = gx * gx + gy * gy
    along = 0.5 * g2 + 0.5 * (gx * gx - gy * gy) * u0 + gx * gy * u1
    return g2 - along, along


def stroke_energies(img: torch.Tensor, doubled: torch.Tensor, weight: torch.Tensor | None = None,
                    log_eps: float | None = None):
    """(E_across, E_along), 0-dim tensors in the image's dtype, differentiable w.r.t. ``img`` [H,W,3]: the weighted
    means of the luminance's squared derivative across and along the stroke field ``doubled`` [H,W,2]
    (c·(cos 2θ, sin 2θ)). Gradients as :func:`render_orientation` takes them (σ PRE_SIGMA pre-blur, Scharr,
    reflected border); weights c · ``weight`` [H,W,1] (the view's coverage; all ones when None), so a pixel without
    a stroke direction (c = 0) counts for nothing. Stripes that run along the strokes raise E_across only.
    ``log_eps``: of log(max(Y, 0) + log_eps) instead of Y (relative contrast, the blur after the log)."""
    gx, gy = _luma_gradients(img.permute(2, 0, 1).unsqueeze(0), log_eps)
    return _energies(gx[0, 0], gy[0, 0], doubled, weight)


def _energies(gx, gy, doubled, weight):  # gx, gy [H,W]
    d = doubled.to(gx)
    n2 = (d * d).sum(-1)
    inv = torch.where(n2 > 0, n2.clamp_min(1e-30).rsqrt(), torch.zeros_like(n2))  # 1/|d|, 0 where d = 0
    across, along = _directional(gx, gy, d[..., 0] * inv, d[..., 1] * inv)
    w = n2 * inv  # c = |d|, with a finite gradient at d = 0
    if weight is not None:
        w = w * weight[..., 0].to(gx)
    sw = w.sum().clamp_min(1e-12)
    return (w * across).sum() / sw, (w * along).sum() / sw


def painting_stroke_energies(style_img, view_h: int, log_eps: float | None = None) -> tuple[float, float]:
    """(T_across, T_along) of a painting [h,w,3] float in [0,1] at ``view_h`` rows (``resize_style``, as the detail
    hinge's target): its own stroke field (:func:`stroke_field`, always of Y), its luminance gradients by OpenCV in
    float64 (the kernels and border of :func:`structure_tensor`; of log(Y + ``log_eps``) when given), the same
    weighted means as :func:`stroke_energies` with weight c. The stroke hinge's targets."""
    p = resize_style(np.asarray(_np(style_img), np.float32), view_h)  # [view_h,w',3] float32
    _, c, d = stroke_field(p)
    y = p.astype(np.float64) @ np.array(LUMA, np.float64)
    if log_eps is not None:
        y = np.log(np.maximum(y, 0.0) + log_eps)
    k1, b = _ksize(PRE_SIGMA), cv2.BORDER_REFLECT_101
    y = cv2.GaussianBlur(y, (k1, k1), PRE_SIGMA, borderType=b)
    gx = cv2.Scharr(y, cv2.CV_64F, 1, 0, borderType=b)
    gy = cv2.Scharr(y, cv2.CV_64F, 0, 1, borderType=b)
    d = d.astype(np.float64)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    u = np.divide(d, n, out=np.zeros_like(d), where=n > 0)
    across, along = _directional(gx, gy, u[..., 0], u[..., 1])
    w = c.astype(np.float64)
    sw = max(float(w.sum()), 1e-12)
    return float((w * across).sum() / sw), float((w * along).sum() / sw)


def stroke_hinge(e_across: torch.Tensor, e_along: torch.Tensor, t_across: float, t_along: float,
                 along: str = "ratio") -> torch.Tensor:
    """relu(1 − E_across/T_across)² plus, while E_along is above T_along, (E_along/T_along − 1)² (``along`` "ratio")
    or (1 − T_along/E_along)² ("bounded", below 1 however far E_along goes), or nothing ("none": contrast along the
    strokes left as it is, an object's studs and brick edges among it): contrast across the strokes is asked for
    up to the painting's level, contrast along them is allowed up to the painting's level; 0 when both hold.
    ``t_*`` floats."""
    across = torch.relu(1.0 - e_across / max(t_across, 1e-12)) ** 2
    if along == "none":
        return across
    if along == "bounded":
        return across + torch.relu(1.0 - max(t_along, 1e-12) / e_along.clamp_min(1e-12)) ** 2
    if along != "ratio":
        raise ValueError(f"along must be 'ratio', 'bounded' or 'none', got {along!r}")
    return across + torch.relu(e_along / max(t_along, 1e-12) - 1.0) ** 2


def gradient_reach() -> int:
    """Pixels an edge reaches into the luminance gradients :func:`stroke_energies` reads: the pre-blur's kernel
    half-width plus the Scharr stencil's one."""
    return _ksize(PRE_SIGMA) // 2 + 1


def interior_weight(weight: torch.Tensor, reach: int) -> torch.Tensor:
    """``weight`` [H,W,1] (a coverage) eroded by ``reach`` px: each pixel takes the smallest weight within its
    (2 reach + 1)² square, so that an outline against an empty background, whose gradients reach that far in, counts
    for nothing; the image border does not erode (a capture, covered everywhere, keeps every pixel). [H,W,1]"""
    w = weight.permute(2, 0, 1).unsqueeze(0)  # [1,1,H,W]; max_pool pads with -inf: no erosion from the border
    return (-F.max_pool2d(-w, 2 * reach + 1, stride=1, padding=reach))[0].permute(1, 2, 0)


def field_terms(img: torch.Tensor, doubled: torch.Tensor, weight: torch.Tensor, *, orient: bool = True,
                stroke_target: tuple[float, float] | None = None, along: str = "ratio",
                stroke_log_eps: float | None = None) -> torch.Tensor:
    """The two loss terms read off the render's luminance gradients against the view's stroke field, from ONE
    gradient pass: [1 − :func:`flow_alignment_score_torch`, :func:`stroke_hinge` of :func:`stroke_energies`] [2],
    an entry 0 where its term is off (``orient`` False, ``stroke_target`` None). img [H,W,3], doubled [H,W,2],
    weight [H,W,1] (the stroke hinge's: the coverage, or :func:`interior_weight` of it). ``stroke_log_eps``: the
    hinge's energies of log luminance (a second gradient pass; ``stroke_target`` then the painting's in the same
    form). One tensor out, so that ``GraphedFn`` replays both as one graph."""
    x = img.permute(2, 0, 1).unsqueeze(0)
    gx, gy = _luma_gradients(x)  # [1,1,H,W] each
    zero = img.new_zeros(())
    orient_term = 1.0 - _alignment(_orientation(gx, gy)[2][0], doubled) if orient else zero
    if stroke_target is not None and stroke_log_eps is not None:
        gx, gy = _luma_gradients(x, stroke_log_eps)
    stroke_term = zero if stroke_target is None else stroke_hinge(
        *_energies(gx[0, 0], gy[0, 0], doubled, weight), *stroke_target, along=along)
    return torch.stack([orient_term, stroke_term])


# ---------------------------------------------------------------- picture of the field
LIC_STEPS = 15  # each way: streaks ~31 px long, visible at painting size without smearing small strokes


def field_picture(image, theta, coherence, steps: int = LIC_STEPS, seed: int = 0) -> np.ndarray:
    """Line-integral convolution of white noise along θ, tinted by the painting: [H,W,3] float32 in [0,1].
    Sample points are advected ``steps`` 1-px steps both ways with cv2.remap; the direction is re-read from
    the interpolated doubled-angle field each step and kept pointing the same way as the last step
    (an orientation field has no sign). Low-coherence areas are drawn with less contrast."""
    th, c = _np(theta).astype(np.float32), _np(coherence).astype(np.float32)
    h, w = th.shape
    img = _np(image).astype(np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    if img.shape[:2] != (h, w):
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    noise = np.random.default_rng(seed).random((h, w), dtype=np.float32)
    c2, s2 = np.cos(2 * th), np.sin(2 * th)
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    acc, n = noise.copy(), 1
    rm = lambda a, px, py, b: cv2.remap(a, px, py, cv2.INTER_LINEAR, borderMode=b)  # noqa: E731
    for sign in (1.0, -1.0):
        px, py = gx.copy(), gy.copy()
        prev_x, prev_y = sign * np.cos(th), sign * np.sin(th)  # [H,W]
        for _ in range(steps):
            a2 = 0.5 * np.arctan2(rm(s2, px, py, cv2.BORDER_REPLICATE), rm(c2, px, py, cv2.BORDER_REPLICATE))
            ux, uy = np.cos(a2), np.sin(a2)
            flip = np.where(ux * prev_x + uy * prev_y < 0, -1.0, 1.0).astype(np.float32)
            ux, uy = ux * flip, uy * flip
            px, py = px + ux, py + uy
            acc += rm(noise, px, py, cv2.BORDER_REFLECT_101)
            n += 1
            prev_x, prev_y = ux, uy
    lic = acc / n
    lo, hi = np.percentile(lic, [1, 99])
    lic = np.clip((lic - lo) / max(hi - lo, 1e-6), 0, 1)  # [H,W] contrast-stretched
    lic = 0.5 + (lic - 0.5) * (0.3 + 0.7 * np.clip(c, 0, 1))  # strokes pop where the field is coherent
    return np.clip(img * (0.5 + lic)[..., None], 0, 1).astype(np.float32)
