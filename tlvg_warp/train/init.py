"""Scene initialization: Gaussians from SfM points (or random points in the camera frustums) and the scene
extent.

- Colors become the SH DC coefficient ((rgb − 0.5) / C0), higher bands zero.
- Initial scale (isotropic) = sqrt of the mean squared distance to the 3 nearest neighbours, as graphdeco's
  ``distCUDA2`` (their "mean distance" is this root-mean-square), floored at sqrt(1e-7).
  The neighbours come from a chunked ``torch.cdist`` + ``topk``: memory O(chunk·N), never an N×N matrix.
- quats identity, opacity 0.1 (3DGS).
- Scene extent = 1.1 × the largest distance of a camera center from the centers' mean (graphdeco's
  ``getNerfppNorm`` radius).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import InputError
from ..types import SH_C0, Gaussians, sh_coeffs

KNN_CHUNK_ELEMS = 1 << 24  # distance entries per chunk (64 MB in float32)
MIN_DIST2 = 1e-7  # graphdeco's clamp of the squared neighbour distance


def knn_distances(points: torch.Tensor, k: int = 3, chunk_elems: int = KNN_CHUNK_ELEMS) -> torch.Tensor:
    """[N,k] Euclidean distances from every point to its k nearest other points (ascending). Points with
    fewer than k others get +inf in the missing columns. Chunked: O(chunk·N) memory."""
    x = points.detach()
    n = x.shape[0]
    kk = min(k + 1, n)
    out = torch.full((n, k), math.inf, dtype=x.dtype, device=x.device)
    if n <= 1:
        return out
    rows = max(1, chunk_elems // n)
    ar = torch.arange(n, device=x.device)
    for s in range(0, n, rows):
        q = x[s:s + rows]
        d = torch.cdist(q, x)  # [rows, N]
        d[torch.arange(q.shape[0], device=x.device), ar[s:s + rows]] = math.inf  # exclude self
        vals = torch.topk(d, kk - 1 if kk - 1 > 0 else 1, dim=1, largest=False).values
        out[s:s + rows, :vals.shape[1]] = vals[:, :k]
    return out


def knn_scale(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """[N] sqrt(mean of the squared distances to the k nearest neighbours), graphdeco's initial scale."""
    d = knn_distances(points, k)
    d2 = torch.where(torch.isfinite(d), d * d, torch.full_like(d, math.nan))
    d2 = torch.nanmean(d2, dim=1)
    d2 = torch.nan_to_num(d2, nan=1e-2).clamp_min(MIN_DIST2)  # a lone point: a small default
    return d2.sqrt()


def camera_centers(cameras) -> torch.Tensor:
    return torch.stack([c.center for c in cameras]).double()


def scene_extent(cameras) -> float:
    """1.1 × max distance of the camera centers from their mean (graphdeco). Co-located cameras give 0;
    then 1.0 is used (the xyz learning rate needs a length scale)."""
    c = camera_centers(cameras)
    r = float((c - c.mean(0)).norm(dim=1).max()) * 1.1
    return r if r > 1e-9 else 1.0


def points_in_front(xyz: torch.Tensor, cameras) -> torch.Tensor:
    """Bool [P]: the point is in front of (z > near) at least one camera."""
    x = xyz.detach().double().cpu()
    ok = torch.zeros(x.shape[0], dtype=torch.bool)
    for c in cameras:
        z = x @ c.R[2] + c.t[2]
        ok |= z > c.near
    return ok


def from_points(xyz, rgb, max_sh_degree: int = 3, opacity: float = 0.1, device="cpu",
                dtype=torch.float32) -> Gaussians:
    """Gaussians at the given points: SH DC from ``rgb`` in [0,1], kNN scales, identity rotations."""
    xyz = torch.as_tensor(np.asarray(xyz) if not torch.is_tensor(xyz) else xyz).to(device=device, dtype=dtype)
    rgb = torch.as_tensor(np.asarray(rgb) if not torch.is_tensor(rgb) else rgb).to(device=device, dtype=dtype)
    if rgb.numel() and rgb.max() > 1.5:  # 8-bit colors
        rgb = rgb / 255.0
    n = xyz.shape[0]
    sh = torch.zeros(n, sh_coeffs(max_sh_degree), 3, dtype=dtype, device=device)
    sh[:, 0] = (rgb.clamp(0, 1) - 0.5) / SH_C0
    scale = knn_scale(xyz, 3)
    quats = torch.zeros(n, 4, dtype=dtype, device=device)
    quats[:, 0] = 1
    logit = math.log(opacity / (1 - opacity))
    return Gaussians(xyz.contiguous(), quats, torch.log(scale)[:, None].repeat(1, 3).contiguous(),
                     torch.full((n,), logit, dtype=dtype, device=device), sh)


