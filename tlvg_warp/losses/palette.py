"""The painting's palette on the photos and on the Gaussians: the colour maps the pre-process can start from.

- ``arf``: ARF's mean/covariance transfer (:func:`color.color_transfer`), one affine map ``x' = M x + t``.
- ``arf_rank`` (ours): ARF's map, then its luminance moved to the painting's at the same rank (:class:`RankPalette`),
  so the clamp to [0,1] no longer cuts the dark tail a capture's luminance distribution maps under 0.
- ``sliced`` (ours, after Pitié et al.'s iterative distribution transfer): the photos' colours moved onto the
  painting's whole colour distribution, one random rotation of RGB at a time, each axis matched quantile for
  quantile. Why: one affine map cannot give a scene the many saturated hues of a Fauvist painting that its colours
  do not span (Woman with a Hat came out pastel, docs/study.md); matching the distribution can. With ``smooth`` (the
  default config: 0.05) the map's displacement is averaged over nearby photo colours, so a grey floor's faint tints
  move together instead of into far-apart hues (:func:`smoothed_displacement`).
- ``tone`` (ours): luminance moved to the painting's mean and spread, chroma read from the painting at the same
  luminance rank. Why: a photo with little colour (a grey floor, a white wall) has a near-singular chroma
  covariance, and whitening it blows up its faint tints into pastel green and violet washes that the painting
  never had (beer x The Starry Night). The tone map instead gives each tone the painting's own colour for that tone
  (The Starry Night: dark blue shadows, blue mid-tones, yellow lights), and chroma is a smooth function of
  luminance, so no photo noise is amplified into colour.

Every map acts on a whole dataset at once (one map for every view) and on Gaussians' SH colours
(:meth:`recolor_sh`), so the pre-process starts from the palette it fits to.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..types import SH_C0
from .color import LUMA, _as_torch, _blur, _luma, apply_color_transform, chroma, color_map, color_transfer, recolor_sh

TONE_BINS = 32  # luminance bins of the painting's chroma table (equal pixel counts)
TONE_MAX_BOOST = 2.0  # a bin's mean chroma is scaled back up to its pixels' mean saturation, by at most this
TONE_MAX_PIXELS = 4_000_000  # the photos' luminance quantiles are read on at most this many pixels (a stride)
TONE_CHROMA_SIGMA = 2.0  # px: an image's chroma is looked up at its luminance blurred by this much, so fine
# luminance detail (tile joints, texture) stays luminance: looked up pixel by pixel, The Starry Night's blue-to-yellow
# table turned it into colour edges (beer: high-frequency Lab a,b energy 22.4 against ARF's 15.9; blurred 9.7)


@dataclass
class AffinePalette:
    """``x' = M x + t`` (ARF's transfer; the identity keeps a scene's colours)."""

    m: torch.Tensor  # [3,3] float64
    t: torch.Tensor  # [3] float64

    @classmethod
    def identity(cls) -> "AffinePalette":
        return cls(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))

    def recolor_sh(self, sh: torch.Tensor) -> torch.Tensor:
        """SH colours [N,K,3] under the map: exact for renders wherever nothing clamps (:func:`color.recolor_sh`)."""
        return recolor_sh(sh, self.m, self.t)


