"""Color: ARF mean/covariance color transfer, differentiable sRGB -> CIE Lab (D65), the Lab chroma
statistics loss, and the luminance image the style loss sees.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..types import SH_C0
from .lab_warp import LabChromaLossFn, chroma_stats_of, lab_ab_jacobian
from .ssim import gauss1d
from .vgg import resize_style

EIG_FLOOR = 1e-8  # ARF clamps covariance eigenvalues to [1e-8, 1e8]: a flat channel must not blow up


def _as_torch(x) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(x))


def _sym_pow(cov: torch.Tensor, p: float) -> torch.Tensor:
    """cov^p for a symmetric PSD 3x3 via its eigendecomposition (the SVD of a PSD matrix is the same)."""
    e, u = torch.linalg.eigh(cov)
    return u @ torch.diag(e.clamp(EIG_FLOOR, 1e8) ** p) @ u.T  # [3,3]


def _moments(items, weights=None):
    """Pooled mean [3] and population covariance [3,3] (as ARF) of all pixels, float64 on the CPU, summed
    image by image so a whole dataset is never concatenated. ``weights`` (one [H,W] or [H,W,1] per image, >= 0):
    each pixel counts by its weight (None, or under one pixel of weight in all: every pixel once)."""
    n, s1, s2 = 0.0, torch.zeros(3, dtype=torch.float64), torch.zeros(3, 3, dtype=torch.float64)
    for i, im in enumerate(items):
        p = _as_torch(im).detach().reshape(-1, 3).double()  # [N,3]
        w = None if weights is None else _as_torch(weights[i]).detach().reshape(-1, 1).to(p)  # [N,1]
        pw = p if w is None else p * w  # [N,3]
        n += float(p.shape[0] if w is None else w.sum())
        s1 += pw.sum(0).cpu()
        s2 += (pw.T @ p).cpu()
    if weights is not None and n < 1.0:  # under one pixel of weight in all (nothing covered): every pixel, as ARF
        return _moments(items)
    mu = s1 / n
    return mu, s2 / n - torch.outer(mu, mu)


def color_transfer(images, style, floor: float = 0.0, weights=None):
    """Recolor ``images`` (a list of [H,W,3] or an array [B,H,W,3], floats in [0,1], numpy or torch) to the
    palette of ``style`` [h,w,3]: pool all pixels, whiten with the content covariance, color with the
    style covariance (symmetric square roots, as ARF), shift means, clamp to [0,1].

    ``floor`` (ours; 0 = ARF): a variance added to the content covariance before whitening, so a colour direction
    the photos barely vary along (a grey floor's faint tints, JPEG blocks) is stretched by at most
    sqrt(painting variance / floor) instead of up to 1/sqrt(1e-8).

    ``weights`` (ours; None = ARF): one [H,W] or [H,W,1] weight per image (the scene's alpha), so the content
    moments are those of the pixels the scene covers: an object on a white background otherwise takes only the
    dark end of the painting's palette, the background having claimed the bright end. Under one pixel of weight
    in all: every pixel, as ARF.

    Returns ``(recolored, M, t)`` with recolored in the input's container/type and ``x' = M x + t``
    (M [3,3], t [3], float64 torch) so the same map can be reapplied (:func:`apply_color_transform`).
    """
    is_list = isinstance(images, (list, tuple))
    items = list(images) if is_list else [images]
    m, t = color_map(items, style, floor, weights)
    out = [apply_color_transform(im, m, t) for im in items]
    return (out if is_list else out[0]), m, t


def color_map(images: list, style, floor: float = 0.0, weights=None) -> tuple:
    """ARF's map alone: ``(M [3,3], t [3])`` float64 of :func:`color_transfer` (same arguments, ``images`` a list),
    without applying it."""
    mu_c, cov_c = _moments(images, weights)
    mu_s, cov_s = _moments([style])
    m = _sym_pow(cov_s, 0.5) @ _sym_pow(cov_c + floor * torch.eye(3, dtype=torch.float64), -0.5)  # [3,3]
    return m, mu_s - m @ mu_c


DETAIL_SIGMA = 2.0  # px: the blur whose residual is "detail" (the evaluation's detail measure uses the same σ)
DETAIL_MAX_GAIN = 3.0  # at most this factor on a view's luminance detail


def _blur(y: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of [B,1,H,W] (separable, reflected border, radius 3σ)."""
    r = max(1, int(round(3 * sigma)))
    k = gauss1d(2 * r + 1, sigma, y.dtype, y.device)  # [2r+1]
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="reflect"), k.view(1, 1, 1, -1))
    return F.conv2d(F.pad(y, (0, 0, r, r), mode="reflect"), k.view(1, 1, -1, 1))


