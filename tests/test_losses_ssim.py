"""SSIM / fit loss / PSNR against a float64 OpenCV implementation (cv2.GaussianBlur, zero border), and the fused Warp
SSIM / fit loss (kernels/ssim.py, what ``ssim`` and ``fit_loss`` run) against their pure-torch twins."""
import sys

import cv2
import numpy as np
import pytest
import torch

from tlvg_warp.losses import fit_loss, psnr, ssim
from tlvg_warp.losses.ssim import fit_loss_torch, fused_terms, ssim_map, ssim_torch, to_bchw

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


# ---- the fused Warp SSIM (kernels/ssim.py) against its pure-torch twin -------------------------------------------
# ssim / fit_loss run the Warp kernels for float32 and float64; ssim_torch / fit_loss_torch (the former torch code)
# are the oracle. test_fused_path_is_taken_and_torch_for_the_rest makes sure that the comparisons below do compare
# two implementations.
SSIM_MOD = sys.modules["tlvg_warp.losses.ssim"]  # (tlvg_warp.losses.ssim the attribute is the function)
F64_TOL = 1e-12  # float64 both: summation order and the order of a few products differ, nothing else
F64_GRAD_TOL = 1e-10
# float32: σxx = G∗x² − μx² cancels, so each of the two blurs' rounding (~1e-7 absolute) is divided by
# σxx + σyy + C2 >= C2 = 9e-4; on a flat image both the fused map and the torch twin's are ~3e-4 off the float64
# truth per pixel (1e-6 on a textured one). Both are compared with the float64 truth at this bound.
F32_MAP_TOL = 1e-3
F32_MEAN_TOL = 1e-4
F32_GRAD_RTOL = 1e-3  # of the largest gradient entry; measured ~2e-5 on the same images


def _pair(shape, gen, lo=0.0, hi=1.0, noise=0.1):
    y = torch.rand(shape, generator=gen, dtype=torch.float64) * (hi - lo) + lo
    return y + noise * torch.randn(shape, generator=gen, dtype=torch.float64), y  # x not clamped: values as given


def _cases():
    """(name, img, ref) in float64: odd sizes, images smaller than the window, a batch, values outside [0, 1],
    and inputs whose strides are not the layout's (a channels-last batch, a strided crop of an [H,W,3] image)."""
    gen = torch.Generator().manual_seed(3)
    yield ("13x17", *_pair((13, 17, 3), gen))
    yield ("1x1", *_pair((1, 1, 3), gen))
    yield ("5x300", *_pair((5, 300, 3), gen))
    yield ("11x4", *_pair((11, 4, 3), gen))
    yield ("batch 2x3x9x14", *_pair((2, 3, 9, 14), gen))
    yield ("outside [0,1]", *_pair((12, 7, 3), gen, -0.5, 1.5, 0.3))
    x, y = _pair((2, 16, 23, 3), gen)
    yield "channels-last batch", x.permute(0, 3, 1, 2), y.permute(0, 3, 1, 2)
    x, y = _pair((26, 35, 3), gen)
    yield "strided crop", x[1::2, ::3], y[1::2, ::3]


def _planes(t):
    """[H,W,3] or [B,3,H,W] -> [B·3,H,W], the kernels' per-pixel layout."""
    t = to_bchw(t)
    return t.reshape(-1, *t.shape[-2:])


def test_fused_forward_equals_torch_twin_float64():
    """Per-pixel SSIM map and L1 term of the kernels, and the scalar losses, against the twin. Fails with a wrong
    border (clamped or mirrored instead of zero, a window off by one: the 1x1, 11x4 and 13x17 maps are mostly
    border), rows and columns or H and W mixed up (the non-square 5x300 and 11x4), the strides of a permuted or
    cropped input ignored, a wrong weight or constant in the value (the fit losses), or an input clamped to [0, 1]."""
    for name, x, y in _cases():
        v, dS, _ = fused_terms(x, y, 0.0, 1.0, 0.0, False)
        assert dS is None
        assert (v - _planes(ssim_map(x, y))).abs().max() < F64_TOL, name
        l1, _, _ = fused_terms(x, y, 1.0, 0.0, 0.0, False)
        assert torch.equal(l1, _planes((x - y).abs())), name
        assert abs(ssim(x, y).item() - ssim_torch(x, y).item()) < F64_TOL, name
        for lam in (0.2, 0.7):
            assert abs(fit_loss(x, y, lam).item() - fit_loss_torch(x, y, lam).item()) < F64_TOL, (name, lam)
        assert fit_loss(x, y).item() == fit_loss(x, y, 0.2).item()  # the default is SPEC's 0.8 L1 + 0.2 (1 − SSIM)


