"""Photometric fit losses: SSIM (11x11 Gaussian window, sigma 1.5, zero padding, as 3DGS), (1 − λ)·L1 + λ·(1 − SSIM)
(λ = 0.2: 0.8*L1 + 0.2*(1-SSIM)), PSNR.

Images are [H,W,3] (channel-last, one image) or [B,3,H,W]; values in [0,1] (taken as given). Everything is
differentiable with respect to the image; the reference is a constant.

``ssim`` and ``fit_loss`` run fused in Warp (kernels/ssim.py: two kernels forward, two backward, the L1 in the same
kernels; through torch they took ~30 launches forward and more backward) for float32 and float64
images on the CPU and CUDA. ``ssim_torch`` / ``fit_loss_torch`` are their pure-torch twins: the tests' oracle,
and the fallback for anything else (other dtypes or devices, a reference that requires grad, an empty image,
shapes that differ). ``fused=False`` forces the twins (for A/B runs).
"""
from __future__ import annotations  # (no kernels in this file)

import math

import torch
import torch.nn.functional as F

from ..kernels.ssim import C1, C2, SIGMA, WINDOW, ssim_kernels
from ..launch import ct, fast_launch, init_warp, warp_on

_kernels: dict = {}


def gauss1d(size: int, sigma: float, dtype, device) -> torch.Tensor:
    """A normalized 1-D Gaussian of ``size`` taps (cached per size, σ, dtype and device)."""
    key = (size, sigma, dtype, str(device))
    if key not in _kernels:
        x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
        g = torch.exp(-x ** 2 / (2 * sigma ** 2))
        _kernels[key] = (g / g.sum()).to(dtype=dtype, device=device)
    return _kernels[key]  # [size]