def smooth_chroma(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """``img`` [H,W,3] with its chroma (RGB minus the luminance Y) Gaussian-blurred by ``sigma`` px (separable,
    reflected border) and its luminance kept: Y of the output is Y of the input, since the chroma has Y = 0 at every
    pixel and the blur is linear."""
    y = luminance(img)  # [H,W,3], Y in every channel
    c = (img - y).permute(2, 0, 1)[:, None]  # [3,1,H,W]
    return y + _blur(c, sigma)[:, 0].permute(1, 2, 0)


def _highpass(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Y minus its σ-blur [H,W] of an [H,W,3] image, in the image's dtype (differentiable)."""
    y = luminance(img)[..., :1].permute(2, 0, 1)[None]  # [1,1,H,W]
    return (y - _blur(y, sigma))[0, 0]


def luminance_detail(img: torch.Tensor, sigma: float = DETAIL_SIGMA) -> torch.Tensor:
    """The luminance's high-pass residual [H,W] of an [H,W,3] image, in float64: Y minus its σ-blur."""
    return _highpass(img.double(), sigma)


def detail_energy(img: torch.Tensor, weight: torch.Tensor | None = None, sigma: float = DETAIL_SIGMA) -> torch.Tensor:
    """Mean squared luminance high-pass (Y minus its σ-blur) of an [H,W,3] image, over the pixels weighted by
    ``weight`` [H,W,1] (all pixels when None). Differentiable, in the image's dtype: the detail hinge's measure."""
    hp2 = _highpass(img, sigma) ** 2  # [H,W]
    if weight is None:
        return hp2.mean()
    w = weight[..., 0].to(hp2)
    return (hp2 * w).sum() / w.sum().clamp_min(1e-12)


def match_detail(images, painting: torch.Tensor, max_gain: float = DETAIL_MAX_GAIN, sigma: float = DETAIL_SIGMA):
    """Give recolored views the painting's level of luminance detail: ``x + (g - 1)·(Y - blur(Y))`` on every
    channel, with one gain g = sqrt(painting's / views' mean detail energy) for all views, in [1, max_gain].

    Why (ours): the ARF transfer matches the painting's global colour covariance, and a dark nocturne has little
    of it (Starry Night over the Rhône: luminance std 0.08), so it flattens the photos' local contrast 4-9x
    (fern, lego and beer to 0.22-0.31 of the painting's detail); the scene fitted to those targets starts as a wash.
    Only the high-pass residual is scaled, so tones and chroma statistics stay the transfer's.
    ``images``: list of [H,W,3] in [0,1]; ``painting`` [h,w,3], compared at the views' height. Returns
    ``(images, g)``."""
    items = [_as_torch(im) for im in images]
    h = int(np.median([im.shape[0] for im in items]))
    p = torch.from_numpy(resize_style(_as_torch(painting).detach().cpu().numpy(), h)).double()  # [h,w',3]
    e_p = float(detail_energy(p, sigma=sigma))
    e_v = float(np.mean([float(detail_energy(im.double(), sigma=sigma)) for im in items]))
    g = float(min(max(math.sqrt(e_p / e_v), 1.0), max_gain)) if e_v > 0 else 1.0
    if g == 1.0:
        return list(images), g
    out = [(im + (g - 1.0) * luminance_detail(im, sigma).to(im)[..., None]).clamp(0.0, 1.0) for im in items]
    return [o.numpy() if isinstance(src, np.ndarray) else o for o, src in zip(out, images)], g


def apply_color_transform(img, m: torch.Tensor, t: torch.Tensor, clamp: bool = True):
    """x' = M x + t on the last axis, clamped to [0,1]; keeps numpy/torch, dtype and device of ``img``."""
    x = _as_torch(img)
    y = x.double() @ m.to(x.device).T + t.to(x.device)  # [...,3]
    y = y.clamp(0.0, 1.0) if clamp else y
    y = y.to(x.dtype)
    return y.numpy() if isinstance(img, np.ndarray) else y


# sRGB (D65) -> XYZ, the IEC 61966-2-1 matrix, and the D65 white that OpenCV also uses.
_RGB2XYZ = torch.tensor([[0.412453, 0.357580, 0.180423],
                         [0.212671, 0.715160, 0.072169],
                         [0.019334, 0.119193, 0.950227]], dtype=torch.float64)
_WHITE = torch.tensor([0.950456, 1.0, 1.088754], dtype=torch.float64)
_EPS_T = (6.0 / 29.0) ** 3  # CIE switch from the cube root to the linear segment
_TINY = 1e-10  # keeps pow() bases positive so the unused branch of torch.where has a finite gradient
LUMA = (0.299, 0.587, 0.114)


def rgb_to_lab(rgb: torch.Tensor) -> torch.Tensor:
    """sRGB in [0,1], channel-last [...,3] -> Lab (L in [0,100], a/b roughly [-128,127]); differentiable."""
    c = rgb.clamp_min(0.0)  # renders are >= 0 by construction; negatives have no sRGB meaning
    lin = torch.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055).clamp_min(_TINY) ** 2.4)
    m, white = _constant(_RGB2XYZ, rgb.dtype, rgb.device), _constant(_WHITE, rgb.dtype, rgb.device)
    xyz = lin @ m.T / white  # [...,3], normalized by the white point
    f = torch.where(xyz > _EPS_T, xyz.clamp_min(_TINY) ** (1.0 / 3.0), xyz / (3 * (6.0 / 29.0) ** 2) + 4.0 / 29.0)
    L = 116.0 * f[..., 1] - 16.0
    a = 500.0 * (f[..., 0] - f[..., 1])
    b = 200.0 * (f[..., 1] - f[..., 2])
    return torch.stack([L, a, b], dim=-1)