def test_fused_float32_within_float32_rounding_of_the_float64_truth():
    """float32 kernels against the float64 twin at F32_*_TOL (see there why): a textured and a flat pair, forward
    and gradient. Fails where the float32 module computes something else than the float64 one (the kernels are
    built per type: a wrong window, constant or term in one of them) beyond float32 rounding."""
    gen = torch.Generator().manual_seed(5)
    x, y = _pair((40, 60, 3), gen)
    flat = torch.full((40, 60, 3), 0.7, dtype=torch.float64)
    noisy = flat + 1e-3 * torch.randn(flat.shape, generator=gen, dtype=flat.dtype)
    for x64, y64 in ((x.clamp(0, 1), y), (flat, noisy)):
        x32, y32 = x64.float(), y64.float()
        v, _, _ = fused_terms(x32, y32, 0.0, 1.0, 0.0, False)
        assert v.dtype == torch.float32
        assert (v.double() - _planes(ssim_map(x64, y64))).abs().max() < F32_MAP_TOL
        assert abs(fit_loss(x32, y32).item() - fit_loss_torch(x64, y64).item()) < F32_MEAN_TOL
        a, b = x32.clone().requires_grad_(True), x64.clone().requires_grad_(True)
        fit_loss(a, y32).backward()
        fit_loss_torch(b, y64).backward()
        assert a.grad.dtype == torch.float32
        assert (a.grad.double() - b.grad).abs().max() < F32_GRAD_RTOL * b.grad.abs().max()


def test_fused_gradient_equals_autograd_of_the_twin_float64():
    """img's gradient (ssim and fit_loss, an upstream weight of 2.5) against torch autograd of the twin. Fails
    without the −2μx·∂S/∂σxx or −μy·∂S/∂σxy terms of ∂S/∂μx, without the 2x or y factors, with a backward blur
    that is not zero-padded, a wrong 1/N or an ignored upstream gradient, the L1 sign flipped or dropped, or the
    gradient written in the wrong layout (the channels-last and cropped cases)."""
    for name, x, y in _cases():
        for fused, twin in ((ssim, ssim_torch), (fit_loss, fit_loss_torch),
                            (lambda a, b: fit_loss(a, b, 0.7), lambda a, b: fit_loss_torch(a, b, 0.7))):
            a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
            (2.5 * fused(a, y)).backward()
            (2.5 * twin(b, y)).backward()
            assert a.grad.shape == x.shape
            assert (a.grad - b.grad).abs().max() < F64_GRAD_TOL, name
            assert b.grad.abs().max() > 1e-4, name  # not vacuous