def to_bchw(img: torch.Tensor) -> torch.Tensor:
    """[H,W,3] -> [1,3,H,W]; [B,3,H,W] passes through."""
    if img.dim() == 3:
        return img.permute(2, 0, 1).unsqueeze(0)
    if img.dim() == 4:
        return img
    raise ValueError(f"expected [H,W,3] or [B,3,H,W], got {tuple(img.shape)}")


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable depthwise Gaussian, zero padding (same as 3DGS's conv2d with padding=window//2)."""
    c, r = x.shape[1], g.numel() // 2
    x = F.conv2d(x, g.view(1, 1, 1, -1).expand(c, 1, 1, -1), padding=(0, r), groups=c)
    return F.conv2d(x, g.view(1, 1, -1, 1).expand(c, 1, -1, 1), padding=(r, 0), groups=c)


def ssim_map(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    x, y = to_bchw(img), to_bchw(ref).to(img.dtype)
    g = gauss1d(WINDOW, SIGMA, x.dtype, x.device)
    mx, my = _blur(x, g), _blur(y, g)  # [B,3,H,W]
    sxx = _blur(x * x, g) - mx * mx
    syy = _blur(y * y, g) - my * my
    sxy = _blur(x * y, g) - mx * my
    return ((2 * mx * my + C1) * (2 * sxy + C2)) / ((mx * mx + my * my + C1) * (sxx + syy + C2))


def ssim_torch(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean SSIM over pixels, channels and batch (a 0-dim tensor), in torch (the fused ``ssim``'s twin)."""
    return ssim_map(img, ref).mean()


def fit_loss_torch(img: torch.Tensor, ref: torch.Tensor, lam: float = 0.2) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM) in torch (the fused ``fit_loss``'s twin)."""
    return (1.0 - lam) * (img - ref.to(img.dtype)).abs().mean() + lam * (1.0 - ssim_torch(img, ref))


def _fused(img: torch.Tensor, ref: torch.Tensor) -> bool:
    """Whether the Warp kernels can take this pair (else the torch twin does)."""
    return (img.dtype in (torch.float32, torch.float64) and img.device.type in ("cpu", "cuda")
            and img.dim() in (3, 4) and tuple(ref.shape) == tuple(img.shape) and ref.device == img.device
            and img.numel() > 0 and not (ref.requires_grad and torch.is_grad_enabled()))


def _warp_kernels(dtype: torch.dtype):
    init_warp()
    return ssim_kernels("float32" if dtype == torch.float32 else "float64")


def fused_terms(img: torch.Tensor, ref: torch.Tensor, a: float, b: float, c: float, need_grad: bool):
    """The fused forward, no autograd: (value [B·C,H,W] = a·|img − ref| + b·SSIM map + c per pixel, SSIM's
    derivatives [3,B·C,H,W] (∂S/∂μx with the variance terms, ∂S/∂(G∗x²), ∂S/∂(G∗xy)) or None, ref as img's
    dtype). Pairs that ``_fused`` accepts only."""
    K = _warp_kernels(img.dtype)
    y = ref.detach().to(img.dtype)
    xb, yb = to_bchw(img.detach()), to_bchw(y)
    B, C, H, W = xb.shape
    n = B * C * H * W
    opts = dict(dtype=img.dtype, device=img.device)
    rows = torch.empty(5, B * C, H, W, **opts)
    value = torch.empty(B * C, H, W, **opts)
    dS = torch.empty((3, B * C, H, W) if need_grad else (1, 1, 1, 1), **opts)  # (1, 1, 1, 1): never written
    with warp_on(img.device) as wdev:
        fast_launch(K.rows, n, [ct(xb), ct(yb), ct(rows)], wdev)
        fast_launch(K.cols, n, [ct(xb), ct(yb), ct(rows), a, b, c, int(need_grad), ct(value), ct(dS)], wdev)
    del rows  # stream-ordered: safe with the launches queued
    return value, dS if need_grad else None, y


class FusedPhotometricFn(torch.autograd.Function):
    """a·mean|img − ref| + b·mean SSIM(img, ref) + c (a 0-dim tensor); gradient with respect to img only.

    Forward: kernels/ssim.py's row and column passes write the per-pixel value (torch takes its mean) and, when
    a gradient is wanted, SSIM's three derivatives per pixel, saved for the backward (its two blur passes)."""

    @staticmethod
    def forward(ctx, img, ref, a: float, b: float, c: float, need_grad: bool):
        value, dS, y = fused_terms(img, ref, a, b, c, need_grad)
        if need_grad:
            ctx.save_for_backward(img, y, dS)
            ctx.coefs = (a, b, value.numel())
        return value.mean()

    @staticmethod
    @torch.autograd.function.once_differentiable  # (a double backward raises instead of returning zeros)
    def backward(ctx, g):
        img, y, dS = ctx.saved_tensors
        a, b, n = ctx.coefs
        K = _warp_kernels(img.dtype)
        rows = torch.empty_like(dS)
        grad = torch.empty_like(img)  # Warp writes its own buffer; autograd accumulates it into img.grad
        gs = g.detach().reshape(1).to(img.dtype).contiguous()
        xb, yb, gb = to_bchw(img.detach()), to_bchw(y), to_bchw(grad)
        with warp_on(img.device) as wdev:
            fast_launch(K.grad_rows, n, [ct(dS), ct(rows)], wdev)
            fast_launch(K.grad_cols, n, [ct(xb), ct(yb), ct(rows), ct(gs), a, b, 1.0 / n, ct(gb)], wdev)
        return grad, None, None, None, None, None


def _photometric(img: torch.Tensor, ref: torch.Tensor, a: float, b: float, c: float) -> torch.Tensor:
    return FusedPhotometricFn.apply(img, ref, a, b, c, bool(img.requires_grad and torch.is_grad_enabled()))


def ssim(img: torch.Tensor, ref: torch.Tensor, *, fused: bool = True) -> torch.Tensor:
    """Mean SSIM over pixels, channels and batch (a 0-dim tensor); ``fused=False``: the torch twin."""
    return _photometric(img, ref, 0.0, 1.0, 0.0) if fused and _fused(img, ref) else ssim_torch(img, ref)


def fit_loss(img: torch.Tensor, ref: torch.Tensor, lam: float = 0.2, *, fused: bool = True) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM); λ = 0.2: 0.8 * L1 + 0.2 * (1 - SSIM), the pre- and post-process photometric
    loss (SPEC §3) and 3DGS's. One fused op (the L1 is computed in the SSIM kernels); ``fused=False``: the torch
    twin."""
    lam = float(lam)
    if fused and _fused(img, ref):
        return _photometric(img, ref, 1.0 - lam, -lam, lam)
    return fit_loss_torch(img, ref, lam)


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    """PSNR in dB for [0,1] images (inf for identical images)."""
    mse = float(((img.detach().double() - ref.detach().double()) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)