_on_device: dict = {}  # (a module constant's id, dtype, device) -> that constant there: made once, so that no call
# copies from the host (a copy from pageable memory waits for the GPU, and a CUDA graph cannot capture it)


def _constant(t: torch.Tensor, dtype, device) -> torch.Tensor:
    key = (id(t), dtype, str(device))
    c = _on_device.get(key)
    if c is None:
        c = _on_device[key] = t.to(dtype=dtype, device=device)
    return c


_LUMA = torch.tensor(LUMA, dtype=torch.float64)


def _luma(dtype, device) -> torch.Tensor:
    return _constant(_LUMA, dtype, device)


def lab_chroma_stats(img: torch.Tensor) -> torch.Tensor:
    """[4] = (μ_a, μ_b, σ_a, σ_b): mean and population standard deviation of Lab a, b over the pixels of an sRGB
    image [...,3] (no gradient). A view's constant target is summarized once: ``lab_chroma_loss(render,
    target_stats=lab_chroma_stats(target))``."""
    with torch.no_grad():
        return chroma_stats_of(lab_ab_jacobian(img))


def lab_chroma_loss(render: torch.Tensor, target: torch.Tensor | None = None, *,
                    target_stats: torch.Tensor | None = None) -> torch.Tensor:
    """½(‖Δμ_ab‖₁ + ‖Δσ_ab‖₁): mean and standard deviation of the a, b channels of the render vs the target
    (the recolored photo of the same view), in Lab units; L1 norms sum over the two channels.
    Inputs [H,W,3] (or any [...,3]) sRGB in [0,1], float32 or float64. ``target_stats``: :func:`lab_chroma_stats`
    of the target, computed once per view, instead of ``target``.

    Two Warp kernels (kernels/lab.py, launched by losses/lab_warp.py: per-pixel Lab (a, b) with its Jacobian, and
    the backward through the statistics) and five small torch reductions: ~8 kernel launches per step where
    autograd through :func:`rgb_to_lab` took ~50 (the formulas are the same; tests/test_losses_color.py compares them)."""
    if target_stats is None:
        if target is None:
            raise ValueError("lab_chroma_loss needs target or target_stats")
        target_stats = lab_chroma_stats(target.to(render))
    return LabChromaLossFn.apply(render, target_stats)