def scene_center_guess(cameras) -> tuple[torch.Tensor, float]:
    """A point the cameras look at and its typical distance: the least-squares intersection of the optical
    axes when they converge; for forward-facing rigs (near-parallel axes), a point ahead of the rig."""
    c = camera_centers(cameras)
    f = torch.stack([c_.R[2] for c_ in cameras]).double()  # optical axes (world)
    A = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for ci, fi in zip(c, f):
        P = torch.eye(3, dtype=torch.float64) - torch.outer(fi, fi)
        A += P
        b += P @ ci
    ev = torch.linalg.eigvalsh(A)
    spread = float((c - c.mean(0)).norm(dim=1).max())
    if float(ev[0]) > 1e-3 * float(ev[-1]):
        p = torch.linalg.solve(A, b)
        d = (p - c).norm(dim=1).median()
        if float(((p - c) * f).sum(1).min()) > 0 and float(d) < 1e3 * max(spread, 1e-9):
            return p, float(d)
    d = max(spread, 1e-3) * 4.0
    return c.mean(0) + f.mean(0) / f.mean(0).norm() * d, d


def random_in_frustums(cameras, num: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """[num,3] float64 points, each inside some camera's frustum at a depth drawn between 0.3× and 2× the
    guessed scene distance (uniform in inverse depth)."""
    _, d = scene_center_guess(cameras)
    g = generator
    cam_idx = torch.randint(len(cameras), (num,), generator=g)
    u = torch.rand(num, 2, generator=g, dtype=torch.float64)
    inv = 1.0 / (2.0 * d) + torch.rand(num, generator=g, dtype=torch.float64) * (1.0 / (0.3 * d) - 1.0 / (2.0 * d))
    z = 1.0 / inv
    pts = torch.empty(num, 3, dtype=torch.float64)
    for i, cam in enumerate(cameras):
        m = cam_idx == i
        if not bool(m.any()):
            continue
        px = u[m, 0] * cam.width
        py = u[m, 1] * cam.height
        zz = z[m]
        pc = torch.stack([(px - cam.cx) / cam.fx * zz, (py - cam.cy) / cam.fy * zz, zz], dim=1)
        pts[m] = (pc - cam.t) @ cam.R  # R^T (pc - t)
    return pts


def initialize(dataset, max_sh_degree=3, opacity=0.1, random_points=20000, max_points=0, device="cpu",
               seed=0) -> tuple[Gaussians, float, str]:
    """(Gaussians, extent, what) for a dataset: its SfM points if it has any, else random points in the
    frustums. ``max_points`` > 0 subsamples the SfM points (random, seeded). Refuses point sets that lie
    entirely behind the cameras."""
    cams = dataset.cameras
    extent = scene_extent(cams)
    gen = torch.Generator().manual_seed(int(seed))
    pts = getattr(dataset, "points", None)
    if pts is not None and len(pts[0]) > 0:
        xyz = torch.as_tensor(np.asarray(pts[0], dtype=np.float64))
        rgb = torch.as_tensor(np.asarray(pts[1], dtype=np.float64))
        finite = torch.isfinite(xyz).all(1) & torch.isfinite(rgb).all(1)
        xyz, rgb = xyz[finite], rgb[finite]
        front = points_in_front(xyz, cams)
        if not bool(front.any()):
            raise InputError(f"all {len(front)} SfM points lie behind every camera (check the pose convention)")
        xyz, rgb = xyz[front], rgb[front]
        if max_points and xyz.shape[0] > max_points:
            idx = torch.randperm(xyz.shape[0], generator=gen)[:max_points].sort().values
            xyz, rgb = xyz[idx], rgb[idx]
        return from_points(xyz, rgb, max_sh_degree, opacity, device), extent, f"{xyz.shape[0]} SfM points"
    n = int(random_points)
    xyz = random_in_frustums(cams, n, gen)
    rgb = 0.5 + 0.1 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    return from_points(xyz, rgb, max_sh_degree, opacity, device), extent, f"{n} random points in the frustums"


__all__ = ["knn_distances", "knn_scale", "scene_extent", "points_in_front", "from_points", "random_in_frustums",
           "initialize", "camera_centers", "scene_center_guess"]
