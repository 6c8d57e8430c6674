"""The tone palette map (losses/palette.py) against a numpy float64 reference written from its definition, its
closed-form properties, and the reason it exists: a grey photo's faint tints are not blown up into colour. The
palette-snap term against a brute-force float64 reference, finite differences and a toy it exists for."""
import glob
import os

import numpy as np
import pytest
import torch

from tlvg_warp.losses.color import color_transfer
from tlvg_warp.losses.palette import (AffinePalette, TonePalette, painting_colours, palette_snap_loss, palette_transfer,
                                       tone_palette)
from tlvg_warp.types import SH_C0

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")
LUMA = np.array([0.299, 0.587, 0.114])


def _reference(photos, style, bins):
    """The tone map by its definition, in numpy float64: luminance by mean and spread, chroma (R-Y, B-Y) of the
    painting's pixels in equal-count luminance bins, read at the photos' luminance rank (np.interp) of the
    luminance blurred by 2 px (OpenCV's Gaussian blur, reflected border)."""
    import cv2
    y_c = np.concatenate([p.reshape(-1, 3) @ LUMA for p in photos])
    s = style.reshape(-1, 3).astype(np.float64)
    y_s = s @ LUMA
    idx = np.array_split(np.argsort(y_s, kind="stable"), bins)
    cs = np.stack([s[:, 0] - y_s, s[:, 2] - y_s], 1)
    table = []
    for g in idx:
        m = cs[g].mean(0)
        boost = np.linalg.norm(cs[g], axis=1).mean() / max(np.linalg.norm(m), 1e-12)
        table.append(m * min(boost, 2.0))
    table = np.array(table)
    knots = np.quantile(y_c, (np.arange(bins) + 0.5) / bins)
    out = []
    for p in photos:
        y = p.reshape(-1, 3) @ LUMA
        y2 = (y - y_c.mean()) * y_s.std() / y_c.std() + y_s.mean()
        yb = cv2.GaussianBlur(y.reshape(p.shape[:2]), (13, 13), 2.0, borderType=cv2.BORDER_REFLECT_101).ravel()
        cr, cb = np.interp(yb, knots, table[:, 0]), np.interp(yb, knots, table[:, 1])
        r, b = y2 + cr, y2 + cb
        g = (y2 - LUMA[0] * r - LUMA[2] * b) / LUMA[1]
        out.append(np.clip(np.stack([r, g, b], 1), 0, 1).reshape(p.shape))
    return out


def _random_images(seed, n=3, h=20, w=24):  # > 12 px: images (blurred chroma lookup), not colour lists
    rng = np.random.default_rng(seed)
    return [rng.random((h, w, 3)) for _ in range(n)]


def test_tone_map_matches_a_float64_reference():
    photos = _random_images(0)
    style = np.random.default_rng(1).random((30, 40, 3)) * np.array([0.4, 0.6, 1.0])  # a bluish painting
    got, pal = palette_transfer([torch.from_numpy(p) for p in photos], torch.from_numpy(style), "tone")
    want = _reference(photos, style, 32)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g.numpy(), w, atol=1e-6)  # quantiles on ties may differ by a hair
    assert isinstance(pal, TonePalette)


def test_tone_map_gives_the_paintings_luminance_mean_and_spread():
    photos = [np.clip(p * 0.3 + 0.5, 0, 1) for p in _random_images(2)]  # pale, low-contrast photos
    style = np.random.default_rng(3).random((30, 40, 3)) ** 2  # darker, higher-contrast painting
    pal = tone_palette([torch.from_numpy(p) for p in photos], torch.from_numpy(style))
    y = np.concatenate([p.reshape(-1, 3) @ LUMA for p in photos])
    y2 = (y - pal.y_mean[0]) * pal.y_scale + pal.y_mean[1]  # the luminance before clamping
    y_s = style.reshape(-1, 3) @ LUMA
    assert y2.mean() == pytest.approx(y_s.mean(), abs=1e-9) and y2.std() == pytest.approx(y_s.std(), rel=1e-9)


def test_a_grey_photos_tints_are_not_blown_up_into_colour():
    """A flat grey wall with faint random tints: ARF's whitening scales its near-singular chroma covariance to the
    painting's (the tints become strong colour noise); the tone map gives each tone one colour."""
    rng = np.random.default_rng(4)
    y = np.repeat(np.linspace(0.55, 0.75, 32)[None, :], 24, 0)[..., None]  # a smooth luminance ramp
    photo = np.clip(y + rng.normal(0, 0.004, (24, 32, 3)), 0, 1)  # +- 1/255 tints
    style = np.random.default_rng(5).random((40, 40, 3))

    def tint_noise(img):  # the chroma's spread around its per-column (same-tone) mean
        c = np.stack([img[..., 0] - img @ LUMA, img[..., 2] - img @ LUMA], -1)
        return float(np.abs(c - c.mean(0, keepdims=True)).mean())

    arf = color_transfer([photo], style)[0][0]
    tone = palette_transfer([photo], style, "tone")[0][0]
    tone = tone.numpy() if torch.is_tensor(tone) else tone
    assert tint_noise(arf) > 5 * tint_noise(photo)  # the failure this map exists for
    assert tint_noise(tone) < 0.5 * tint_noise(arf)


def _recolored_like_pixels(mode, photos, seed):
    """A palette of ``mode`` from ``photos`` to a random painting, 50 random degree-1 Gaussians and their recolour,
    once it is checked that each one's base colour (DC term) went through the map as a pixel of that colour does.
    Returns (palette, sh, recoloured sh, painting)."""
    rng = np.random.default_rng(seed)
    style = rng.random((30, 40, 3))
    _, pal = palette_transfer([torch.from_numpy(p) for p in photos], torch.from_numpy(style), mode)
    sh = torch.from_numpy(rng.normal(0, 0.5, (50, 4, 3)))  # degree 1
    out = pal.recolor_sh(sh)
    colours = (SH_C0 * sh[:, 0] + 0.5).clamp(0, 1)
    want = pal.apply(colours.numpy())  # the map on the colours as an image of 50 pixels
    np.testing.assert_allclose((SH_C0 * out[:, 0] + 0.5).numpy(), want, atol=1e-9)
    return pal, sh, out, style


