"""Pure-torch reference twins of the raster ops (same signatures), the oracle the tests compare against.

Written for clarity, not speed: every pixel sees every Gaussian (a [pixels, N] matrix, chunked), with the
same thresholds and the same tile membership as the Warp path (SPEC §2). Differentiable by torch
autograd; run it in float64 for tests."""
from __future__ import annotations

import math

import torch

from .kernels.blend import ALPHA_MAX, ALPHA_MIN, T_MIN
from .kernels.binning import TILE
from .kernels.projection import EWA_BLUR, FOV_CLAMP, SH_C0, SH_C1, SH_C2, SH_C3, SIGMA_CUTOFF
from .raster import Projected
from .renderer import RenderOutput, check_inputs
from .types import Camera, Gaussians


def quat_to_rotation(q: torch.Tensor) -> torch.Tensor:  # [N, 4] -> [N, 3, 3]
    n = q.norm(dim=-1, keepdim=True)
    ident = torch.tensor([1.0, 0, 0, 0], dtype=q.dtype, device=q.device).expand_as(q)
    q = torch.where(n.square() > 1e-24, q / n.clamp_min(1e-30), ident)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def sh_basis(d: torch.Tensor, degree: int) -> torch.Tensor:  # [N, 3] unit dirs -> [N, (degree+1)^2]
    x, y, z = d.unbind(-1)
    one = torch.ones_like(x)
    cols = [SH_C0 * one]
    if degree > 0:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        cols += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                 SH_C2[4] * (xx - yy)]
    if degree > 2:
        cols += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
                 SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                 SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(cols, -1)


def shade_reference(means: torch.Tensor, sh: torch.Tensor, cam: Camera, degree: int) -> torch.Tensor:
    """autograd.ShadeFn's twin: max(SH up to ``degree`` (unit direction from the camera center) + 0.5, 0).  # [N, 3]"""
    dirs = means - cam.center.to(means.dtype).to(means.device)
    dirs = dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-30)
    k = (degree + 1) ** 2
    return (torch.einsum("nk,nkc->nc", sh_basis(dirs, degree), sh[:, :k]) + 0.5).clamp_min(0)


def project_reference(g: Gaussians, cam: Camera, sh_degree: int | None = None) -> Projected:
    dt, dev = g.dtype, g.device
    R = cam.R.to(dt).to(dev)
    t = cam.t.to(dt).to(dev)
    finite = (torch.isfinite(g.means).all(1) & torch.isfinite(g.quats).all(1) & torch.isfinite(g.log_scales).all(1)
              & torch.isfinite(g.opacity_logits))
    means = torch.where(finite[:, None], g.means, 0.0)
    p = means @ R.T + t  # [N, 3]
    z = p[:, 2]
    ok = finite & (z > cam.near) & (z < cam.far)
    zs = torch.where(ok, z, torch.ones_like(z))  # keep culled rows finite so they cannot poison gradients
    s = torch.exp(torch.where(finite[:, None], g.log_scales, 0.0))
    ok = ok & (torch.isfinite(s).all(1))
    s = torch.where(ok[:, None], s, 0.0)
    M = quat_to_rotation(torch.where(finite[:, None], g.quats, 1.0)) * s[:, None, :]
    Sigma = M @ M.transpose(1, 2)
    lim_x = FOV_CLAMP * 0.5 * cam.width / cam.fx
    lim_y = FOV_CLAMP * 0.5 * cam.height / cam.fy
    tx = (p[:, 0] / zs).clamp(-lim_x, lim_x) * zs
    ty = (p[:, 1] / zs).clamp(-lim_y, lim_y) * zs
    zero = torch.zeros_like(zs)
    J = torch.stack([cam.fx / zs, zero, -cam.fx * tx / zs**2, zero, cam.fy / zs, -cam.fy * ty / zs**2], -1).reshape(-1, 2, 3)
    T = J @ R
    S2 = T @ Sigma @ T.transpose(1, 2)
    a, b, c = S2[:, 0, 0] + EWA_BLUR, S2[:, 0, 1], S2[:, 1, 1] + EWA_BLUR
    det = a * c - b * b
    ok = ok & ((det > 0) & torch.isfinite(det))
    det = torch.where(ok, det, torch.ones_like(det))
    mid = 0.5 * (a + c)
    r = torch.ceil(SIGMA_CUTOFF * torch.sqrt(mid + torch.sqrt((mid * mid - det).clamp_min(0))))
    u = cam.fx * p[:, 0] / zs + cam.cx
    v = cam.fy * p[:, 1] / zs + cam.cy
    ok = ok & (~((u + r <= 0) | (u - r >= cam.width) | (v + r <= 0) | (v - r >= cam.height)) & (r <= 1e7))
    rgb = shade_reference(means, g.sh, cam, g.sh_degree if sh_degree is None else sh_degree)
    okf = ok.to(dt)
    return Projected(
        means2d=torch.stack([u, v], -1) * okf[:, None],
        cov2d=torch.stack([a, b, c], -1) * okf[:, None],
        conic=torch.stack([c / det, -b / det, a / det], -1) * okf[:, None],
        depth=z * okf,
        opacity=torch.sigmoid(g.opacity_logits.nan_to_num()) * okf,
        color=rgb.nan_to_num() * okf[:, None],
        radii=torch.where(ok, r, torch.zeros_like(r)).to(torch.int32),
    )


