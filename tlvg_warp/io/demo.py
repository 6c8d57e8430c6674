"""The built-in demo: a procedural 3DGS still life, an orbit of cameras, its rendered "photos", and a
built-in painting, so ``stylize`` runs on a fresh machine with no data.

The scene (world z up, ground at z = 0, units ~ metres): a striped sphere, a checkered cube, a torus with
spiral bands and a fluted cylinder on a plank floor; ~17k flat Gaussians, each a small disc tangent to
its surface (two scales ~0.6 x sample spacing, the third thin) so the surfaces read as solid.
``spacing`` > 1 builds the same still life from fewer, larger discs (sample spacing x ``spacing``, so about
1/spacing² the Gaussians): at small render sizes the default discs project below a pixel, where the EWA
blur makes every footprint round and a splat's orientation cannot show in the image."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..renderer import render
from ..types import SH_C0, Camera, Gaussians
from .datasets import Dataset
from .images import read_image

ASSETS = Path(__file__).resolve().parent.parent / "assets"
DISC = 0.6  # in-plane scale / sample spacing: neighbouring discs overlap, no holes at 0.9 opacity
THIN = 0.12  # normal scale / spacing: flat enough to read as a surface, not so thin it aliases
OPACITY = 0.9
DEMO_BACKGROUND = (1.0, 1.0, 1.0)  # white, like the Blender convention load_dataset composites onto


def _count(n: int, k: float) -> int:
    return max(2, round(n / k))  # samples along one direction at sample spacing x k


def _ground(rng, k=1.0):
    n = _count(90, k)  # 90 x 90 samples over 3.6 m: spacing 0.04 (x k)
    s = np.linspace(-1.8, 1.8, n)
    x, y = (a.ravel() for a in np.meshgrid(s, s, indexing="ij"))
    plank = np.floor(y / 0.3)  # 30 cm planks running along x, each its own tone, with wavy grain
    tone = 0.85 + 0.15 * np.sin(plank * 2.3)
    grain = 0.06 * np.sin(40 * x + 3 * np.sin(7 * y) + plank * 1.7)
    gap = (np.abs(y / 0.3 - np.round(y / 0.3)) < 0.06) * 0.25  # dark seams between planks
    base = np.array([0.62, 0.46, 0.30])
    rgb = base * (tone + grain - gap)[:, None]  # [N, 3]
    pts = np.stack([x, y, np.zeros_like(x)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    return pts, nrm, rgb, np.full(len(x), s[1] - s[0])


def _sphere(rng, k=1.0, center=(-0.55, 0.35, 0.35), r=0.35, n=3000):
    n = max(8, round(n / (k * k)))  # a surface: spacing x k is 1/k² the samples
    i = np.arange(n) + 0.5  # Fibonacci lattice: near-uniform samples on the sphere
    z = 1 - 2 * i / n
    phi = math.pi * (3 - math.sqrt(5)) * i
    nrm = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    band = np.floor((z + 1) * 4).astype(int) % 2  # 8 latitude bands, alternating red / cream
    rgb = np.where(band[:, None] == 0, [0.80, 0.12, 0.10], [0.95, 0.88, 0.70])
    return np.asarray(center) + r * nrm, nrm, rgb, np.full(n, math.sqrt(4 * math.pi * r * r / n))


def _cube(rng, k=1.0, center=(0.55, 0.3, 0.25), side=0.5, yaw_deg=30.0, m=24):
    m = _count(m, k)
    u = (np.arange(m) + 0.5) / m - 0.5
    a, b = (v.ravel() for v in np.meshgrid(u, u, indexing="ij"))
    pts, nrm, rgb = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            if axis == 2 and sign < 0:
                continue  # the bottom face rests on the floor, never seen
            p = np.zeros((len(a), 3))
            p[:, axis] = 0.5 * sign
            p[:, (axis + 1) % 3], p[:, (axis + 2) % 3] = a, b
            nn = np.zeros_like(p)
            nn[:, axis] = sign
            check = (np.floor((a + 0.5) * 4) + np.floor((b + 0.5) * 4)) % 2  # 4x4 checker per face
            pts.append(p), nrm.append(nn)
            rgb.append(np.where(check[:, None] == 0, [0.10, 0.25, 0.75], [0.92, 0.92, 0.95]))
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    pts, nrm = np.concatenate(pts) * side @ R.T + center, np.concatenate(nrm) @ R.T
    return pts, nrm, np.concatenate(rgb), np.full(len(pts), side / m)


def _torus(rng, k=1.0, center=(-0.05, -0.55, 0.12), R=0.30, r=0.12, nu=90, nv=36):
    nu, nv = _count(nu, k), _count(nv, k)
    u, v = (a.ravel() for a in np.meshgrid(np.arange(nu) * 2 * math.pi / nu, np.arange(nv) * 2 * math.pi / nv,
                                             indexing="ij"))
    nrm = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], 1)
    pts = np.asarray(center) + np.stack([R * np.cos(u), R * np.sin(u), np.zeros_like(u)], 1) + r * nrm
    spiral = np.sin(3 * u + 2 * v) > 0.3  # helical bands wrapping the tube
    rgb = np.where(spiral[:, None], [0.95, 0.80, 0.15], [0.10, 0.50, 0.25])
    return pts, nrm, rgb, np.full(len(u), 2 * math.pi * (R + r) / nu)


def _cylinder(rng, k=1.0, center=(0.75, -0.45, 0.0), r=0.15, h=0.55, nu=48, nz=28):
    nu, nz, nr, nt = _count(nu, k), _count(nz, k), _count(8, k), _count(24, k)  # nr, nt: the cap's rings, spokes
    u, z = (a.ravel() for a in np.meshgrid(np.arange(nu) * 2 * math.pi / nu, (np.arange(nz) + 0.5) / nz * h,
                                             indexing="ij"))
    side_n = np.stack([np.cos(u), np.sin(u), np.zeros_like(u)], 1)
    side_p = np.asarray(center) + r * side_n + np.stack([0 * u, 0 * u, z], 1)
    flute = (np.floor(u / (2 * math.pi) * 12) % 2)[:, None]  # 12 vertical flutes, two purples
    side_c = np.where(flute == 0, [0.45, 0.20, 0.60], [0.70, 0.55, 0.85])
    rr, tt = (a.ravel() for a in np.meshgrid(np.linspace(0, r, nr)[1:], np.arange(nt) * 2 * math.pi / nt,
                                             indexing="ij"))
    cap_p = np.asarray(center) + np.stack([rr * np.cos(tt), rr * np.sin(tt), np.full_like(rr, h)], 1)
    cap_p = np.concatenate([cap_p, np.asarray(center)[None] + [0, 0, h]])
    cap_n = np.tile([0.0, 0.0, 1.0], (len(cap_p), 1))
    cap_c = np.tile([0.85, 0.75, 0.95], (len(cap_p), 1))
    spacing = np.concatenate([np.full(len(u), 2 * math.pi * r / nu), np.full(len(cap_p), r / (nr - 1))])
    return (np.concatenate([side_p, cap_p]), np.concatenate([side_n, cap_n]),
            np.concatenate([side_c, cap_c]), spacing)


def _tangent_quats(nrm):  # [N, 3] unit normals -> [N, 4] w,x,y,z rotating local z onto the normal
    q = np.stack([1 + nrm[:, 2], -nrm[:, 1], nrm[:, 0], np.zeros(len(nrm))], 1)  # [1 + z.n, z x n]
    q[nrm[:, 2] < -1 + 1e-9] = [0.0, 1.0, 0.0, 0.0]  # antiparallel: half turn about x
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def demo_scene(seed: int = 0, n_views: int = 24, width: int = 160, height: int = 120,
               sh_degree: int = 0, spacing: float = 1.0) -> tuple[Gaussians, list[Camera]]:
    """(Gaussians, orbit cameras). ``seed`` jitters colors by a few percent, deterministically; ``spacing``
    multiplies the sample spacing (and so the disc size) of every surface."""
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    rng = np.random.default_rng(seed)
    parts = [f(rng, spacing) for f in (_ground, _sphere, _cube, _torus, _cylinder)]
    pts, nrm, rgb, step = (np.concatenate([p[k] for p in parts]) for k in range(4))  # [N, ...] step: local spacing
    rgb = np.clip(rgb * (1 + 0.04 * rng.standard_normal(rgb.shape)), 0.02, 0.98)
    n = len(pts)
    log_s = np.log(np.stack([DISC * step, DISC * step, THIN * step], 1))  # [N, 3]
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3))
    sh[:, 0] = (rgb - 0.5) / SH_C0
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    g = Gaussians(t(pts), t(_tangent_quats(nrm)), t(log_s),
                  t(np.full(n, math.log(OPACITY / (1 - OPACITY)))), t(sh))
    return g, orbit_cameras(n_views, width, height)


def orbit_cameras(n_views=24, width=160, height=120, radius=2.6, elevation=1.6, target=(0.05, 0.0, 0.2),
                  fov_deg=50.0) -> list[Camera]:
    """``n_views`` cameras evenly around the z axis, looking at the still life."""
    cams = []
    for k in range(n_views):
        a = 2 * math.pi * k / n_views
        eye = (radius * math.cos(a), radius * math.sin(a), elevation)
        cams.append(Camera.look_at(eye, target, up=(0, 0, 1), fov_deg=fov_deg, width=width, height=height,
                                   name=f"view_{k:03d}"))
    return cams


def demo_dataset(seed: int = 0, n_views: int = 24, width: int = 160, height: int = 120, split=None,
                 holdout_every: int = 8, background=DEMO_BACKGROUND, spacing: float = 1.0):
    """A Dataset (same interface as load_dataset's) whose photos are renders of :func:`demo_scene`.

    Extra attributes: ``gaussians`` (the scene itself) and ``background``. ``points`` are every 8th
    Gaussian's center and color, standing in for SfM points."""
    g, cams = demo_scene(seed, n_views, width, height, spacing=spacing)
    names = [c.name for c in cams]
    keep = list(range(n_views))
    if split is not None:
        keep = [i for i in keep if (i % holdout_every == 0) == (split == "test")]
    # render the photos where the work will run (a GPU-only Warp install cannot compile CPU kernels)
    g_dev = g.to("cuda") if torch.cuda.is_available() else g

    def load(i):
        with torch.no_grad():
            return render(g_dev, cams[keep[i]], background=background).color.detach().cpu().numpy()

    sub = torch.arange(0, g.num, 8)
    rgb = (g.sh[sub, 0] * SH_C0 + 0.5).clamp(0, 1)
    ds = Dataset(Path("<demo>"), [cams[i] for i in keep], [names[i] for i in keep], load,
                 (g.means[sub].clone(), rgb), kind="demo", threaded=False)  # its photos are Warp renders
    ds.gaussians, ds.background = g, background
    return ds


def builtin_painting() -> torch.Tensor:
    """Van Gogh's The Starry Night (1889, public domain), height 256: float32 [H, W, 3] RGB in [0, 1]."""
    return torch.from_numpy(read_image(ASSETS / "starry_night.jpg")[:, :, :3].copy())
