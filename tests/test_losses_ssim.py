"""SSIM / fit loss / PSNR against a float64 OpenCV implementation (cv2.GaussianBlur, zero border)."""
import cv2
import numpy as np
import torch

from tlvg_warp.losses import fit_loss, psnr, ssim

SSIM_TOL = 1e-10  # both float64; only summation order differs


def ssim_cv(x, y):
    blur = lambda z: cv2.GaussianBlur(z, (11, 11), 1.5, borderType=cv2.BORDER_CONSTANT)  # noqa: E731
    vals = []
    for ch in range(3):
        a, b = x[..., ch], y[..., ch]
        ma, mb = blur(a), blur(b)
        saa, sbb, sab = blur(a * a) - ma ** 2, blur(b * b) - mb ** 2, blur(a * b) - ma * mb
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        vals.append(((2 * ma * mb + c1) * (2 * sab + c2)) / ((ma ** 2 + mb ** 2 + c1) * (saa + sbb + c2)))
    return float(np.mean(vals))


def test_ssim_matches_opencv_oracle_and_is_one_on_identity():
    rng = np.random.default_rng(0)
    x = rng.random((37, 50, 3))
    y = np.clip(x + 0.1 * rng.standard_normal(x.shape), 0, 1)
    got = ssim(torch.from_numpy(x), torch.from_numpy(y)).item()
    assert abs(got - ssim_cv(x, y)) < SSIM_TOL
    assert got < 0.99  # the noise really lowers it (the comparison is not vacuous)
    assert abs(ssim(torch.from_numpy(x), torch.from_numpy(x)).item() - 1.0) < SSIM_TOL
    # batch layout [B,3,H,W] gives the mean over the batch
    xb = torch.from_numpy(np.stack([x, y])).permute(0, 3, 1, 2)
    yb = torch.from_numpy(np.stack([y, y])).permute(0, 3, 1, 2)
    assert abs(ssim(xb, yb).item() - (ssim_cv(x, y) + 1.0) / 2) < SSIM_TOL


def test_fit_loss_and_psnr_closed_forms_and_gradient():
    rng = np.random.default_rng(1)
    y = torch.from_numpy(rng.random((20, 24, 3)))
    x = (y + 0.05).clone().requires_grad_(True)  # constant shift: L1 = 0.05 exactly
    loss = fit_loss(x, y)
    expect = 0.8 * 0.05 + 0.2 * (1 - ssim_cv(x.detach().numpy(), y.numpy()))
    assert abs(loss.item() - expect) < 1e-9
    loss.backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert abs(psnr(x, y) - (-10 * np.log10(0.05 ** 2))) < 1e-6