def render_reference(g: Gaussians, cam: Camera, background=None, *, sh_degree: int | None = None,
                     return_weights: bool = False, all_tiles: bool = False, depth: bool = True,
                     chunk: int = 2048) -> RenderOutput:
    bg = torch.tensor(check_inputs(g, cam, background), dtype=g.dtype, device=g.device)
    proj = project_reference(g, cam, sh_degree)
    vis = proj.radii > 0
    order = torch.sort(proj.depth.float(), stable=True).indices  # the radix sort's (depth, index) order
    order = order[vis[order]]
    probe = torch.zeros(g.num, 2, dtype=g.dtype, device=g.device, requires_grad=True)  # screen-mean gradient
    m2 = (proj.means2d + probe)[order]
    conic, op, col, dep = (x[order] for x in (proj.conic, proj.opacity, proj.color, proj.depth))
    # tile rectangle of each Gaussian, computed like the kernel (float32 means, exclusive upper bounds)
    tiles_x, tiles_y = math.ceil(cam.width / TILE), math.ceil(cam.height / TILE)
    mf, rf = proj.means2d.float()[order], proj.radii.float()[order]
    x0 = torch.floor((mf[:, 0] - rf) / TILE).clamp(0, tiles_x)
    x1 = (torch.floor((mf[:, 0] + rf) / TILE) + 1).clamp(0, tiles_x)
    y0 = torch.floor((mf[:, 1] - rf) / TILE).clamp(0, tiles_y)
    y1 = (torch.floor((mf[:, 1] + rf) / TILE) + 1).clamp(0, tiles_y)
    H, W = cam.height, cam.width
    jj, ii = torch.meshgrid(torch.arange(W, device=g.device), torch.arange(H, device=g.device), indexing="xy")
    pix = torch.stack([jj.flatten(), ii.flatten()], -1)  # [P, 2] (col, row)
    colors, alphas, depths = [], [], []
    weights = torch.zeros(g.num, dtype=g.dtype, device=g.device)
    for s in range(0, pix.shape[0], chunk):
        pj, pi = pix[s:s + chunk, 0:1], pix[s:s + chunk, 1:2]
        tx, ty = (pj // TILE).float(), (pi // TILE).float()
        member = torch.ones_like(tx, dtype=torch.bool) if all_tiles else (
            (tx >= x0) & (tx < x1) & (ty >= y0) & (ty < y1))  # [P, N']
        dx = (pj.to(g.dtype) + 0.5) - m2[:, 0]
        dy = (pi.to(g.dtype) + 0.5) - m2[:, 1]
        power = -0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) - conic[:, 1] * dx * dy
        alpha = torch.clamp_max(op * torch.exp(power.clamp_max(0)), ALPHA_MAX)
        valid = member & (power <= 0) & (alpha >= ALPHA_MIN)
        a = alpha * valid
        stop = torch.cumsum(valid & (torch.cumprod(1 - a, 1) < T_MIN), 1) > 0  # stop before that Gaussian
        a = a * ~stop
        T_excl = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), 1 - a[:, :-1]], 1), 1)
        w = a * T_excl  # [P, N']
        T_final = T_excl[:, -1] * (1 - a[:, -1]) if a.shape[1] else torch.ones(a.shape[0], dtype=g.dtype, device=g.device)
        A = 1 - T_final
        colors.append(w @ col + T_final[:, None] * bg)
        alphas.append(A)
        S = w @ dep
        depths.append(torch.where(A > 0, S / torch.where(A > 0, A, torch.ones_like(A)), torch.zeros_like(A)))
        if return_weights:
            weights = weights.index_add(0, order, w.sum(0))
    color = torch.cat(colors).reshape(H, W, 3)
    return RenderOutput(color, torch.cat(alphas).reshape(H, W), torch.cat(depths).reshape(H, W) if depth else None,
                        proj.radii, probe,
                        weights if return_weights else None)