_VAR_FLOOR = 1e-30


def lab_chroma_loss_torch(render: torch.Tensor, target_stats: torch.Tensor) -> torch.Tensor:
    """:func:`lab_chroma_loss` through :func:`rgb_to_lab` and autograd (~50 small kernels a call where the Warp
    version takes ~8): what a CUDA graph of the stylize terms replays, since it records only torch's own kernels."""
    ab = rgb_to_lab(render.reshape(-1, 3))[:, 1:]  # [P,2]
    var, mu = torch.var_mean(ab, dim=0, correction=0)
    sd = var.clamp_min(_VAR_FLOOR).sqrt()  # a grey render (σ = 0): a 0 gradient there, as the Warp version; not NaN
    return 0.5 * torch.linalg.vector_norm(torch.cat([mu, sd]) - target_stats.reshape(4), ord=1)


def luminance(img: torch.Tensor) -> torch.Tensor:
    """Y = 0.299R + 0.587G + 0.114B replicated to 3 channels (paper §3.3). [...,H,W,3] channel-last, or
    [B,3,H,W] (4-D with 3 channels on axis 1). Same shape out."""
    w = _luma(img.dtype, img.device)
    if img.dim() == 4 and img.shape[1] == 3 and img.shape[-1] != 3:
        return (img * w.view(1, 3, 1, 1)).sum(1, keepdim=True).expand_as(img)
    return (img @ w).unsqueeze(-1).expand_as(img)


def gray_gradient(img: torch.Tensor) -> torch.Tensor:
    """``img`` [...,3] unchanged in value; its gradient spread evenly over the three channels (each gets the mean
    of the incoming three). A luminance-only term fed this image moves a pixel's colour along the grey axis
    (R, G, B by the same amount), which leaves its chroma RGB - Y, instead of along Y's weights (0.299, 0.587,
    0.114), which shifts Lab a, b about as much as L."""
    m = img.mean(-1, keepdim=True)  # [...,1]
    return img.detach() + (m - m.detach())


def chroma(img: torch.Tensor) -> torch.Tensor:
    """The chroma residual ``img - Y`` (what is left of a colour once its luminance is taken out): same shape out."""
    return img - luminance(img)


def recolor_sh(sh: torch.Tensor, m: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Spherical-harmonic colours of Gaussians under the colour map ``x' = M x + t``: since color =
    SH(dir) + 0.5 and blending is an affine combination (Σ αT + T_final = 1), rendering the mapped Gaussians
    over background ``M·bg + t`` gives exactly ``M·render + t`` wherever no colour is clamped at 0. So
    the pre-process fit can start from the palette it fits to (every coefficient mixes channels by M; the DC
    term also takes the shift). ``sh`` [N,K,3] -> [N,K,3]."""
    m = m.to(device=sh.device, dtype=torch.float64)
    t = t.to(device=sh.device, dtype=torch.float64)
    out = sh.double() @ m.T  # [N,K,3]
    out[:, 0] += (m @ torch.full((3,), 0.5, dtype=torch.float64, device=sh.device) + t - 0.5) / SH_C0
    return out.to(sh.dtype)