def test_fused_gradient_finite_differences():
    """torch.autograd.gradcheck (central differences of the fused forward itself) on a tiny image: checks the
    backward kernels independently of the twin. |x − y| >= 0.05 keeps the L1 kink out of the differences."""
    gen = torch.Generator().manual_seed(7)
    y = torch.rand(4, 6, 3, generator=gen, dtype=torch.float64)
    x = (y + 0.05 + 0.2 * torch.rand(y.shape, generator=gen, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: fit_loss(t, y), (x,), eps=1e-6, atol=1e-8, rtol=1e-6)
    assert torch.autograd.gradcheck(lambda t: ssim(t, y), (x,), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_identical_images_give_ssim_one_and_zero_gradient():
    """SSIM(x, x) = 1 and no gradient (the minimum of the fit loss), float64 and float32, values in and outside
    [0, 1]. Fails with a ∂S/∂μx missing one of its variance terms or a backward without the 2x factor (each
    leaves a gradient at the minimum)."""
    gen = torch.Generator().manual_seed(9)
    for x in (torch.rand(9, 14, 3, generator=gen, dtype=torch.float64),
              torch.randn(2, 3, 7, 12, generator=gen, dtype=torch.float64)):
        for dtype, tol in ((torch.float64, 1e-14), (torch.float32, 1e-6)):
            a = x.to(dtype).clone().requires_grad_(True)
            s = ssim(a, a.detach())
            assert abs(s.item() - 1.0) <= tol
            s.backward()
            assert a.grad.abs().max() <= tol
            b = x.to(dtype).clone().requires_grad_(True)
            loss = fit_loss(b, b.detach())
            assert abs(loss.item()) <= tol
            loss.backward()
            assert b.grad.abs().max() <= tol


def test_fused_path_is_taken_and_torch_for_the_rest(monkeypatch):
    """float32/float64 pairs never reach the twin (else every comparison above would be the twin against itself);
    another dtype, a reference that requires grad, shapes that differ and fused=False go to the twin.
    The gradient accumulates into img.grad (Warp writes a buffer of its own), and no_grad works."""
    calls = []
    monkeypatch.setattr(SSIM_MOD, "ssim_torch", lambda *a: calls.append("ssim") or ssim_torch(*a))
    monkeypatch.setattr(SSIM_MOD, "fit_loss_torch", lambda *a: calls.append("fit") or fit_loss_torch(*a))
    gen = torch.Generator().manual_seed(11)
    x, y = _pair((6, 8, 3), gen)
    for dtype in (torch.float64, torch.float32):
        a = x.to(dtype).clone().requires_grad_(True)
        fit_loss(a, y).backward()
        g1 = a.grad.clone()
        fit_loss(a, y).backward()
        assert torch.allclose(a.grad, 2 * g1)
        ssim(a, y.to(dtype))
        with torch.no_grad():
            assert fit_loss(a, y).grad_fn is None
    assert calls == []
    s16 = ssim(x.to(torch.bfloat16), y.to(torch.bfloat16))
    assert s16.dtype == torch.bfloat16 and calls == ["ssim"]
    r = y.clone().requires_grad_(True)
    calls.clear()
    fit_loss(x, r).backward()
    assert r.grad is not None and calls[0] == "fit"
    calls.clear()
    with pytest.raises(RuntimeError):  # shapes that differ: the twin's error is kept
        ssim(x, y[:5])
    assert calls == ["ssim"]
    calls.clear()
    a = x.clone().requires_grad_(True)
    got = fit_loss(a, y, 0.3, fused=False)
    assert calls[0] == "fit" and torch.equal(got, fit_loss_torch(x, y, 0.3))  # (the twin calls ssim_torch)
    got.backward()
    assert a.grad is not None
    calls.clear()
    got = ssim(x, y, fused=False)
    assert calls == ["ssim"] and torch.equal(got, ssim_torch(x, y))
    monkeypatch.setenv("TLVG_WARP_FUSED_SSIM", "0")  # the environment no longer picks the path
    calls.clear()
    fit_loss(x, y)
    ssim(x, y)
    assert calls == []


def test_loop_photometric_loss_is_the_fit_loss():
    """The fit phase's loss (train/loop.py) is (1 − λ)·L1 + λ·(1 − SSIM) for every λ, L1 alone at λ = 0, with the
    twin's gradient. Fails if the loop passes λ in the wrong place (e.g. as the L1 weight) or drops a term."""
    from tlvg_warp.train.loop import photometric_loss

    gen = torch.Generator().manual_seed(13)
    x, y = _pair((10, 15, 3), gen)
    for lam in (0.0, 0.2, 0.6, 1.0):
        a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
        got, want = photometric_loss(a, y, lam), fit_loss_torch(b, y, lam)
        assert abs(got.item() - want.item()) < F64_TOL, lam
        got.backward()
        want.backward()
        assert (a.grad - b.grad).abs().max() < F64_GRAD_TOL, lam