def _chroma(rgb: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(R - Y, B - Y) [...,2]: the two colour-difference axes of BT.601, linear and exactly invertible."""
    return torch.stack([rgb[..., 0] - y, rgb[..., 2] - y], -1)


def _from_luma_chroma(y: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """RGB [...,3] from Y [...] and (R - Y, B - Y) [...,2] (the inverse of :func:`_chroma`)."""
    r, b = y + c[..., 0], y + c[..., 1]
    g = (y - LUMA[0] * r - LUMA[2] * b) / LUMA[1]
    return torch.stack([r, g, b], -1)


def _luma64(img: torch.Tensor) -> torch.Tensor:
    return img.double() @ _luma(torch.float64, img.device)  # [...]: the weights built once per device


def _interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """np.interp on the last axis of ``fp`` [K,D] at ``x`` [...] -> [...,D] (constant beyond the ends)."""
    i = torch.searchsorted(xp, x.contiguous()).clamp(1, len(xp) - 1)
    x0, x1 = xp[i - 1], xp[i]
    w = ((x - x0) / (x1 - x0).clamp_min(1e-12)).clamp(0.0, 1.0)[..., None]
    return fp[i - 1] * (1 - w) + fp[i] * w


@dataclass
class TonePalette:
    """Luminance ``y' = (y - mu_c) * sd_s / sd_c + mu_s``; chroma = the painting's at the photos' rank of ``y``."""

    y_mean: tuple  # (mu_c, mu_s): the photos' and the painting's mean luminance
    y_scale: float  # sd_s / sd_c
    knots: torch.Tensor  # [K] float64: the photos' luminance at the bins' centre ranks (increasing)
    chroma: torch.Tensor  # [K,2] float64: the painting's (R - Y, B - Y) in the bin of the same rank

    def apply(self, img):
        """An image [H,W,3] (or colours [...,3]) in [0,1], numpy or torch, under the map, clamped to [0,1]; type and
        dtype kept. An image's chroma follows its luminance blurred by TONE_CHROMA_SIGMA px; colours' their own."""
        x = _as_torch(img)
        y = _luma64(x)
        y2 = (y - self.y_mean[0]) * self.y_scale + self.y_mean[1]
        is_image = x.dim() == 3 and min(x.shape[:2]) > 6 * TONE_CHROMA_SIGMA
        y_look = _blur(y[None, None], TONE_CHROMA_SIGMA)[0, 0] if is_image else y
        c = _interp(y_look, self.knots.to(y.device), self.chroma.to(y.device))
        out = _from_luma_chroma(y2, c).clamp(0.0, 1.0).to(x.dtype)
        return out.numpy() if isinstance(img, np.ndarray) else out

    def recolor_sh(self, sh: torch.Tensor) -> torch.Tensor:
        """SH colours [N,K,3]: each Gaussian's base colour (the DC term) through :meth:`apply`; the view-dependent
        bands keep only their luminance, scaled as luminance is (the map is not affine, so unlike ARF's this is
        the start of the pre-process fit, not an exact image of the renders)."""
        base = (SH_C0 * sh[:, 0].double() + 0.5).clamp(0.0, 1.0)  # [N,3]
        out = sh.double().clone()
        out[:, 0] = (self.apply(base).double() - 0.5) / SH_C0
        if sh.shape[1] > 1:
            out[:, 1:] = (_luma64(sh[:, 1:]) * self.y_scale)[..., None].expand(-1, -1, 3)
        return out.to(sh.dtype)


RANK_BINS = 256  # luminance quantiles of the rank map (arf_rank)


def _fit_gamut(c: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The chroma ``c`` [...,3] (RGB minus luminance: its luminance is 0) scaled down, where it must be, so that
    ``y + c`` lies in [0,1] on every channel for a luminance ``y`` [...] in [0,1]: the colour keeps its luminance and
    its hue and loses saturation, where a per-channel clamp would change all three (a dark tail ARF maps under 0,
    lifted to the painting's tones, would otherwise come out a saturated primary)."""
    yy = y[..., None]
    room = torch.where(c > 0, (1.0 - yy) / c.clamp_min(1e-12), torch.where(c < 0, yy / (-c).clamp_min(1e-12),
                                                                            torch.ones_like(c)))
    return c * room.amin(-1, keepdim=True).clamp(0.0, 1.0)


@dataclass
class RankPalette:
    """ARF's map ``x' = M x + t``, then its luminance moved to the painting's at the same rank (arf_rank, ours).

    Why: ARF matches the painting's colour covariance with an affine map, so the photos keep the shape of their own
    luminance distribution. A capture's bright floor with a dark tail (a can, shadows) maps that tail below 0, and the
    clamp to [0,1] takes a quarter of the painting's luminance spread back and lifts the mean: beer x The Shipwreck,
    9% of the pixels under 0 and a luminance spread of 0.126 where the painting has 0.181 (benchmarks/palette_clamp.py). Matching luminance by rank
    gives the recoloured photos the painting's luminance distribution itself, with nothing under 0, and keeps ARF's
    chroma (x' minus its luminance) pixel for pixel, scaled down only where the colour would leave [0,1]."""

    m: torch.Tensor  # [3,3] float64: ARF's map
    t: torch.Tensor  # [3] float64
    knots: torch.Tensor  # [K] float64: the ARF-mapped photos' luminance at the bins' centre ranks (increasing)
    values: torch.Tensor  # [K,1] float64: the painting's luminance at the same ranks

    def apply(self, img):
        """An image [H,W,3] (or colours [...,3]) in [0,1], numpy or torch, under the map, clamped to [0,1]; type and
        dtype kept."""
        x = _as_torch(img)
        xa = apply_color_transform(x.double(), self.m, self.t, clamp=False)  # [...,3] ARF's, unclamped
        y = _luma64(xa)
        y2 = _interp(y, self.knots.to(x.device), self.values.to(x.device))[..., 0].clamp(0.0, 1.0)
        out = (y2[..., None] + _fit_gamut(xa - y[..., None], y2)).clamp(0.0, 1.0).to(x.dtype)  # (the clamp: rounding)
        return out.numpy() if isinstance(img, np.ndarray) else out

    def recolor_sh(self, sh: torch.Tensor) -> torch.Tensor:
        """SH colours [N,K,3]: the view-dependent bands under ARF's M (as :class:`AffinePalette`), each Gaussian's base
        colour (the DC term) through :meth:`apply` (the map is not affine: the start of the pre-process fit, not an
        exact image of the renders)."""
        out = recolor_sh(sh, self.m, self.t).double()
        base = (SH_C0 * sh[:, 0].double() + 0.5).clamp(0.0, 1.0)  # [N,3]
        out[:, 0] = (self.apply(base).double() - 0.5) / SH_C0
        return out.to(sh.dtype)


def rank_palette(images, style, floor: float = 0.0, coverage=None, bins: int = RANK_BINS) -> RankPalette:
    """The arf_rank map from the photos (list of [H,W,3] in [0,1]) to the painting ``style`` [h,w,3]: ARF's map over
    the pixels ``coverage`` marks (None: all; as ``palette_transfer``'s ``covered``), then the quantiles of its
    luminance there against the painting's."""
    m, t = color_map(list(images), style, floor, coverage)
    mapped = [apply_color_transform(_as_torch(im).detach().double().cpu(), m, t, clamp=False) for im in images]
    y_c = _pooled_luma(mapped, coverage)
    y_s = _luma64(_as_torch(style).detach().cpu().double().reshape(-1, 3))
    q = (torch.arange(bins, dtype=torch.float64) + 0.5) / bins
    knots = torch.quantile(y_c, q) + torch.arange(bins, dtype=torch.float64) * 1e-9  # strictly increasing
    return RankPalette(m, t, knots, torch.quantile(y_s, q)[:, None])


SLICED_STEPS = 10  # rotations of the sliced map: each matches three axes, so 10 match 30 directions
SLICED_QUANTILES = 64  # knots of each axis's monotone map (piecewise linear between them)
SLICED_MAX_PIXELS = 400_000  # the photos' and the painting's colours are read on at most this many pixels (a stride)


def _rotation(gen: torch.Generator) -> torch.Tensor:
    """A uniformly random 3x3 rotation, float64: QR of a Gaussian matrix with the signs fixed."""
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    return q * torch.sign(torch.diagonal(r))[None, :]


@dataclass
class SlicedPalette:
    """The photos' colour distribution moved onto the painting's: ``steps`` times, the colours are rotated, each of
    the three rotated axes goes through the monotone map that sends the photos' quantiles there to the painting's,
    and the colours are rotated back (sliced optimal transport in three dimensions: a colour keeps its rank along
    every axis, so neighbouring colours stay neighbours). With ``lut`` the map's displacement is read from a table
    smoothed over the photos' colours instead (:func:`smoothed_displacement`)."""

    rotations: torch.Tensor  # [K,3,3] float64
    src: torch.Tensor  # [K,Q,3] float64: the photos' colours (after the steps before) along each rotated axis, at Q
    # quantiles from 0 to 1
    dst: torch.Tensor  # [K,Q,3] float64: the painting's at the same quantiles
    lut: torch.Tensor | None = None  # [G,G,G,3] float64: the smoothed displacement on a grid of RGB (index r,g,b)

    @staticmethod
    def _step(x: torch.Tensor, rot, src, dst) -> torch.Tensor:
        p = x @ rot  # [N,3]
        p = torch.stack([_interp(p[:, a], src[:, a].contiguous(), dst[:, a, None])[..., 0] for a in range(3)], -1)
        return p @ rot.T

    def transport(self, y: torch.Tensor) -> torch.Tensor:
        """Colours [N,3] float64 through the sliced map itself (unclamped, unsmoothed)."""
        for rot, src, dst in zip(self.rotations.to(y.device), self.src.to(y.device), self.dst.to(y.device)):
            y = self._step(y, rot, src, dst)
        return y

    def apply(self, img):
        """An image [H,W,3] (or colours [...,3]) in [0,1], numpy or torch, under the map, clamped to [0,1]; type and
        dtype kept."""
        x = _as_torch(img)
        y = x.detach().double().reshape(-1, 3)
        y = self.transport(y) if self.lut is None else y + _trilinear(self.lut.to(y.device), y)
        out = y.clamp(0.0, 1.0).reshape(x.shape).to(x.dtype)
        return out.numpy() if isinstance(img, np.ndarray) else out

    def recolor_sh(self, sh: torch.Tensor) -> torch.Tensor:
        """SH colours [N,K,3]: each Gaussian's base colour (the DC term) through :meth:`apply`; the view-dependent
        bands as they were (the map has no single linear part to carry them; a stylization keeps degree 0)."""
        out = sh.double().clone()
        base = (SH_C0 * sh[:, 0].double() + 0.5).clamp(0.0, 1.0)  # [N,3]
        out[:, 0] = (self.apply(base).double() - 0.5) / SH_C0
        return out.to(sh.dtype)


def _trilinear(lut: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """The table ``lut`` [G,G,G,C] (a grid over [0,1]^3, index r,g,b) read at colours ``x`` [N,3] by trilinear
    interpolation -> [N,C] (torch's ``grid_sample``); colours outside [0,1] read the nearest face."""
    vol = lut.permute(3, 0, 1, 2)[None]  # [1,C,G(r),G(g),G(b)]: grid_sample's depth, height, width
    where = (x.to(lut.dtype).flip(-1) * 2.0 - 1.0).reshape(1, -1, 1, 1, 3)  # (b, g, r) = (width, height, depth)
    out = torch.nn.functional.grid_sample(vol, where, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(lut.shape[-1], -1).T  # [N,C]


SLICED_LUT = 25  # grid points a side of the smoothed map's table (spacing 1/24 of the RGB cube)
FOCUS_STEPS = 10  # mean-shift steps of the smoothed map's focus (smoothed_displacement)
FOCUS_NEIGHBOURS = 256  # the photo colours of largest kernel weight each grid point's focus climbs over
SLICED_SMOOTH_SAMPLES = 8192  # photo colours the smoothing averages over (a stride of the pooled ones)


def smoothed_displacement(x: torch.Tensor, d: torch.Tensor, sigma: float, grid: int = SLICED_LUT,
                          focus: float = 0.0) -> torch.Tensor:
    """The displacements ``d`` [M,3] of the photo colours ``x`` [M,3] averaged with a Gaussian kernel of width
    ``sigma`` in RGB at every point of a ``grid``^3 table over [0,1]^3 -> [G,G,G,3] float64 (Nadaraya-Watson,
    normalized per grid point, so a point far from every photo colour takes its nearest colours' displacement).
    Why: the sliced map sends a grey floor's faint tints to far-apart hues of the painting (soft blobs on beer);
    averaged over colours within ``sigma``, colours that close move together and keep their own differences, while
    colours farther apart (a scene's own hues) still move to different hues of the painting.

    ``focus`` > 0: where those nearby colours were sent is not averaged but its densest place is found (mean shift
    over the destinations ``x + d``, each weighted by its kernel weight times a Gaussian of width ``focus`` around
    the estimate, from the mean, ``FOCUS_STEPS`` times), and the displacement is that place minus the colours' own
    kernel-weighted mean. Why: a floor of one colour that the map sends half to the painting's blue and half to its
    yellow takes their mean, a grey blue neither holds; with the focus it takes the painting's blue or its yellow
    (beer's photos x The Starry Night, the floor's mean Lab chroma C*: 15.5 at ``sigma`` 0.05, 22.1 with a focus of
    0.2)."""
    axis = torch.linspace(0.0, 1.0, grid, dtype=torch.float64, device=x.device)
    pts = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)  # [G^3,3]
    y = x + d  # [M,3] where each photo colour was sent
    out = torch.empty_like(pts)
    for lo in range(0, pts.shape[0], 2048):  # chunks of grid points: [2048,M] weights at a time
        w = torch.softmax(-torch.cdist(pts[lo:lo + 2048], x).square() / (2.0 * sigma * sigma), dim=1)  # [g,M]
        if focus > 0:
            # a colour keeps its own offset from its neighbours' mean
            out[lo:lo + 2048] = _densest(w, y, focus) - w @ x
        else:
            out[lo:lo + 2048] = w @ d
    return out.reshape(grid, grid, grid, 3)


def _densest(w: torch.Tensor, y: torch.Tensor, focus: float) -> torch.Tensor:
    """For each row of weights ``w`` [g,M] (summing to 1) over the points ``y`` [M,3]: the place [g,3] that mean
    shift reaches from the weighted mean, each step's weights ``w`` times a Gaussian of width ``focus`` around the
    estimate, ``FOCUS_STEPS`` steps (a fixed count: no host sync). Only each row's ``FOCUS_NEIGHBOURS`` largest
    weights take part (the rest are renormalized away): on 2 CPU cores the full product took 50 s for a table."""
    if w.shape[1] > FOCUS_NEIGHBOURS:
        w, idx = w.topk(FOCUS_NEIGHBOURS, dim=1)  # [g,K]
        w = w / w.sum(1, keepdim=True)
        ys = y[idx]  # [g,K,3]
    else:
        ys = y.expand(w.shape[0], -1, -1)
    m = (w[..., None] * ys).sum(1)  # [g,3] from the mean of the destinations ...
    for _ in range(FOCUS_STEPS):  # ... uphill to the nearest dense place
        k = w * torch.exp(-(ys - m[:, None]).square().sum(-1) / (2.0 * focus * focus))  # [g,K]
        m = (k[..., None] * ys).sum(1) / k.sum(1, keepdim=True).clamp_min(1e-300)
    return m


def _pooled_colours(items, coverage=None, limit: int = SLICED_MAX_PIXELS, device=None) -> torch.Tensor:
    """[N,3] float64 on ``device`` (default the CPU): the images' colours pooled over the pixels ``coverage`` marks
    (all pixels without it, or where it marks none), every k-th of them in order kept so that at most ``limit``
    remain. Each image gives only its own share of that stride before it is copied and widened, so a large dataset
    is never held whole in float64 (200 photos of a megapixel would be 4.8 GB)."""
    dev = torch.device("cpu") if device is None else device
    xs = [_as_torch(im).detach().reshape(-1, 3) for im in items]  # views of the inputs: nothing copied yet
    if coverage is not None:
        keep = [(_as_torch(c).detach().reshape(-1) > COVERED).to(x.device) for x, c in zip(xs, coverage)]
        if any(bool(k.any()) for k in keep):
            xs = [x[k] for x, k in zip(xs, keep)]
    stride = max(1, -(-sum(x.shape[0] for x in xs) // limit))
    out, offset = [], 0  # the pooled index of each image's first pixel: the picks continue across images
    for x in xs:
        out.append(x[(-offset) % stride::stride].to(dev, torch.float64))
        offset += x.shape[0]
    return torch.cat(out)


def sliced_palette(images, style, coverage=None, steps: int = SLICED_STEPS, quantiles: int = SLICED_QUANTILES,
                   seed: int = 0, smooth: float = 0.0, focus: float = 0.0) -> SlicedPalette:
    """The sliced map from the photos (list of [H,W,3] in [0,1]) to the painting ``style`` [h,w,3], over the pixels
    ``coverage`` marks (None: all); the rotations from ``seed`` (the same photos and painting give the same map).
    ``smooth`` > 0: its displacement averaged over photo colours within that RGB distance, ``focus`` > 0: sent to
    the densest place of their destinations instead of their mean (:func:`smoothed_displacement`)."""
    gen = torch.Generator().manual_seed(seed)  # on the CPU: the same rotations on every device
    dev = _as_torch(images[0]).device  # where the photos are (a GPU: the quantiles and the smoothing in milliseconds)
    x0, t = _pooled_colours(images, coverage, device=dev), _pooled_colours([style], device=dev)
    q = torch.linspace(0.0, 1.0, quantiles, dtype=torch.float64, device=dev)  # the ends too: the photos' extremes
    # to the painting's
    ramp = torch.arange(quantiles, dtype=torch.float64, device=dev)[:, None] * 1e-9  # strictly increasing where a
    # photo is flat
    rots, srcs, dsts, x = [], [], [], x0
    for _ in range(steps):  # a few steps, each vectorized over every pixel
        rot = _rotation(gen).to(dev)
        src, dst = torch.quantile(x @ rot, q, dim=0) + ramp, torch.quantile(t @ rot, q, dim=0)  # [Q,3] each
        x = SlicedPalette._step(x, rot, src, dst)
        rots.append(rot), srcs.append(src), dsts.append(dst)
    pal = SlicedPalette(torch.stack(rots), torch.stack(srcs), torch.stack(dsts))
    if smooth > 0:
        stride = max(1, -(-x0.shape[0] // SLICED_SMOOTH_SAMPLES))
        pal.lut = smoothed_displacement(x0[::stride], x[::stride] - x0[::stride], smooth, focus=focus)
    return pal


COVERED = 0.5  # a pixel belongs to the scene where the un-stylized render's alpha is above this


DARK_OBJECT_GAP = 0.15  # the covered pixels' mean luminance this far under the painting's: worth a note
EMPTY_SHARE = 0.1  # at least this share of the views' pixels uncovered: an object in front of an empty background


def dark_object_note(photos, coverage, style, mode: str, where: str) -> str | None:
    """One line for the user when the colour map's covered-pixel statistics (``mode`` arf, arf_rank or sliced,
    ``where`` = covered; the tone map always reads the covered pixels, so ``palette_where`` cannot help it) are about
    to give a dark object in front of an empty background the painting's mean tone (the biker under Monet: covered
    luminance 0.26, the painting 0.53, stylized 0.63; docs/study.md): the object comes out much lighter than it is, and
    ``palette_where=all`` keeps it dark. None where it does not apply: statistics over all pixels, a capture that
    fills its views (fewer than ``EMPTY_SHARE`` of the pixels uncovered), or an object within ``DARK_OBJECT_GAP`` of
    the painting's mean luminance (or lighter)."""
    if where != "covered" or mode not in ("arf", "arf_rank", "sliced"):
        return None
    n_px = n_cov = y_sum = 0.0  # sums view by view, where the views live: no pooled copy of every pixel
    for im, c in zip(photos, coverage):
        y, n = covered_luminance_sums(im, c)
        y_sum, n_cov, n_px = y_sum + y, n_cov + n, n_px + _as_torch(c).numel()
    share = n_cov / max(n_px, 1)
    if share == 0.0 or share > 1.0 - EMPTY_SHARE:
        return None
    y_obj, y_paint = y_sum / n_cov, float(_luma64(_as_torch(style).detach()).mean())
    if y_obj > y_paint - DARK_OBJECT_GAP:
        return None
    return (f"note: the scene covers {share:.0%} of its views and is darker than the painting "
            f"(mean luminance {y_obj:.2f} against {y_paint:.2f}); palette_where: covered gives it the painting's mean "
            f"tone, so it comes out lighter: --set palette_where=all keeps it dark")


TONE_DRIFT = 0.15  # the stylized scene's covered mean luminance this far from its colour target's: worth a note


def covered_luminance_sums(img, coverage) -> tuple[float, float]:
    """(sum of BT.601 luminance, pixel count) over the pixels ``coverage`` [H,W] or [H,W,1] (the un-stylized
    scene's alpha) covers in ``img`` [H,W,3]: summed view by view, so that no pooled copy of every pixel is made."""
    keep = _as_torch(coverage).detach().reshape(-1) > COVERED  # [H*W]
    y = _luma64(_as_torch(img).detach()).reshape(-1)[keep]
    return float(y.sum()), float(keep.sum())


def covered_mean_luminance(images, coverage) -> float | None:
    """The mean BT.601 luminance over the pixels ``coverage`` covers in every view of ``images``, summed view by
    view (``covered_luminance_sums``); None where no pixel is covered."""
    y_sum = n = 0.0
    for im, c in zip(images, coverage):
        y, k = covered_luminance_sums(im, c)
        y_sum, n = y_sum + y, n + k
    return y_sum / n if n else None


def tone_drift_note(stylized: float, target: float, hold: float = 0.0) -> str | None:
    """One line for the user when the stylized scene's mean luminance over the pixels the un-stylized scene covers
    has moved ``TONE_DRIFT`` or more from its colour target's (the recoloured photos' over the same pixels): the
    biker splats under Starry Night over the Rhône went from a target of 0.22 to 0.48 without the tone hold, a black
    figure painted pale grey (docs/study.md). It names the tone hold's weight to use: 100 where the run had none
    (``hold``: the run's ``loss.w_tone_hold``), ten times the run's otherwise. None within the margin."""
    if not abs(stylized - target) >= TONE_DRIFT:
        return None
    way = "lighter" if stylized > target else "darker"
    fix = (f"--set loss.w_tone_hold={10 * hold:g} holds it closer (this run: {hold:g})" if hold > 0
           else "--set loss.w_tone_hold=100 holds it near the target")
    return (f"note: the stylized scene came out {way} than its colour target over the pixels it covers (mean "
            f"luminance {stylized:.2f} against {target:.2f}); {fix}")


def _pooled_luma(items, coverage=None) -> torch.Tensor:
    """The photos' luminance, pooled over the pixels the scene covers (all pixels without ``coverage``, or where
    it covers none): a Blender object on a white background must take the painting's tones from its own range,
    not sit in the darkest ranks below the white (lego x The Starry Night turned into a dark grey mass)."""
    return _luma64(_pooled_colours(items, coverage, TONE_MAX_PIXELS))


def tone_palette(images, style, bins: int = TONE_BINS, coverage=None) -> TonePalette:
    """The tone map from the photos ``images`` (list of [H,W,3] in [0,1]) to the painting ``style`` [h,w,3];
    the photos' statistics over the pixels ``coverage`` (per view [H,W,1], the un-stylized scene's alpha) marks."""
    y_c = _pooled_luma(images, coverage)
    s = _as_torch(style).detach().cpu().double().reshape(-1, 3)  # [P,3]
    y_s = _luma64(s)
    order = torch.argsort(y_s)
    groups = torch.tensor_split(order, bins)
    c_s = _chroma(s, y_s)  # [P,2]
    tone_chroma = []
    for g in groups:  # K small bins: a loop over bins, not pixels
        c = c_s[g]
        mean = c.mean(0)
        boost = float(c.norm(dim=1).mean() / mean.norm().clamp_min(1e-12))
        tone_chroma.append(mean * min(boost, TONE_MAX_BOOST))  # averaging opposite hues must not leave grey
    q = (torch.arange(bins, dtype=torch.float64) + 0.5) / bins
    knots = torch.quantile(y_c, q)
    knots = knots + torch.arange(bins, dtype=torch.float64) * 1e-9  # strictly increasing where photos are flat
    sd_c = float(y_c.std(unbiased=False))
    return TonePalette((float(y_c.mean()), float(y_s.mean())), float(y_s.std(unbiased=False)) / max(sd_c, 1e-6),
                       knots, torch.stack(tone_chroma))


def palette_transfer(images, style, mode: str, coverage=None, floor: float = 0.0, where: str = "all",
                     smooth: float = 0.0, focus: float = 0.0):
    """``(recolored, palette)``: the photos (list of [H,W,3]) in the painting's palette by ``mode`` (arf | arf_rank |
    sliced | tone), and the map, whose ``recolor_sh`` gives the Gaussians the same palette. ``coverage`` (per view
    [H,W,1]) limits the tone map's photo statistics to the scene, and ARF's and the sliced map's where ``where`` is
    ``covered``; with ``all`` ARF pools every pixel, as released (the baseline uses it). ``floor``: ARF's variance
    floor (:func:`color.color_transfer`); ``smooth``, ``focus``: the sliced map's smoothing and focus widths
    (:func:`sliced_palette`)."""
    if where not in ("all", "covered"):
        raise ValueError(f"palette statistics over all or covered pixels, got {where!r}")
    if mode == "arf":
        out, m, t = color_transfer(list(images), style, floor, coverage if where == "covered" else None)
        return out, AffinePalette(m, t)
    if mode == "tone":
        pal = tone_palette(images, style, coverage=coverage)
        return [pal.apply(im) for im in images], pal
    if mode == "arf_rank":
        pal = rank_palette(images, style, floor, coverage if where == "covered" else None)
        return [pal.apply(im) for im in images], pal
    if mode == "sliced":
        pal = sliced_palette(images, style, coverage if where == "covered" else None, smooth=smooth, focus=focus)
        return [pal.apply(im) for im in images], pal
    raise ValueError(f"palette mode must be arf, arf_rank, sliced or tone, got {mode!r}")


# --- the painting's colours as a set: the palette-snap term of the Stylize phase (ours) -------------------------
SNAP_MAX_PIXELS = 200_000  # k-means runs on at most this many of the painting's pixels (a stride)


def painting_colours(painting, k: int, seed: int = 0) -> torch.Tensor:
    """The painting's ``k`` dominant colours [k,3] float32 in [0,1]: OpenCV's k-means (k-means++ seeding, 3 tries)
    on its RGB pixels ([H,W,3] in [0,1], numpy or torch)."""
    import cv2  # lazy: cv2 takes a tenth of a second to import

    px = _as_torch(painting).detach().reshape(-1, 3).cpu().numpy().astype(np.float32)
    px = np.ascontiguousarray(px[:: max(1, -(-len(px) // SNAP_MAX_PIXELS))])
    k = int(min(k, len(np.unique(px, axis=0))))  # a flat painting has fewer colours than asked for
    cv2.setRNGSeed(int(seed))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    _, _, centres = cv2.kmeans(px, k, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
    return torch.from_numpy(centres.astype(np.float32))


def palette_snap_loss(img: torch.Tensor, colours: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over pixels (weighted by ``weight`` [H,W,1], e.g. the scene's coverage) of the squared chroma distance
    between each pixel of ``img`` [H,W,3] and the painting colour of ``colours`` [K,3] nearest to it in RGB.
    Chroma = RGB minus its luminance (BT.601), so the term is blind to grey added to a pixel and its gradient has no
    grey component (R + G + B stays): the pull is on colour, the level is the style term's, and a stroke's tone
    picks its colour (The Starry Night: a light stroke goes yellow, a dark one blue) instead of
    every pixel taking one mean tint. The assignment carries no gradient (the nearest colour is a constant)."""
    x = img.reshape(-1, 3)  # [P,3]
    c = colours.to(x)
    with torch.no_grad():  # ‖x‖² - 2x·c + ‖c‖², without the constant ‖x‖²: one matmul
        nearest = ((c * c).sum(1)[None] - 2.0 * x @ c.T).argmin(1)  # [P]
    diff = x - c[nearest]  # [P,3]
    d_chroma = chroma(diff)  # [P,3]: Y of a difference is linear, so this is chroma(x) - chroma(colour)
    sq = (d_chroma * d_chroma).sum(1)  # [P]
    if weight is None:
        return sq.mean()
    w = weight.reshape(-1).to(sq)
    return (w * sq).sum() / w.sum().clamp_min(1e-12)
