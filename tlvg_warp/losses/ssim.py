"""Photometric fit losses: SSIM (11x11 Gaussian window, sigma 1.5, as 3DGS), 0.8*L1 + 0.2*(1-SSIM), PSNR.

Images are [H,W,3] (channel-last, one image) or [B,3,H,W]; values in [0,1]. Everything is differentiable.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

WINDOW = 11
SIGMA = 1.5
C1 = 0.01 ** 2  # the usual SSIM stabilizers for a dynamic range of 1
C2 = 0.03 ** 2

_kernels: dict = {}


def _gauss1d(size: int, sigma: float, dtype, device) -> torch.Tensor:
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
    g = _gauss1d(WINDOW, SIGMA, x.dtype, x.device)
    mx, my = _blur(x, g), _blur(y, g)  # [B,3,H,W]
    sxx = _blur(x * x, g) - mx * mx
    syy = _blur(y * y, g) - my * my
    sxy = _blur(x * y, g) - mx * my
    return ((2 * mx * my + C1) * (2 * sxy + C2)) / ((mx * mx + my * my + C1) * (sxx + syy + C2))


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean SSIM over pixels, channels and batch (a 0-dim tensor)."""
    return ssim_map(img, ref).mean()


def fit_loss(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """0.8 * L1 + 0.2 * (1 - SSIM): the pre- and post-process photometric loss (SPEC §3)."""
    return 0.8 * (img - ref.to(img.dtype)).abs().mean() + 0.2 * (1.0 - ssim(img, ref))


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    """PSNR in dB for [0,1] images (inf for identical images)."""
    mse = float(((img.detach().double() - ref.detach().double()) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)
