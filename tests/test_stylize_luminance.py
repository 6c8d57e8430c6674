"""Luminance–structure decoupling (paper §3.3): the luminance-only style loss does not see chroma.

Property, to first order: for any per-pixel color change δ with no luminance (0.299, 0.587, 0.114)·δ = 0
(a pure chroma change), the luminance-only loss's directional derivative ⟨∇L, δ⟩ is 0, while the RGB
loss's is not; and a finite chroma-only change leaves the luminance loss unchanged. Oracle: the directional
derivative by central differences in float64 (independent of autograd) and the YIQ definition of Y.
The feature network is a random VGG (its weights do not matter for this property)."""
import pytest
import torch

from tlvg_warp.losses import fast_loss, flatten_feats, load_vgg, luminance

Y = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
FD_H = 1e-5  # central-difference step in float64: truncation ~h² · curvature, round-off ~1e-16/h
ZERO_TOL = 1e-7  # |⟨∇L_lum, δ⟩| bound: float64 round-off of a sum over ~10⁴ terms (gradients are O(1e-3))
RGB_MIN = 1e-4  # the RGB loss's derivative along the same δ is at least this (it sees chroma)


@pytest.fixture(scope="module")
def setup():
    torch.manual_seed(0)
    net = load_vgg("random").double()
    img = torch.rand(32, 40, 3, dtype=torch.float64) * 0.8 + 0.1
    style = torch.rand(48, 48, 3, dtype=torch.float64)
    s_lum = flatten_feats(net(luminance(style))).detach()
    s_rgb = flatten_feats(net(style)).detach()
    # a chroma-only direction: random, with its luminance component removed at every pixel
    d = torch.randn(32, 40, 3, dtype=torch.float64)
    d = d - ((d @ Y) / (Y @ Y))[..., None] * Y
    return net, img, s_lum, s_rgb, d


def _loss(net, img, s, lum, match):
    x = luminance(img) if lum else img
    a = flatten_feats(net(x))
    # the FAST target's match is held fixed (it is computed without gradient in the loss)
    return fast_loss(a, s) if match is None else match(a, s)


def test_chroma_direction_has_no_luminance(setup):
    _, _, _, _, d = setup
    assert (d @ Y).abs().max() < 1e-12 and d.abs().mean() > 0.1


def test_luminance_loss_ignores_chroma_to_first_order(setup):
    net, img, s_lum, s_rgb, d = setup
    x = img.clone().requires_grad_(True)
    _loss(net, x, s_lum, True, None).backward()
    g_lum = (x.grad * d).sum()
    x2 = img.clone().requires_grad_(True)
    _loss(net, x2, s_rgb, False, None).backward()
    g_rgb = (x2.grad * d).sum()
    assert abs(float(g_lum)) < ZERO_TOL
    assert abs(float(g_rgb)) > RGB_MIN
    # the gradient of the luminance loss is per pixel a multiple of the luminance weights
    along = (x.grad @ Y)[..., None] * Y / (Y @ Y)
    assert (x.grad - along).abs().max() < 1e-12 + 1e-9 * x.grad.abs().max()


def test_directional_derivative_by_finite_differences(setup):
    net, img, s_lum, s_rgb, d = setup
    with torch.no_grad():
        fd_lum = (_loss(net, img + FD_H * d, s_lum, True, None) - _loss(net, img - FD_H * d, s_lum, True, None)) / (2 * FD_H)
        fd_rgb = (_loss(net, img + FD_H * d, s_rgb, False, None) - _loss(net, img - FD_H * d, s_rgb, False, None)) / (2 * FD_H)
        # a finite chroma change: the luminance loss sees exactly the same input
        same = _loss(net, img + 0.05 * d, s_lum, True, None) - _loss(net, img, s_lum, True, None)
    assert abs(float(fd_lum)) < ZERO_TOL
    assert abs(float(fd_rgb)) > RGB_MIN
    assert abs(float(same)) < 1e-12


def test_chroma_tv_in_lab_is_opencv_lab_tv():
    """loss.chroma_tv_space lab: the TV of Lab a*, b* x LAB_TV_SCALE. Oracle: OpenCV's Lab (float path) of the same
    image, its neighbour differences summed in numpy. Catches L* read instead of a*, b*, a lost scale, the RGB
    chroma residual read in lab mode; and a grey-axis stripe on a saturated dark blue, whose Lab chroma moves with
    lightness, costs in Lab and not in RGB (on grey, in neither)."""
    import cv2
    import numpy as np

    from tlvg_warp.stylize.pipeline import LAB_TV_SCALE, chroma_tv_loss

    gen = torch.Generator().manual_seed(2)
    img = torch.rand(9, 11, 3, generator=gen, dtype=torch.float64)
    ab = cv2.cvtColor(img.numpy().astype(np.float32), cv2.COLOR_RGB2Lab)[..., 1:].astype(np.float64) * LAB_TV_SCALE
    want = (np.diff(ab, axis=0) ** 2).mean() + (np.diff(ab, axis=1) ** 2).mean()
    assert float(chroma_tv_loss(img, "lab")) == pytest.approx(want, rel=2e-3)

    def stripes(base):  # alternate columns 0.05 darker along the grey axis
        out = torch.tensor(base, dtype=torch.float64).expand(6, 6, 3).clone()
        out[:, ::2] -= 0.05
        return out

    blue, grey = stripes((0.08, 0.08, 0.45)), stripes((0.45, 0.45, 0.45))
    assert float(chroma_tv_loss(grey, "lab")) < 1e-9 and float(chroma_tv_loss(grey, "rgb")) < 1e-12
    # RGB's chroma residual does not see a grey-axis stripe at all; Lab's chroma does, on the saturated blue
    assert float(chroma_tv_loss(blue, "rgb")) < 1e-12 and float(chroma_tv_loss(blue, "lab")) > 1e-5
