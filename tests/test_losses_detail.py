"""match_detail: the recolored views get the painting's level of luminance detail. A closed form against an
OpenCV blur (float64), the gain's clamps, chroma differences kept exactly, and on real photos (fern and beer x
Starry Night over the Rhône, where the palette transfer flattens them) the evaluation's detail measure rising
while the Lab chroma spread stays. The real-data test skips with a message when ../shared/data is absent."""
import cv2
import numpy as np
import pytest
import torch

from _io_helpers import data_root
from tlvg_warp.eval import metrics as M
from tlvg_warp.losses import color_transfer, match_detail
from tlvg_warp.losses.color import DETAIL_MAX_GAIN, DETAIL_SIGMA

LUMA = np.array([0.299, 0.587, 0.114])


def _hp(img: np.ndarray) -> np.ndarray:
    """Y minus its σ 2 blur, by OpenCV with the same 13-tap kernel and reflected border (the oracle)."""
    y = img @ LUMA
    r = int(round(3 * DETAIL_SIGMA))
    return y - cv2.GaussianBlur(y, (2 * r + 1, 2 * r + 1), DETAIL_SIGMA, borderType=cv2.BORDER_REFLECT_101)


def _scene(rng, amp):
    yy, xx = np.mgrid[0:48, 0:64]
    base = 0.5 + 0.1 * np.sin(xx / 9.0)[..., None] * np.array([1.0, 0.6, 0.3])
    return base + amp * rng.standard_normal((48, 64, 3)) * np.array([1.0, 0.8, 1.2])


def test_match_detail_is_the_closed_form_gain_on_the_high_pass():
    rng = np.random.default_rng(0)
    views = [_scene(rng, 0.01) for _ in range(3)]
    painting = _scene(rng, 0.03)  # about 3x the views' detail amplitude: a gain inside (1, max)
    out, g = match_detail([torch.from_numpy(v) for v in views], torch.from_numpy(painting))
    e_p = (_hp(painting) ** 2).mean()
    e_v = np.mean([(_hp(v) ** 2).mean() for v in views])
    assert 1.0 < g < DETAIL_MAX_GAIN
    assert g == pytest.approx(np.sqrt(e_p / e_v), rel=1e-9)
    for v, o in zip(views, out):
        assert o.min() > 0 and o.max() < 1  # the premise: nothing clipped
        want = v + (g - 1) * _hp(v)[..., None]
        assert np.abs(o.numpy() - want).max() < 1e-9
        # the same value is added to every channel: colour differences (chroma) are untouched
        assert np.abs((o.numpy()[..., 0] - o.numpy()[..., 1]) - (v[..., 0] - v[..., 1])).max() < 1e-12


def test_match_detail_never_lowers_detail_and_caps_the_gain():
    rng = np.random.default_rng(1)
    views = [_scene(rng, 0.02) for _ in range(2)]
    flat_painting = _scene(rng, 0.0)  # less detail than the views: returned as they are
    out, g = match_detail(views, torch.from_numpy(flat_painting))
    assert g == 1.0 and all(o is v for o, v in zip(out, views))
    busy_painting = _scene(rng, 0.5)  # far more: the gain stops at the cap
    _, g = match_detail([torch.from_numpy(v) for v in views], torch.from_numpy(busy_painting))
    assert g == DETAIL_MAX_GAIN


ROOT = data_root()


@pytest.mark.skipif(ROOT is None, reason="../shared/data (or $TLVG_DATA) not found: real-photo detail test skipped")
@pytest.mark.parametrize("scene,pattern", [("fern", "fern_llff/images_8/*"), ("beer", "beer_colmap/images/*")])
def test_match_detail_restores_detail_the_palette_took_on_real_photos(scene, pattern):
    """Measured (12 photos at 256 rows): fern 2.07 -> ARF 0.31 -> 0.80, beer 0.73 -> 0.22 -> 0.56 of the
    painting's detail, Lab a,b spread within 0.5 units (docs/study.md)."""
    def rd(p, rows):
        im = cv2.imread(str(p), cv2.IMREAD_COLOR)[:, :, ::-1].astype(np.float32) / 255
        return cv2.resize(im, (round(im.shape[1] * rows / im.shape[0]), rows), interpolation=cv2.INTER_AREA)

    photos = [rd(p, 256) for p in sorted((ROOT / "scenes").glob(pattern))[:12]]
    painting = rd(ROOT / "styles" / "starry_night_over_the_rhone.png", 512)  # its working size: twice the views
    recolored, _, _ = color_transfer(photos, painting)
    boosted, g = match_detail(recolored, torch.from_numpy(painting))
    h, w = photos[0].shape[:2]
    ref = M.hf_energy(M.luma(M.sticker(painting, h, w)))  # the evaluation's detail measure, by OpenCV
    detail = lambda xs: np.mean([M.hf_energy(M.luma(np.asarray(x, np.float32))) for x in xs]) / ref  # noqa: E731
    spread = lambda xs: np.mean([M.lab_ab(np.asarray(x, np.float32)).reshape(-1, 2).std(0) for x in xs])  # noqa: E731
    assert detail(recolored) < 0.4  # the premise: the palette flattened them
    assert g > 1.4 and detail(boosted) > 2 * detail(recolored)
    assert abs(spread(boosted) - spread(recolored)) < 0.05 * spread(recolored)
