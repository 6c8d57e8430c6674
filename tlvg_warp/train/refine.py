"""Stroke-size refinement (ours): split the splats too coarse to carry a brushstroke, before a stylization.

A fitted scene paints flat regions (a floor, a wall, a sky) with a few splats hundreds of pixels wide: the
colour of such a splat is one number, so no style loss can put a brushstroke inside it, and the stylization
comes out as a smooth colour wash. Gradient-driven densification does not fix it within a budget: its room
goes to small splats with large gradients first. This pass does what a painter's underdrawing does: every
splat whose screen radius (mean over the views, weighted by what it contributes) exceeds ``radius`` pixels is
replaced by children ``radius`` wide, sampled inside it with the same mixture moments, as many as cover its
area with some overlap. The room comes from the budget and, where that is short, from splats that contribute
almost nothing to any view; the splats covering the most pixels are refined first.
"""
from __future__ import annotations

import math

import torch

from ..renderer import render
from ..types import Gaussians
from .optim import quat_to_rotmat

OVERLAP = 2.5  # children per unit of area ratio: each point is covered about this often, so no gaps open (1.5 left 2-3% holes on a synthetic wall, 2 about 0.9%)
MAX_CHILDREN = 16  # per parent and pass; a huge splat is refined over several passes
NEGLIGIBLE_PX = 0.05  # blend weight (pixels, summed over the views) under which a splat may make room
CLAMP_SIGMA = 2.0  # children's centres within 2 sigma of the parent


@torch.no_grad()
def view_footprints(g: Gaussians, cams, background=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean screen radius [N] in pixels, weighted by each view's Σ αT; total Σ αT [N] over the views)."""
    wsum = torch.zeros(g.num, dtype=torch.float64, device=g.device)
    wr = torch.zeros_like(wsum)
    for cam in cams:
        out = render(g, cam, background, return_weights=True, depth=False)
        w = out.weights.double()
        wsum += w
        wr += w * out.radii.double()
    return (wr / wsum.clamp_min(1e-12)).float(), wsum


def _stratified_normal(kids: torch.Tensor, seed: int) -> torch.Tensor:
    """[sum(kids), 3] standard-normal offsets, clamped at 2 sigma; each parent's children take consecutive points
    of one scrambled Sobol sequence, so they spread evenly instead of clumping (random centres left gaps)."""
    n = int(kids.sum())
    u = torch.quasirandom.SobolEngine(3, scramble=True, seed=seed).draw(int(kids.max()) if n else 0, dtype=torch.float64)
    first = torch.repeat_interleave(torch.cumsum(kids, 0) - kids, kids).cpu()
    rank = torch.arange(n) - first  # the child's index within its parent
    u = u[rank].clamp(1e-6, 1 - 1e-6)
    return (math.sqrt(2.0) * torch.erfinv(2.0 * u - 1.0)).clamp(-CLAMP_SIGMA, CLAMP_SIGMA)


def _shared_opacity(logits: torch.Tensor) -> torch.Tensor:
    """Each point of a parent is covered by about OVERLAP children: their opacity o' = 1 - (1 - o)^(1/OVERLAP)
    composites to the parent's o there, so a semi-transparent splat does not turn opaque."""
    o = torch.sigmoid(logits.double()).clamp(1e-6, 1 - 1e-6)
    o2 = (1.0 - (1.0 - o) ** (1.0 / OVERLAP)).clamp(1e-6, 1 - 1e-6)
    return torch.logit(o2).to(logits.dtype)


def _children(g: Gaussians, idx: torch.Tensor, kids: torch.Tensor, shrink: torch.Tensor, seed: int) -> Gaussians:
    """``kids[i]`` children of parent ``idx[i]``: scales x ``shrink[i]``, centres drawn from N(mu, (1 - shrink²) Σ)
    so that the children's mixture keeps the parent's mean and covariance."""
    parent = torch.repeat_interleave(idx, kids)  # [M]
    f = torch.repeat_interleave(shrink, kids).to(g.dtype)  # [M]
    s = g.log_scales[parent].exp()  # [M, 3]
    z = _stratified_normal(kids, seed).to(device=g.device, dtype=g.dtype)  # [M, 3]
    R = quat_to_rotmat(g.quats[parent])  # [M, 3, 3]
    spread = s * torch.sqrt((1.0 - f * f).clamp_min(0.0))[:, None]
    means = g.means[parent] + (R @ (z * spread).unsqueeze(-1)).squeeze(-1)
    return Gaussians(means=means, quats=g.quats[parent], log_scales=g.log_scales[parent] + torch.log(f)[:, None],
                     opacity_logits=_shared_opacity(g.opacity_logits[parent]), sh=g.sh[parent])


@torch.no_grad()
def refine_to_radius(g: Gaussians, cams, radius: float, budget: int, *, passes: int = 3, background=None,
                     seed: int = 0) -> tuple[Gaussians, dict]:
    """``g`` with its splats wider than ``radius`` pixels split into children of that size, at most ``budget``
    Gaussians in all. Returns (Gaussians, counts: refined parents, children, pruned, passes run)."""
    info = {"refined": 0, "children": 0, "pruned": 0, "passes": 0, "radius_px": float(radius)}
    for _ in range(passes):
        r, con = view_footprints(g, cams, background)
        big = (r > radius) & (con > NEGLIGIBLE_PX)
        if not bool(big.any()):
            break
        shrink = (radius / r.clamp_min(1e-6)).clamp(max=1.0)
        kids = torch.ceil(OVERLAP / shrink**2).clamp(2, MAX_CHILDREN).to(torch.int64)
        shrink = torch.maximum(shrink, torch.sqrt(OVERLAP / kids.float()))  # capped: as small as the cap allows
        cost = torch.where(big, kids - 1, torch.zeros_like(kids))
        # priority: the pixels a splat covers too coarsely
        prio = torch.where(big, con * (1.0 - shrink.double()), torch.full_like(con, -1.0))
        order = torch.argsort(prio, descending=True)[: int(big.sum())]
        spare = (con < NEGLIGIBLE_PX) & ~big  # splats that may go to make room, the least seen first
        n_spare = int(spare.sum())
        room_max = budget - g.num + n_spare
        if room_max <= 0:
            break
        chosen = order[torch.cumsum(cost[order], 0) <= room_max]
        if chosen.numel() == 0:
            break
        need = int(cost[chosen].sum()) - (budget - g.num)
        keep = torch.ones(g.num, dtype=torch.bool, device=g.device)
        if need > 0:
            drop = torch.topk(torch.where(spare, -con, torch.full_like(con, -math.inf)), need).indices
            keep[drop] = False
            info["pruned"] += need
        kids_g = _children(g, chosen, kids[chosen], shrink[chosen], seed + info["passes"])
        keep[chosen] = False  # parents are replaced by their children
        g = Gaussians(**{f: torch.cat([getattr(g, f)[keep], getattr(kids_g, f)]) for f in Gaussians.FIELDS})
        info["refined"] += int(chosen.numel())
        info["children"] += kids_g.num
        info["passes"] += 1
    return g, info


__all__ = ["refine_to_radius", "view_footprints", "OVERLAP", "MAX_CHILDREN", "NEGLIGIBLE_PX"]
