"""Adaptive density control (3DGS): clone / split / prune, opacity reset, a hard Gaussian budget, and
pruning of Gaussians that contribute to no training view. One component, used by reconstruction and by
the stylization loop::

    dc = DensityControl(DensityConfig(...), num=params.num, device=params.device)
    out = render(params.gaussians(), cam, return_weights=dc.wants_weights_at(step))
    loss.backward()
    dc.accumulate(out, cam.width, cam.height)        # on-device, no host sync
    opt.step()
    if dc.is_densify_step(step): dc.densify_and_prune(opt, extent, step)   # syncs once
    if dc.is_reset_step(step): dc.reset_opacity(opt)

Gradient units. graphdeco's rasterizer differentiates with respect to the NDC mean: its screen-space
gradient is ``dL/dpixel × (0.5·W, 0.5·H)``; gsplat rescales its pixel gradients the same way. The
renderer here gives ``dL/dpixel`` in ``RenderOutput.means2d.grad``, so we multiply x by W/2 and y by H/2
before taking the norm: the 3DGS threshold 2e-4 then means the same thing it does there.

Decisions beyond 3DGS (documented here, tested in tests/test_train_density.py):
- Layout after ``densify_and_prune``: the surviving originals in their order, then the clones, then the
  split children (first children of all split parents, then the second ones) — graphdeco's layout.
- Split children are sampled from N(μ, Σ) truncated to ±3σ per axis (so a child is always inside its
  parent's 3σ box); scale / (0.8·2) = /1.6; other attributes copied. Clones copy everything.
- ``split_mode="moments"`` (the stylization's choice): two children at μ ± 0.6·σ_max·e_max along the parent's
  longest axis, that axis's scale × 0.8 (0.6² + 0.8² = 1: the pair keeps the parent's mean and covariance),
  the other axes unchanged. 3DGS's children cover 2/1.6² = 78% of the parent's footprint at random offsets
  and rely on later fitting to close the gaps; in a stylization the scales are anchored and the phases short,
  so the gaps stayed (the demo at 2x: 11-13% of covered pixels under alpha 0.9, 1% without densification).
- Pruning (low opacity, too large on screen or in the world, no contribution) is decided on the
  Gaussians present before densification; a Gaussian that is pruned is not densified; new Gaussians are
  not pruned in the step that creates them.
- Budget: the count after a densify step never exceeds ``max_gaussians``. When the candidates do not fit,
  those with the largest mean gradient are densified first. If the survivors alone exceed the budget
  (e.g. a lowered budget), the least opaque are pruned.
- No-contribution pruning: Σ αT per Gaussian (``RenderOutput.weights``) summed since the Gaussian was
  born or last checked; once it has been rendered over ``contribution_window`` views (a training epoch)
  and the sum is below ``min_contribution`` (pixel·alpha units) it is pruned. Weights are only asked for
  in the ``contribution_window`` steps before each densify step (``wants_weights_at``), so a full epoch
  (one random view per step, without replacement) is seen right before each check.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .optim import FIELDS, GaussianOptimizer, quat_to_rotmat


@dataclass
class DensityConfig:
    grad_threshold: float = 2e-4  # mean NDC-space screen gradient norm that triggers clone/split (3DGS)
    percent_dense: float = 0.01  # clone when max scale <= this × extent, else split (3DGS)
    min_opacity: float = 0.005  # prune below this opacity (3DGS)
    max_screen_size: float = 20.0  # prune when max 2D radius exceeded this many pixels (after the 1st reset)
    max_world_size: float = 0.1  # prune when max scale > this × extent (with the screen-size rule)
    split_children: int = 2  # children per split Gaussian (3DGS: 2, scale / (0.8·2))
    split_mode: str = "3dgs"  # "3dgs": children sampled in the parent, scales / 1.6; "moments": see below
    interval: int = 100  # densify every this many steps
    start: int = 500  # first densify step
    until: int = 15000  # no densification at or after this step
    opacity_reset_interval: int = 3000  # reset opacities to <= reset_opacity every this many steps (0 = off)
    reset_opacity: float = 0.01  # the opacity ceiling after a reset (3DGS)
    max_gaussians: int = 1_000_000  # hard budget
    prune_unseen: bool = True  # prune Gaussians contributing to no training view
    min_contribution: float = 0.5  # Σ αT over an epoch (pixel units) under which a Gaussian counts as unseen
    contribution_window: int = 0  # views per check window (0: set by the caller to the training-view count)


class DensityControl:
    """Per-Gaussian accumulators (all on the device) and the densify / prune / reset operations."""

    def __init__(self, config: DensityConfig | None = None, num: int = 0, device="cpu", dtype=torch.float32):
        self.config = config or DensityConfig()
        self.device, self.dtype = torch.device(device), dtype
        self.reset_stats(num)
        self.contrib = torch.zeros(num, dtype=dtype, device=self.device)  # Σ αT since birth / last check
        self.contrib_views = torch.zeros(num, dtype=torch.int32, device=self.device)
        self.generator = None  # torch.Generator for split sampling (None: the global RNG)
        # the caller's per-Gaussian tensors (e.g. the stylization's regularizer anchors): every keep / append
        # applies to them as to the parameters, Adam's moments and the statistics; a new row takes the new
        # Gaussian's value of the parameter field of the same name (zeros when the name is not a field)
        self.tracked: dict[str, torch.Tensor] = {}

    # accumulators ------------------------------------------------------------------------------------
    def reset_stats(self, num: int) -> None:
        self.grad_accum = torch.zeros(num, dtype=self.dtype, device=self.device)
        self.denom = torch.zeros(num, dtype=self.dtype, device=self.device)
        self.max_radii = torch.zeros(num, dtype=self.dtype, device=self.device)

    @property
    def num(self) -> int:
        return int(self.grad_accum.shape[0])

    def wants_weights_at(self, step: int) -> bool:
        """Whether the render of ``step`` (1-based) should return Σ αT: only during the last
        ``contribution_window`` steps before each densify step (the weights cost an atomic add per
        contribution, so they are not gathered when no check will use them)."""
        c = self.config
        if not c.prune_unseen or not self.accumulating(step):
            return False
        if c.contribution_window <= 0 or c.interval <= 0 or c.contribution_window >= c.interval:
            return True
        nxt = -(-step // c.interval) * c.interval  # the next densify step at or after this one
        return nxt >= c.start and nxt - step < c.contribution_window

    def accumulate(self, out, width: int, height: int) -> None:
        """Add one view's statistics (call after backward). Vectorized, no host sync."""
        vis = out.radii > 0
        visf = vis.to(self.dtype)
        with torch.no_grad():
            if out.means2d.grad is not None:
                g = out.means2d.grad.detach().to(self.dtype)
                gn = torch.hypot(g[:, 0] * (0.5 * width), g[:, 1] * (0.5 * height))
                self.grad_accum += gn * visf
                self.denom += visf
            self.max_radii = torch.maximum(self.max_radii, out.radii.to(self.dtype) * visf)
            if out.weights is not None and out.weights.numel() == self.num:
                self.contrib += out.weights.detach().to(self.dtype)
                self.contrib_views += 1  # views whose weights were seen

    def mean_grads(self) -> torch.Tensor:
        return torch.where(self.denom > 0, self.grad_accum / self.denom.clamp_min(1), torch.zeros_like(self.denom))

    # schedule ------------------------------------------------------------------------------------------
    def is_densify_step(self, step: int) -> bool:
        """``step`` is 1-based (the number of optimizer steps taken), as graphdeco's ``iteration``."""
        c = self.config
        return c.interval > 0 and c.start <= step < c.until and step % c.interval == 0

    def is_reset_step(self, step: int) -> bool:
        c = self.config
        return c.opacity_reset_interval > 0 and step < c.until and step % c.opacity_reset_interval == 0

    def accumulating(self, step: int) -> bool:
        return step < self.config.until

    # operations -----------------------------------------------------------------------------------------
    @torch.no_grad()
    def prune_mask(self, opt: GaussianOptimizer, extent: float, step: int) -> torch.Tensor:
        """Bool [N]: Gaussians removed at this densify step (before densification)."""
        c, p = self.config, opt.params
        opac = torch.sigmoid(p.opacity_logits.detach())
        prune = opac < c.min_opacity
        if c.opacity_reset_interval <= 0 or step > c.opacity_reset_interval:  # graphdeco: size rules after 1st reset
            prune |= self.max_radii > c.max_screen_size
            prune |= p.log_scales.detach().exp().amax(dim=1) > c.max_world_size * extent
        if c.prune_unseen:
            window = c.contribution_window
            done = self.contrib_views >= window if window > 0 else torch.zeros_like(prune)
            prune |= done & (self.contrib < c.min_contribution)
        return prune

    @torch.no_grad()
    def densify_and_prune(self, opt: GaussianOptimizer, extent: float, step: int) -> dict:
        """Clone / split / prune once; resets the gradient statistics. Returns counts (host ints)."""
        c, p = self.config, opt.params
        n = p.num
        prune = self.prune_mask(opt, extent, step)
        grads = self.mean_grads()
        max_scale = p.log_scales.detach().exp().amax(dim=1)
        cand = (grads >= c.grad_threshold) & ~prune
        # budget: each clone adds 1, each split adds split_children - 1
        n_keep = n - int(prune.sum())
        over = max(0, n_keep - c.max_gaussians)
        if over:  # survivors alone exceed the budget: drop the least opaque survivors
            opac = torch.where(prune, torch.full_like(grads, -1.0), torch.sigmoid(p.opacity_logits.detach()))
            cut = torch.topk(opac, over, largest=False).indices  # pruned ones (-1) are not in this set
            prune[cut] = True
            cand &= ~prune
            n_keep -= over
        room = c.max_gaussians - n_keep
        is_clone = max_scale <= c.percent_dense * extent
        cost = torch.where(is_clone, 1, max(c.split_children - 1, 0)).to(torch.int64)
        n_cand = int(cand.sum())
        if n_cand and int((cost * cand).sum()) > room:
            order = torch.argsort(torch.where(cand, grads, torch.full_like(grads, -1.0)), descending=True)[:n_cand]
            fits = torch.cumsum(cost[order], 0) <= room
            cand = torch.zeros_like(cand)
            cand[order[fits]] = True
        clone_idx = torch.nonzero(cand & is_clone).squeeze(1)
        split_idx = torch.nonzero(cand & ~is_clone).squeeze(1)
        appended = self._new_gaussians(p, clone_idx, split_idx)
        keep = ~prune
        keep[split_idx] = False  # split parents are replaced by their children
        opt.rebuild(keep, appended)
        n_new = appended["means"].shape[0]
        self._after_rebuild(keep, n_new)
        for name, t in list(self.tracked.items()):
            new = appended[name].to(t) if name in appended else t.new_zeros((n_new, *t.shape[1:]))
            self.tracked[name] = torch.cat([t[keep], new]).contiguous()
        return {"cloned": int(clone_idx.numel()), "split": int(split_idx.numel()),
                "pruned": int(prune.sum()), "num": opt.params.num}

    def _new_gaussians(self, p, clone_idx, split_idx) -> dict:
        k = self.config.split_children
        t = {f: getattr(p, f).detach() for f in FIELDS}
        parts = {f: [t[f][clone_idx]] for f in FIELDS}
        if split_idx.numel() and self.config.split_mode == "moments":
            mu, q, ls = t["means"][split_idx], t["quats"][split_idx], t["log_scales"][split_idx]
            j = ls.argmax(dim=1)
            axis = torch.gather(quat_to_rotmat(q), 2, j.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(-1)  # [M,3]
            off = 0.6 * ls.gather(1, j[:, None]).exp() * axis
            ls2 = ls.scatter_add(1, j[:, None], torch.full_like(ls[:, :1], math.log(0.8)))
            parts["means"] += [mu + off, mu - off]
            parts["log_scales"] += [ls2, ls2]
            for f in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
                parts[f] += [t[f][split_idx]] * 2
        elif split_idx.numel():
            mu, q, ls = t["means"][split_idx], t["quats"][split_idx], t["log_scales"][split_idx]
            s = ls.exp().repeat(k, 1)
            z = torch.randn(s.shape, dtype=s.dtype, device=s.device, generator=self.generator).clamp_(-3.0, 3.0)
            R = quat_to_rotmat(q).repeat(k, 1, 1)
            parts["means"].append(mu.repeat(k, 1) + (R @ (z * s).unsqueeze(-1)).squeeze(-1))
            parts["log_scales"].append(ls.repeat(k, 1) - math.log(0.8 * k))
            for f in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
                x = t[f][split_idx]
                parts[f].append(x.repeat(k, *([1] * (x.dim() - 1))))
        return {f: torch.cat(v, dim=0) for f, v in parts.items()}

    def _after_rebuild(self, keep, n_new: int) -> None:
        n_total = int(keep.sum()) + n_new
        self.reset_stats(n_total)
        z = torch.zeros(n_new, dtype=self.contrib.dtype, device=self.device)
        self.contrib = torch.cat([self.contrib[keep], z])
        self.contrib_views = torch.cat([self.contrib_views[keep], z.to(torch.int32)])
        w = self.config.contribution_window
        if w > 0:  # a full window has been checked: start the next one
            done = self.contrib_views >= w
            self.contrib = torch.where(done, torch.zeros_like(self.contrib), self.contrib)
            self.contrib_views = torch.where(done, torch.zeros_like(self.contrib_views), self.contrib_views)

    @torch.no_grad()
    def reset_opacity(self, opt: GaussianOptimizer) -> None:
        """opacity ← min(opacity, reset_opacity), Adam moments of the opacities zeroed (graphdeco)."""
        p = opt.params
        cap = torch.logit(torch.tensor(self.config.reset_opacity, dtype=p.opacity_logits.dtype))
        new = torch.minimum(p.opacity_logits.detach(), cap.to(p.device))
        opt.replace("opacity_logits", new, reset_state=torch.ones(p.num, dtype=torch.bool, device=p.device))

    # checkpoints ------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        sd = {k: getattr(self, k).detach().clone()
              for k in ("grad_accum", "denom", "max_radii", "contrib", "contrib_views")}
        sd["tracked"] = {k: v.detach().clone() for k, v in self.tracked.items()}
        return sd

    def load_state_dict(self, sd: dict) -> None:
        for k, v in sd.items():
            if k == "tracked":
                self.tracked = {n: t.to(self.device) for n, t in v.items()}
            else:
                setattr(self, k, v.to(self.device))


__all__ = ["DensityConfig", "DensityControl"]