def test_recolor_sh_maps_each_gaussians_base_colour_like_the_images():
    pal, sh, out, _ = _recolored_like_pixels("tone", _random_images(7), 6)
    band_y = sh[:, 1:].numpy() @ LUMA  # view-dependent bands: their luminance, scaled as luminance is, on grey
    np.testing.assert_allclose(out[:, 1:].numpy(), np.repeat((band_y * pal.y_scale)[..., None], 3, -1), atol=1e-12)


def test_affine_palette_identity_keeps_sh():
    sh = torch.randn(10, 4, 3, dtype=torch.float64)
    torch.testing.assert_close(AffinePalette.identity().recolor_sh(sh), sh)


def test_unknown_palette_mode_is_refused():
    with pytest.raises(ValueError, match="arf, arf_rank, sliced or tone"):
        palette_transfer([torch.zeros(2, 2, 3)], torch.zeros(2, 2, 3), "lut")


@pytest.mark.skipif(not glob.glob(os.path.join(DATA, "scenes", "beer_colmap", "images", "*")),
                    reason="../shared/data/scenes/beer_colmap absent")
def test_beer_photos_in_the_starry_nights_tones_are_blue_with_yellow_lights():
    """Real photos (beer: a grey floor) and The Starry Night: the tone map's chroma noise (the evaluation's
    high-frequency Lab a,b energy) is below ARF's, and its lightest tones lean to yellow (B - Y < 0), its
    darkest to blue (B - Y > 0), as in the painting."""
    import cv2

    from tlvg_warp.eval.metrics import hf_energy, lab_ab

    files = sorted(glob.glob(os.path.join(DATA, "scenes", "beer_colmap", "images", "*")))[::10][:4]
    photos = [cv2.resize(cv2.imread(f)[..., ::-1], (180, 320), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
              for f in files]
    style = cv2.imread(os.path.join(DATA, "styles", "starry_night.jpg"))[..., ::-1].astype(np.float32) / 255
    style = cv2.resize(style, (320, 254), interpolation=cv2.INTER_AREA)
    arf = color_transfer(photos, style)[0]
    tone, pal = palette_transfer(photos, style, "tone")
    e_arf = np.mean([hf_energy(lab_ab(np.asarray(a))) for a in arf])
    e_tone = np.mean([hf_energy(lab_ab(np.asarray(t))) for t in tone])
    assert e_tone < 0.7 * e_arf
    assert float(pal.chroma[-1, 1]) < 0 < float(pal.chroma[0, 1])


@pytest.mark.skipif(not glob.glob(os.path.join(DATA, "scenes", "beer_colmap", "images", "*")),
                    reason="../shared/data/scenes/beer_colmap absent")
def test_beer_floor_under_the_smoothed_sliced_map_is_clean_and_nearer_the_painting_than_arfs():
    """Real photos (beer: a grey floor, JPEG blocks) and The Starry Night: the sliced map itself turns the floor's
    faint tints into colour blobs (the evaluation's high-frequency Lab a,b energy many times ARF's); smoothed at the
    default 0.05 it is cleaner than ARF's, and its colours lie nearer the painting's than ARF's do (numpy's sliced
    Wasserstein distance). Catches a smoothing that is skipped, too narrow, or that pulls the colours back to the
    photos'."""
    import cv2

    from tlvg_warp.eval.metrics import hf_energy, lab_ab

    files = sorted(glob.glob(os.path.join(DATA, "scenes", "beer_colmap", "images", "*")))[::10][:4]
    photos = [cv2.resize(cv2.imread(f)[..., ::-1], (180, 320), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
              for f in files]
    style = cv2.imread(os.path.join(DATA, "styles", "starry_night.jpg"))[..., ::-1].astype(np.float32) / 255
    style = cv2.resize(style, (320, 254), interpolation=cv2.INTER_AREA)
    arf = palette_transfer(photos, style, "arf", floor=0.004)[0]
    raw = palette_transfer(photos, style, "sliced")[0]
    smooth = palette_transfer(photos, style, "sliced", smooth=0.05)[0]
    energy = {k: np.mean([hf_energy(lab_ab(np.asarray(a))) for a in v]) for k, v in
              (("arf", arf), ("raw", raw), ("smooth", smooth))}
    assert energy["raw"] > 4 * energy["arf"] and energy["smooth"] < energy["arf"]
    flat = lambda xs: np.concatenate([np.asarray(x).reshape(-1, 3) for x in xs])
    paint = style.reshape(-1, 3)
    assert _sliced_w1(flat(smooth), paint) < 0.85 * _sliced_w1(flat(arf), paint) < _sliced_w1(flat(photos), paint)


def test_tone_statistics_come_from_the_covered_pixels_only():
    """An object on a white background: with the coverage marking it, the map does not depend on how much
    background the views show; pooled over every pixel (no coverage) the white pushes the object down the ranks."""
    rng = np.random.default_rng(8)
    obj = rng.random((16, 16, 3)) * 0.8 + 0.1
    style = rng.random((30, 40, 3))
    maps = []
    for pad in (4, 24):  # a little and a lot of white around the same object
        img = np.ones((16 + 2 * pad, 16 + 2 * pad, 3))
        img[pad:pad + 16, pad:pad + 16] = obj
        cov = np.zeros(img.shape[:2] + (1,))
        cov[pad:pad + 16, pad:pad + 16] = 1.0
        masked = tone_palette([torch.from_numpy(img)], torch.from_numpy(style), coverage=[torch.from_numpy(cov)])
        pooled = tone_palette([torch.from_numpy(img)], torch.from_numpy(style))
        maps.append((masked, pooled))
    (m_small, p_small), (m_big, p_big) = maps
    torch.testing.assert_close(m_small.knots, m_big.knots)
    assert m_small.y_mean == pytest.approx(m_big.y_mean) and m_small.y_scale == pytest.approx(m_big.y_scale)
    q = len(p_big.knots) // 4  # the lower quartile: the object in the small view, the white in the big one
    assert p_big.knots[q] > p_small.knots[q] + 0.05
    y_obj = obj.reshape(-1, 3) @ LUMA  # the masked knots are the object's own luminance quantiles
    np.testing.assert_allclose(m_small.knots.numpy(), np.quantile(y_obj, (np.arange(32) + 0.5) / 32), atol=1e-6)


def _arf_map(photos, style, floor):
    """ARF's map with a variance floor, in numpy float64: M = S^1/2 (C + floor I)^-1/2, t = mu_s - M mu_c (pooled
    moments, symmetric square roots, no clamp)."""
    def sym_pow(c, p):
        e, u = np.linalg.eigh(c)
        return u @ np.diag(np.clip(e, 1e-8, 1e8) ** p) @ u.T
    x = np.concatenate([p.reshape(-1, 3) for p in photos])
    s = style.reshape(-1, 3).astype(np.float64)
    m = sym_pow(np.cov(s.T, bias=True), 0.5) @ sym_pow(np.cov(x.T, bias=True) + floor * np.eye(3), -0.5)
    return m, s.mean(0) - m @ x.mean(0)


def _arf_reference(photos, style, floor):
    """ARF's transfer: the map of :func:`_arf_map` on the photos, clamped to [0,1]; and M."""
    m, t = _arf_map(photos, style, floor)
    return [np.clip(p @ m.T + t, 0, 1) for p in photos], m


@pytest.mark.parametrize("floor", [0.0, 0.004])
def test_arf_with_a_variance_floor_matches_a_float64_reference(floor):
    photos = _random_images(9)
    style = np.random.default_rng(10).random((30, 40, 3)) * np.array([0.4, 0.6, 1.0])
    got, pal = palette_transfer([torch.from_numpy(p) for p in photos], torch.from_numpy(style), "arf", floor=floor)
    want, m = _arf_reference(photos, style, floor)
    np.testing.assert_allclose(pal.m.numpy(), m, atol=1e-9)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g.numpy(), w, atol=1e-9)


def test_the_floor_tames_a_grey_photos_tints_and_spares_a_colourful_one():
    rng = np.random.default_rng(11)
    y = np.repeat(np.linspace(0.55, 0.75, 32)[None, :], 24, 0)[..., None]
    grey = np.clip(y + rng.normal(0, 0.004, (24, 32, 3)), 0, 1)  # +- 1/255 tints on a luminance ramp
    style = np.random.default_rng(12).random((40, 40, 3))

    def tint_noise(img):
        c = np.stack([img[..., 0] - img @ LUMA, img[..., 2] - img @ LUMA], -1)
        return float(np.abs(c - c.mean(0, keepdims=True)).mean())

    plain = color_transfer([grey], style)[0][0]
    floored = color_transfer([grey], style, 0.004)[0][0]
    assert tint_noise(floored) < tint_noise(plain) / 3
    colourful = rng.random((24, 32, 3))  # variance 1/12 per channel, far above the floor
    m0 = color_transfer([colourful], style)[1]
    m1 = color_transfer([colourful], style, 0.004)[1]
    assert float((m1 - m0).norm() / m0.norm()) < 0.05


# --- the palette-snap term ---------------------------------------------------------------------------------------
def _snap_reference(img, colours, weight):
    """The snap term by its definition, numpy float64: every pixel against every colour (no matmul trick), the
    nearest in RGB, the squared distance of (RGB - Y) between them, weighted mean."""
    x = img.reshape(-1, 3).astype(np.float64)
    c = colours.astype(np.float64)
    nearest = np.argmin(((x[:, None, :] - c[None]) ** 2).sum(-1), axis=1)
    d = x - c[nearest]
    chroma = d - (d @ LUMA)[:, None]
    w = weight.reshape(-1).astype(np.float64)
    return float((w * (chroma ** 2).sum(1)).sum() / w.sum())


def test_painting_colours_finds_a_flat_paintings_colours():
    """Three flat blocks of colour (and a fourth with a tenth of the pixels): k-means with k=4 returns exactly them;
    with k larger than the painting's distinct colours, no more than those."""
    want = np.array([[0.9, 0.8, 0.1], [0.1, 0.2, 0.7], [0.2, 0.5, 0.3], [0.95, 0.95, 0.9]], np.float32)
    p = np.zeros((40, 30, 3), np.float32)
    p[:, :9], p[:, 9:18], p[:, 18:27], p[:, 27:] = want
    got = painting_colours(p, 4).numpy()
    order = [int(np.argmin(((got - w) ** 2).sum(1))) for w in want]
    assert sorted(order) == [0, 1, 2, 3]
    np.testing.assert_allclose(got[order], want, atol=1e-5)
    assert painting_colours(p, 16).shape == (4, 3)


def test_palette_snap_loss_matches_a_float64_reference_with_its_gradient():
    rng = np.random.default_rng(3)
    img = rng.random((9, 11, 3))
    colours = rng.random((6, 3)).astype(np.float32)
    weight = rng.random((9, 11, 1))
    x = torch.tensor(img, dtype=torch.float64, requires_grad=True)
    loss = palette_snap_loss(x, torch.from_numpy(colours), torch.from_numpy(weight))
    assert float(loss.detach()) == pytest.approx(_snap_reference(img, colours, weight), rel=1e-12)
    loss.backward()
    # central finite differences of the reference (steps small enough that no pixel changes its nearest colour)
    eps, fd = 1e-6, np.zeros_like(img)
    for idx in [(0, 0, 0), (4, 5, 1), (8, 10, 2), (3, 7, 0), (6, 2, 2)]:
        up, dn = img.copy(), img.copy()
        up[idx] += eps
        dn[idx] -= eps
        fd[idx] = (_snap_reference(up, colours, weight) - _snap_reference(dn, colours, weight)) / (2 * eps)
        assert float(x.grad[idx]) == pytest.approx(fd[idx], rel=1e-5, abs=1e-10)
    # blind to grey: the gradient's R + G + B is 0 at every pixel, so a step leaves each pixel's mean level alone
    assert torch.allclose(x.grad.sum(-1), torch.zeros(9, 11, dtype=torch.float64), atol=1e-15)
    assert float(x.grad.abs().max()) > 1e-4  # and there is a pull at all


def test_palette_snap_pulls_a_teal_wash_to_the_paintings_blue_and_yellow():
    """The reason it exists: a render in one mean tint (teal, between a painting's blue and yellow) whose light
    strokes should turn yellow and dark ones blue. Gradient descent on the term alone moves each pixel's colour to
    the painting colour nearest it; the light pixels end closer to yellow than to blue, the dark ones the reverse."""
    blue, yellow = np.array([0.15, 0.25, 0.65]), np.array([0.9, 0.8, 0.25])
    y = np.linspace(0.2, 0.8, 64)  # a ramp of tones in one tint
    teal = np.array([0.35, 0.55, 0.55]) - np.array([0.35, 0.55, 0.55]) @ LUMA
    img = (y[:, None] + teal[None])[None]  # [1,64,3]
    x = torch.tensor(img, dtype=torch.float64, requires_grad=True)
    colours = torch.tensor(np.stack([blue, yellow]), dtype=torch.float32)
    before = float(palette_snap_loss(x, colours).detach())
    opt = torch.optim.SGD([x], lr=20.0)
    for _ in range(200):
        opt.zero_grad()
        palette_snap_loss(x, colours).backward()
        opt.step()
    assert float(palette_snap_loss(x, colours).detach()) < 0.01 * before
    out = x.detach().numpy()[0]
    chroma = out - (out @ LUMA)[:, None]
    to = lambda c: np.linalg.norm(chroma - (c - c @ LUMA), axis=1)  # noqa: E731
    # each pixel went to the colour nearest it at the start (brute force): the light end yellow, the dark end blue
    went_yellow = ((img[0] - yellow) ** 2).sum(1) < ((img[0] - blue) ** 2).sum(1)
    assert went_yellow[-1] and not went_yellow[0] and 0 < went_yellow.sum() < len(y)
    assert (to(yellow)[went_yellow] < 1e-3).all() and (to(blue)[~went_yellow] < 1e-3).all()
    np.testing.assert_allclose(out.mean(1), img[0].mean(1), atol=1e-12)  # no grey moved: each pixel's level stays


# --- arf_rank: ARF's map, then luminance by rank (RankPalette) -----------------------------------------------------
def _capture_like(seed, n=3, h=20, w=24):
    """Bright, low-contrast photos with a dark tail (a can, its shadow): the luminance distribution whose dark end
    ARF's affine map puts under 0."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        p = 0.7 + 0.05 * rng.random((h, w, 3))
        dark = rng.random((h, w)) < 0.1  # ~10% dark pixels, each of its own colour
        p[dark] = rng.random((int(dark.sum()), 3)) * 0.15
        out.append(p)
    return out


def test_arf_rank_gives_the_photos_the_paintings_luminance_by_rank_and_keeps_arfs_hue():
    photos = _capture_like(10)
    style = np.random.default_rng(11).random((40, 50, 3)) ** 1.5 * np.array([0.7, 0.8, 1.0])
    got, pal = palette_transfer([torch.from_numpy(p) for p in photos], torch.from_numpy(style), "arf_rank", floor=0.004)
    m, t = _arf_map(photos, style, 0.004)
    arf = [p.reshape(-1, 3) @ m.T + t for p in photos]  # unclamped
    assert min(a.min() for a in arf) < -0.05  # the case the map exists for: ARF puts the dark tail under 0
    out = np.concatenate([g.numpy().reshape(-1, 3) for g in got])
    a = np.concatenate(arf)
    y_out, y_arf, y_s = out @ LUMA, a @ LUMA, style.reshape(-1, 3) @ LUMA
    assert out.min() >= 0.0 and out.max() <= 1.0
    q = np.linspace(0.05, 0.95, 19)  # the painting's luminance distribution, rank for rank (256 bins: 1/256 apart)
    np.testing.assert_allclose(np.quantile(y_out, q), np.quantile(y_s, q), atol=0.01)
    order = np.argsort(y_arf, kind="stable")  # a monotone map of ARF's luminance
    assert np.all(np.diff(y_out[order]) >= -1e-9)
    # the chroma is ARF's, scaled by a factor in [0, 1] (hue kept; a per-channel clamp would turn it)
    c_out, c_arf = out - y_out[:, None], a - y_arf[:, None]
    k = (c_out * c_arf).sum(1) / np.maximum((c_arf * c_arf).sum(1), 1e-24)
    np.testing.assert_allclose(c_out, k[:, None] * c_arf, atol=1e-9)
    assert k.min() >= -1e-9 and k.max() <= 1 + 1e-9 and np.mean(k > 1 - 1e-9) > 0.5  # most colours untouched
    # the plain ARF map on the same photos: its clamp cuts the luminance spread
    clamped = np.clip(a, 0, 1) @ LUMA
    assert clamped.std() < 0.9 * y_s.std() and abs(y_out.std() - y_s.std()) < 0.02 * y_s.std()


def test_arf_rank_recolors_the_gaussians_base_colour_like_a_pixel_and_the_bands_by_arfs_matrix():
    photos = _capture_like(13)
    _, sh, out, style = _recolored_like_pixels("arf_rank", photos, 12)
    m, _ = _arf_map(photos, style, 0.0)
    np.testing.assert_allclose(out[:, 1:].numpy(), sh[:, 1:].numpy() @ m.T, atol=1e-9)


@pytest.mark.parametrize("mode", ["arf_rank", "sliced"])
def test_rank_and_sliced_maps_take_their_statistics_over_the_covered_pixels(mode):
    """With ``where='covered'`` the map's statistics (arf_rank: ARF's moments and the luminance ranks; sliced: every
    rotation's quantiles) come from the pixels the scene covers: a white background outside them changes nothing
    (for sliced this also needs the same rotations on every call: they come from a fixed seed)."""
    photos = _capture_like(14)
    style = np.random.default_rng(15).random((30, 40, 3))
    cover = [np.zeros(p.shape[:2] + (1,)) for p in photos]
    for c in cover:
        c[:, :12] = 1.0
    framed = [p.copy() for p in photos]
    for p in framed:
        p[:, 12:] = 1.0  # white where nothing is covered
    pt = lambda xs: [torch.from_numpy(x) for x in xs]
    a, _ = palette_transfer(pt(photos), torch.from_numpy(style), mode, coverage=pt(cover), where="covered")
    b, _ = palette_transfer(pt(framed), torch.from_numpy(style), mode, coverage=pt(cover), where="covered")
    for x, y in zip(a, b):
        np.testing.assert_allclose(x[:, :12].numpy(), y[:, :12].numpy(), atol=1e-9)
    c, _ = palette_transfer(pt(framed), torch.from_numpy(style), mode)  # all pixels: the white moves the map
    assert np.abs(c[0][:, :12].numpy() - b[0][:, :12].numpy()).max() > 0.02


def _object_views(object_rgb, share, n=3, size=40, seed=0):
    """``n`` views [size,size,3] of a square object of colour ``object_rgb`` (with a little noise) covering about
    ``share`` of each view on a white background, and their coverage [size,size,1]."""
    gen = np.random.default_rng(seed)
    side = int(round(size * share ** 0.5))
    photos, cover = [], []
    for _ in range(n):
        img = np.ones((size, size, 3))
        a = np.zeros((size, size, 1))
        img[:side, :side] = np.clip(np.array(object_rgb) + gen.normal(0, 0.02, (side, side, 3)), 0, 1)
        a[:side, :side] = 1.0
        photos.append(torch.from_numpy(img))
        cover.append(torch.from_numpy(a))
    return photos, cover


def test_dark_object_note_names_the_object_and_painting_luminance_and_only_where_it_applies():
    from tlvg_warp.losses.palette import dark_object_note
    painting = torch.from_numpy(np.random.default_rng(1).uniform(0.35, 0.85, (30, 50, 3)))
    photos, cover = _object_views((0.15, 0.12, 0.1), share=0.25)
    note = dark_object_note(photos, cover, painting, "arf", "covered")
    y_obj = np.concatenate([p.numpy().reshape(-1, 3) @ LUMA for p in photos])[
        np.concatenate([c.numpy().reshape(-1) for c in cover]) > 0.5].mean()
    y_paint = (painting.numpy().reshape(-1, 3) @ LUMA).mean()
    assert note is not None and "palette_where=all" in note and "\n" not in note
    assert f"{y_obj:.2f} against {y_paint:.2f}" in note  # the numbers, from numpy's BT.601
    assert dark_object_note(photos, cover, painting, "arf", "all") is None  # already ARF's all-pixel statistics
    assert dark_object_note(photos, cover, painting, "arf_rank", "covered") == note  # the same statistics
    assert dark_object_note(photos, cover, painting, "tone", "covered") is None  # palette_where cannot help
    dark = [torch.full_like(p, 0.15) for p in photos]  # a dark capture: covered everywhere, where covered = all
    full = [torch.ones_like(c) for c in cover]
    assert dark_object_note(dark, full, painting, "arf", "covered") is None
    light, lcover = _object_views((0.55, 0.5, 0.45), share=0.25)  # within the gap of the painting's mean
    assert dark_object_note(light, lcover, painting, "arf", "covered") is None


def test_covered_luminance_sums_and_the_tone_drift_note():
    """The covered pixels' luminance sums against numpy's BT.601 in float64 (alpha above 0.5 counts, [H,W] or
    [H,W,1]); the note names the direction and both tones, and is silent within TONE_DRIFT of the target."""
    from tlvg_warp.losses.palette import TONE_DRIFT, covered_luminance_sums, covered_mean_luminance, tone_drift_note

    g = torch.Generator().manual_seed(3)
    img = torch.rand(20, 30, 3, generator=g)
    cov = torch.rand(20, 30, generator=g)
    cov[0, 0], cov[0, 1] = 0.5, 0.5001  # the boundary: at 0.5 not covered, above it covered
    x, keep = img.double().numpy(), cov.numpy() > 0.5
    y = x[..., 0] * 0.299 + x[..., 1] * 0.587 + x[..., 2] * 0.114
    for c in (cov, cov[..., None]):
        total, n = covered_luminance_sums(img, c)
        assert n == keep.sum() and total == pytest.approx(y[keep].sum(), rel=1e-9)
    # over views: the pooled mean of every covered pixel (not the mean of the views' means); None when none is covered
    half = cov.clone()
    half[:, 15:] = 0.0
    pooled = np.concatenate([y[keep], y[half.numpy() > 0.5]]).mean()
    assert covered_mean_luminance([img, img], [cov, half]) == pytest.approx(pooled, rel=1e-9)
    assert covered_mean_luminance([img], [torch.zeros_like(cov)]) is None
    assert tone_drift_note(0.30, 0.30 + TONE_DRIFT * 0.9) is None and tone_drift_note(0.5, 0.5) is None
    lighter = tone_drift_note(0.479, 0.222)
    assert "lighter" in lighter and "0.48 against 0.22" in lighter and "loss.w_tone_hold" in lighter
    assert "darker" in tone_drift_note(0.20, 0.40)
    # with the hold on, the note names ten times the run's weight, not the weight the run already had
    held = tone_drift_note(0.479, 0.222, 100.0)
    assert "loss.w_tone_hold=1000" in held and "this run: 100" in held and "w_tone_hold=100 " not in held


# --- the sliced map (palette_map: sliced) -------------------------------------------------------------------------
def _sliced_w1(a: np.ndarray, b: np.ndarray, n_dirs: int = 16, seed: int = 3) -> float:
    """Mean over random directions of the 1-D Wasserstein-1 distance between two colour sets [N,3] and [M,3] (numpy,
    at 101 quantiles): an oracle written apart from the map."""
    dirs = np.random.default_rng(seed).normal(size=(n_dirs, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    q = np.linspace(0, 1, 101)
    return float(np.mean([np.abs(np.quantile(a @ d, q) - np.quantile(b @ d, q)).mean() for d in dirs]))


def test_sliced_map_of_a_painting_onto_itself_is_the_identity():
    """Photos with the painting's own colours: every step's quantiles agree, so each axis map is the identity (a map
    that rotated back the wrong way, or sent an axis's values to another axis, would not be)."""
    from tlvg_warp.losses.palette import sliced_palette

    s = torch.from_numpy(np.random.default_rng(21).random((40, 30, 3)) ** 2)
    pal = sliced_palette([s], s)
    np.testing.assert_allclose(pal.apply(s).numpy(), s.numpy(), atol=1e-6)


def test_sliced_map_gives_the_photos_the_paintings_colour_distribution():
    """Dull photos (a narrow band of colour) under a colourful painting: along random directions the recoloured
    photos' colours are distributed as the painting's (numpy's sliced Wasserstein distance a twentieth of what it was
    before), where ARF's affine map, which matches two moments only, leaves them several times farther."""
    rng = np.random.default_rng(22)
    photos = [0.35 + 0.15 * rng.random((30, 40, 3)) ** 3 for _ in range(3)]
    hues = np.array([[0.9, 0.2, 0.1], [0.1, 0.3, 0.8], [0.95, 0.85, 0.2], [0.2, 0.6, 0.3]])  # four saturated patches
    style = np.clip(hues[rng.integers(0, 4, (50, 60))] + rng.normal(0, 0.03, (50, 60, 3)), 0, 1)
    pt = [torch.from_numpy(p) for p in photos]
    sliced, _ = palette_transfer(pt, torch.from_numpy(style), "sliced")
    arf, _ = palette_transfer(pt, torch.from_numpy(style), "arf")
    flat = lambda xs: np.concatenate([np.asarray(x).reshape(-1, 3) for x in xs])
    paint = style.reshape(-1, 3)
    before, after, affine = (_sliced_w1(flat(x), paint) for x in (photos, sliced, arf))
    assert after < before / 20 and affine > 3 * after


def test_sliced_map_recolors_the_gaussians_base_colour_like_a_pixel_and_keeps_the_bands():
    _, sh, out, _ = _recolored_like_pixels("sliced", _capture_like(23), 24)
    np.testing.assert_allclose(out[:, 1:].numpy(), sh[:, 1:].numpy(), atol=1e-12)


# --- the sliced map smoothed over the photos' colours (palette_smooth) --------------------------------------------
def test_smoothed_displacement_matches_a_float64_loop_reference():
    """Each grid point's displacement is the Gaussian-kernel average of the photo colours' displacements (numpy,
    one grid point at a time, the grid indexed r,g,b); a very wide kernel gives their plain mean everywhere. Catches
    a kernel of the wrong width, a grid in another axis order, a missing normalization."""
    from tlvg_warp.losses.palette import smoothed_displacement

    rng = np.random.default_rng(31)
    x, d = rng.random((60, 3)), rng.normal(0, 0.2, (60, 3))
    out = smoothed_displacement(torch.from_numpy(x), torch.from_numpy(d), 0.15, grid=4).numpy()
    axis = np.linspace(0, 1, 4)
    for i, j, k in [(0, 0, 0), (3, 1, 2), (1, 2, 3), (2, 3, 0)]:
        w = np.exp(-((x - [axis[i], axis[j], axis[k]]) ** 2).sum(1) / (2 * 0.15 ** 2))
        np.testing.assert_allclose(out[i, j, k], (w[:, None] * d).sum(0) / w.sum(), rtol=1e-10, atol=1e-12)
    wide = smoothed_displacement(torch.from_numpy(x), torch.from_numpy(d), 1e4, grid=3).numpy()
    np.testing.assert_allclose(wide.reshape(-1, 3), np.broadcast_to(d.mean(0), (27, 3)), atol=1e-9)


def _mean_shift_reference(w, y, focus):
    """numpy, float64: mean shift over the points ``y`` [K,3] with weights ``w`` [K] (summing to 1), from their
    weighted mean, each step's weights ``w`` times a Gaussian of width ``focus`` around the estimate, FOCUS_STEPS
    steps."""
    from tlvg_warp.losses.palette import FOCUS_STEPS

    m = (w[:, None] * y).sum(0)
    for _ in range(FOCUS_STEPS):
        k = w * np.exp(-((y - m) ** 2).sum(1) / (2 * focus ** 2))
        m = (k[:, None] * y).sum(0) / k.sum()
    return m


def test_focused_displacement_matches_a_float64_mean_shift_loop():
    """palette_focus: at each grid point the destinations x + d, weighted by the point's kernel over x, are climbed
    by mean shift from their weighted mean (numpy, FOCUS_STEPS steps, one grid point at a time), and the displacement
    is the place reached minus the kernel-weighted mean of x; an enormous focus width gives the plain smoothing back.
    Catches the climb started elsewhere, the focus kernel on the sources instead of the destinations, a step count
    other than the constant's, the photo colour's own offset lost."""
    from tlvg_warp.losses.palette import smoothed_displacement

    rng = np.random.default_rng(41)
    x, d = rng.random((50, 3)), rng.normal(0, 0.25, (50, 3))
    out = smoothed_displacement(torch.from_numpy(x), torch.from_numpy(d), 0.2, grid=3, focus=0.12).numpy()
    axis, y = np.linspace(0, 1, 3), x + d
    for i, j, k in [(0, 0, 0), (2, 1, 0), (1, 2, 2)]:
        w = np.exp(-((x - [axis[i], axis[j], axis[k]]) ** 2).sum(1) / (2 * 0.2 ** 2))
        w /= w.sum()
        m = _mean_shift_reference(w, y, 0.12)
        np.testing.assert_allclose(out[i, j, k], m - (w[:, None] * x).sum(0), rtol=1e-9, atol=1e-11)
    plain = smoothed_displacement(torch.from_numpy(x), torch.from_numpy(d), 0.2, grid=3).numpy()
    wide = smoothed_displacement(torch.from_numpy(x), torch.from_numpy(d), 0.2, grid=3, focus=1e4).numpy()
    np.testing.assert_allclose(wide, plain, atol=1e-9)


def test_focus_climbs_over_each_grid_points_largest_weights_only():
    """More photo colours than FOCUS_NEIGHBOURS: each grid point's climb uses its FOCUS_NEIGHBOURS colours of largest
    kernel weight, renormalized (numpy: argsort of the weights), and its offset the full kernel mean of x. Catches
    the smallest weights kept instead, weights not renormalized, the offset taken over the kept colours only."""
    from tlvg_warp.losses.palette import FOCUS_NEIGHBOURS, smoothed_displacement

    rng = np.random.default_rng(43)
    n = FOCUS_NEIGHBOURS + 150
    x, d = rng.random((n, 3)), rng.normal(0, 0.25, (n, 3))
    out = smoothed_displacement(torch.from_numpy(x), torch.from_numpy(d), 0.3, grid=2, focus=0.15).numpy()
    y = x + d
    for i, j, k in [(0, 0, 0), (1, 0, 1)]:
        w = np.exp(-((x - [i, j, k]) ** 2).sum(1) / (2 * 0.3 ** 2))
        w /= w.sum()
        keep = np.argsort(-w)[:FOCUS_NEIGHBOURS]
        m = _mean_shift_reference(w[keep] / w[keep].sum(), y[keep], 0.15)
        np.testing.assert_allclose(out[i, j, k], m - (w[:, None] * x).sum(0), rtol=1e-9, atol=1e-11)


def test_focus_sends_a_one_colour_floor_to_one_of_the_paintings_colours_not_their_mix():
    """A grey floor whose colours the sliced map sends 60% to a blue and 40% to a yellow (the destinations given
    directly): smoothed, the floor lands on their mix, a grey neither colour is (closed form: 0.6 blue + 0.4 yellow);
    with a focus of 0.1 it lands on the blue, the denser of the two (within 0.01)."""
    from tlvg_warp.losses.palette import _trilinear, smoothed_displacement

    rng = np.random.default_rng(42)
    x = 0.5 + rng.normal(0, 0.01, (1000, 3))
    blue, yellow = np.array([0.15, 0.25, 0.75]), np.array([0.95, 0.85, 0.2])
    dest = np.where((np.arange(1000) < 600)[:, None], blue, yellow) + rng.normal(0, 0.01, (1000, 3))
    at = torch.tensor([[0.5, 0.5, 0.5]], dtype=torch.float64)
    for focus, want in ((0.0, 0.6 * blue + 0.4 * yellow), (0.1, blue)):
        lut = smoothed_displacement(torch.from_numpy(x), torch.from_numpy(dest - x), 0.05, focus=focus)
        np.testing.assert_allclose((at + _trilinear(lut, at)).numpy()[0], want, atol=0.01)


def test_trilinear_lookup_reads_an_affine_table_exactly():
    """A table of an affine function of RGB is reproduced exactly between its grid points by trilinear
    interpolation (closed form); colours outside [0,1] read the nearest face."""
    from tlvg_warp.losses.palette import _trilinear

    a, b = np.array([[0.3, -0.2, 0.5], [0.1, 0.7, -0.4], [-0.6, 0.2, 0.9]]), np.array([0.05, -0.1, 0.2])
    axis = np.linspace(0, 1, 6)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1)  # [6,6,6,3]
    lut = torch.from_numpy(grid @ a.T + b)
    x = np.random.default_rng(32).random((500, 3))
    np.testing.assert_allclose(_trilinear(lut, torch.from_numpy(x)).numpy(), x @ a.T + b, atol=1e-12)
    outside = np.array([[1.3, -0.2, 0.5]])
    np.testing.assert_allclose(_trilinear(lut, torch.from_numpy(outside)).numpy(),
                               np.clip(outside, 0, 1) @ a.T + b, atol=1e-12)


def _grey_and_two_hues(seed):
    rng = np.random.default_rng(seed)
    grey = [0.55 + rng.normal(0, 0.012, (30, 40, 3)) for _ in range(2)]  # a bare floor: faint tints only
    hues = np.array([[0.95, 0.85, 0.2], [0.15, 0.25, 0.75], [0.85, 0.2, 0.15], [0.2, 0.55, 0.3]])
    style = np.clip(hues[rng.integers(0, 4, (50, 60))] + rng.normal(0, 0.03, (50, 60, 3)), 0, 1)
    return [torch.from_numpy(g) for g in grey], torch.from_numpy(style)


def test_smoothing_keeps_a_grey_photos_tints_as_faint_as_they_were():
    """A grey photo under a colourful painting: the sliced map itself spreads its faint tints over the painting's
    hues (the soft colour blobs on beer's floor); smoothed over colours within 0.05 the tints move together, so the
    displacement varies little over the photo and the colours' spread stays under twice the photo's own (the map
    itself: over five times)."""
    grey, style = _grey_and_two_hues(33)
    x = torch.cat([g.reshape(-1, 3) for g in grey]).numpy()
    raw, _ = palette_transfer(grey, style, "sliced")
    smooth, _ = palette_transfer(grey, style, "sliced", smooth=0.05)
    flat = lambda xs: np.concatenate([np.asarray(r).reshape(-1, 3) for r in xs])
    spread = lambda y: float(np.std(y - y.mean(0), axis=0).mean())
    assert spread(flat(raw)) > 5 * spread(x)  # the failure the option is for
    assert spread(flat(smooth)) < 2 * spread(x)
    assert np.abs(flat(smooth).mean(0) - x.mean(0)).max() > 0.02  # it still moves the photo's colour


def test_smoothing_keeps_far_apart_hues_on_their_own_hues():
    """Two photo colours far apart (red and blue objects) under a four-hue painting: with smoothing each keeps the
    colour the sliced map gives it (means within 0.05), so the two still land on different hues of the painting."""
    rng = np.random.default_rng(34)
    red = 0.02 * rng.normal(size=(30, 40, 3)) + [0.8, 0.25, 0.2]
    blue = 0.02 * rng.normal(size=(30, 40, 3)) + [0.2, 0.3, 0.8]
    photos = [torch.from_numpy(np.clip(p, 0, 1)) for p in (red, blue)]
    _, style = _grey_and_two_hues(35)
    raw, _ = palette_transfer(photos, style, "sliced")
    smooth, _ = palette_transfer(photos, style, "sliced", smooth=0.05)
    for r, s in zip(raw, smooth):
        np.testing.assert_allclose(s.reshape(-1, 3).mean(0).numpy(), r.reshape(-1, 3).mean(0).numpy(), atol=0.05)
    assert float((smooth[0].reshape(-1, 3).mean(0) - smooth[1].reshape(-1, 3).mean(0)).abs().max()) > 0.3


def test_the_shipped_config_smooths_the_sliced_map_and_another_map_ignores_the_width():
    """configs/tlvg.yaml's map is the smoothed sliced one; switching the map back to ARF's over that config is valid
    and gives ARF's map exactly (the width belongs to the sliced map alone)."""
    from pathlib import Path

    from tlvg_warp.stylize.config import load_config

    cfg_path = Path(__file__).resolve().parents[1] / "configs" / "tlvg.yaml"
    cfg = load_config(cfg_path)
    assert (cfg.palette_map, cfg.palette_smooth) == ("sliced", 0.05)
    assert load_config(cfg_path, ["palette_map=arf"]).validate().palette_map == "arf"
    photos, style = _grey_and_two_hues(36)
    plain, _ = palette_transfer(photos, style, "arf", floor=0.004)
    widened, _ = palette_transfer(photos, style, "arf", floor=0.004, smooth=0.05)
    for a, b in zip(plain, widened):
        assert torch.equal(a, b)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the palette on a CUDA device")
@pytest.mark.parametrize("focus", [0.0, 0.1])
def test_the_smoothed_sliced_map_on_cuda_matches_the_cpu(focus):
    """Photos on a GPU: the map is fitted there (quantiles, smoothing table, its focus) and recolours as the CPU's
    does."""
    photos, style = _grey_and_two_hues(37)
    photos = photos + [torch.from_numpy(np.random.default_rng(38).random((30, 40, 3)))]
    cpu, _ = palette_transfer(photos, style, "sliced", smooth=0.05, focus=focus)
    gpu, pal = palette_transfer([p.cuda() for p in photos], style.cuda(), "sliced", smooth=0.05, focus=focus)
    assert pal.lut.is_cuda
    for a, b in zip(cpu, gpu):
        np.testing.assert_allclose(b.cpu().numpy(), a.numpy(), atol=1e-6)


@pytest.mark.parametrize("with_coverage", [False, True])
def test_pooled_colours_are_every_kth_of_the_concatenated_pixels(with_coverage):
    """The pooled colours are exactly every k-th colour of all the images' (covered) pixels in order, written the
    direct way (concatenate in float64, then stride), for images of uneven sizes whose pixel counts do not divide
    the stride; at most ``limit`` remain."""
    from tlvg_warp.losses.palette import COVERED, _pooled_colours

    rng = np.random.default_rng(39)
    imgs = [torch.from_numpy(rng.random((h, w, 3)).astype(np.float32)) for h, w in ((7, 9), (11, 5), (3, 13))]
    cov = ([torch.from_numpy(rng.random((*im.shape[:2], 1)).astype(np.float32)) for im in imgs] if with_coverage
           else None)
    for limit in (1000, 50, 17):
        got = _pooled_colours(imgs, cov, limit)
        flat = [im.reshape(-1, 3).double() for im in imgs]
        if with_coverage:
            flat = [f[c.reshape(-1) > COVERED] for f, c in zip(flat, cov)]
        ref = torch.cat(flat)
        ref = ref[::max(1, -(-ref.shape[0] // limit))]
        assert got.dtype == torch.float64 and got.shape[0] <= limit
        assert torch.equal(got, ref)
