"""Adaptive density control (3DGS): clone / split / prune, opacity reset, a hard Gaussian budget, and
pruning of Gaussians that contribute to no training view. One component for every phase that runs it; it
owns its schedule and every per-Gaussian tensor that must follow a keep / append (as gsplat's strategies)::

    dc = DensityControl(cfg.density, num=params.num, device=dev, extent=extent, window=2 * n_views - 1, seed=s)
    dc.track("opacity_logits", anchor)               # a caller's per-Gaussian tensor (kept aligned from now on)
    out = render(g, cam, return_weights=dc.wants_weights(s))
    loss.backward()
    dc.accumulate(out, cam.width, cam.height)        # on-device, no host sync
    opt.step()
    dc.step(opt, s, n)                               # densify / prune / reset when the schedule says (syncs then)

``s`` is the 1-based step within the phase and ``n`` the phase's length: no structural change at a phase's
last step, so what a phase hands on (the exported model, the next phase) is what it trained.

Gradient units. graphdeco's rasterizer differentiates with respect to the NDC mean: its screen-space
gradient is ``dL/dpixel × (0.5·W, 0.5·H)``; gsplat rescales its pixel gradients the same way. The
renderer here gives ``dL/dpixel`` in ``RenderOutput.means2d.grad``, so we multiply x by W/2 and y by H/2
before taking the norm: the 3DGS threshold 2e-4 then means the same thing it does there. A step that
averages the loss over k views scales each view's gradient by 1/k; ``accumulate(..., grad_scale=k)``
undoes that (gsplat multiplies by its camera count the same way), so the threshold is per view.

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
  not pruned in the step that creates them. The size rules apply after the first opacity reset (3DGS;
  never without resets), always (``size_rules: always``, ABC-GS's pre-process), or never prune but split
  (``size_rules: split``, the stylization: a fitted scene's large splats are refined, not deleted). The
  screen rule was set for ~1000-pixel images: larger images scale it, so a sharper view of the same scene
  does not prune every splat as "too big on screen" (seen in the stability suite).
- Budget: the count after a densify step never exceeds the budget (``max_gaussians``, or ``budget_factor``
  × the starting count when it is 0). When the candidates do not fit, those with the largest mean gradient
  are densified first. If the survivors alone exceed the budget (e.g. a lowered budget), the least opaque
  are pruned.
- No-contribution pruning: Σ αT per Gaussian (``RenderOutput.weights``) summed since the Gaussian was
  born or last checked; once it has been rendered over ``window`` views (2 epochs - 1: any that many
  consecutive views hold a whole epoch) and the sum is below ``min_contribution`` (pixel·alpha units) it is
  pruned. Weights are asked for (``wants_weights``) only in the steps that hold the last window of views
  before each densify step; renders that carry weights anyway (the flow terms') are counted too.
- Several ranks (torch.distributed): every rank accumulates its own views; at a densify step the
  statistics are summed (screen radii: max) over the ranks first, and the split RNG is seeded identically,
  so every rank makes the same decision. The contribution sums that carry over to the next window stay
  on the main rank only (the others restart from zero), so the next sum counts each view once.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .optim import FIELDS, GaussianOptimizer, quat_to_rotmat

SPLIT_CHILDREN = 2  # children per split Gaussian (3DGS)
SCREEN_SIZE_REFERENCE = 1000  # pixels: the image size 3DGS's max_screen_size was chosen for


@dataclass
class DensityConfig:
    """The ``density`` section of every config (class defaults: graphdeco's 3DGS; each command sets its own)."""

    phases: list[str] = field(default_factory=lambda: ["fit"])  # the phases that run density control
    interval: int = 100  # densify every this many steps of a phase (3DGS)
    start: int = 500  # first densify step of a phase (3DGS)
    until: int = 15000  # no densification from this step of a phase on (3DGS); 0: no end
    grad_threshold: float = 2e-4  # mean NDC screen-gradient norm for clone/split (3DGS)
    percent_dense: float = 0.01  # clone when the max scale is below this fraction of the extent, split above (3DGS)
    split_mode: str = "3dgs"  # 3dgs: 2 children sampled in the parent, scales / 1.6; moments: keep mean and covariance
    min_opacity: float = 0.005  # prune below this opacity (3DGS)
    max_screen_size: float = 20.0  # prune above this 2D radius in pixels (3DGS; scaled up for images over 1000 px)
    max_world_size: float = 0.1  # prune above this fraction of the extent (3DGS); 0: off
    size_rules: str = "after_reset"  # the two size rules: prune after_reset (3DGS; never without resets) | prune always | split (first in the budget, never prune)
    opacity_reset_interval: int = 3000  # cap the opacities at reset_opacity every this many steps (3DGS); 0: never
    reset_opacity: float = 0.01  # the opacity ceiling of a reset (3DGS)
    max_gaussians: int = 1_000_000  # hard budget; 0: budget_factor x the starting count
    budget_factor: float = 1.2  # the budget relative to the starting count when max_gaussians is 0
    use_budget: bool = True  # cap the Gaussian count at the budget (ABC-GS has no cap)
    prune_unseen: bool = True  # prune Gaussians that contribute to no training view over an epoch
    min_contribution: float = 0.5  # Σ αT (pixels) over the check window under which a Gaussian is unseen

    RULES = {"interval": (">=", 1), "start": (">=", 0), "until": (">=", 0), "grad_threshold": (">=", 0),
             "percent_dense": (">=", 0), "split_mode": ("of", "moments", "3dgs"), "min_opacity": (">=", 0),
             "max_screen_size": (">=", 0), "max_world_size": (">=", 0), "size_rules": ("of", "after_reset", "always", "split"),
             "opacity_reset_interval": (">=", 0), "reset_opacity": ("in", 0, 1), "max_gaussians": (">=", 0),
             "budget_factor": (">=", 1), "min_contribution": (">=", 0)}

    def budget(self, num: int) -> int | None:
        """The Gaussian budget of a run that starts with ``num`` Gaussians (None: no cap)."""
        if not self.use_budget:
            return None
        # floor: 1.2 x the input is a ceiling (ceil gave one over it); the epsilon keeps 1.2 x 5 = 6 from 5.999...
        return self.max_gaussians or max(num, int(math.floor(self.budget_factor * num + 1e-6)))


# old flat config names of the ``density`` section shared by both commands (they still load, with a note)
DENSITY_RENAMED = {"densify_interval": "density.interval", "densify_grad_threshold": "density.grad_threshold",
                   **{k: f"density.{k}" for k in ("percent_dense", "split_mode", "min_opacity", "max_screen_size",
                                                  "max_world_size", "prune_unseen")}}


class DensityStrategy:
    """What the training loop asks of density control, and nothing more (as gsplat's strategies): a new rule set
    (MCMC relocation, a fixed budget, none) is a subclass that overrides what it needs, not a fork of the loop.

    This base class is the strategy that never changes the Gaussians: it accumulates nothing and keeps the
    caller's per-Gaussian tensors (``track``) as they are. The loop calls, per phase that runs density control:
    ``begin_phase(n)`` at the phase's start; per step ``accumulating(s)`` and ``wants_weights(s)`` before the
    render, ``accumulate(out, W, H, grad_scale)`` after backward, ``acts_at(s, n)`` and ``step(opt, s, n, tag)``
    after the optimizer step; ``state_dict`` / ``load_state_dict`` for checkpoints; ``events`` for the metrics."""

    budget = None  # the Gaussian budget (None: no cap)

    def __init__(self):
        self.views_per_step = 1  # set by the loop: views accumulated per step over all ranks
        self.events: list[dict] = []  # one dict per structural change (counts, step, phase)
        self.tracked: dict[str, torch.Tensor] = {}

    def track(self, name: str, tensor: torch.Tensor) -> None:
        """Keep ``tensor`` [N, ...] aligned with the Gaussians through every structural change (unless already)."""
        self.tracked.setdefault(name, tensor)

    def begin_phase(self, num: int) -> None:
        pass

    def accumulating(self, s: int) -> bool:
        return False

    def wants_weights(self, s: int) -> bool:
        return False

    def accumulate(self, out, width: int, height: int, grad_scale: float = 1.0) -> None:
        pass

    def acts_at(self, s: int, n: int | None = None) -> bool:
        return False

    def step(self, opt: GaussianOptimizer, s: int, n: int | None = None, tag: dict | None = None) -> dict | None:
        return None

    def state_dict(self, global_stats: bool = False) -> dict:
        return {"tracked": {k: v.detach().clone() for k, v in self.tracked.items()},
                "events": [dict(e) for e in self.events]}

    def load_state_dict(self, sd: dict, from_checkpoint: bool = False) -> None:
        self.tracked = {n: t for n, t in sd.get("tracked", {}).items()}
        self.events = [dict(e) for e in sd.get("events", [])]


class DensityControl(DensityStrategy):
    """Per-Gaussian accumulators (all on the device), the schedule, and the densify / prune / reset operations.

    extent: the scene extent (clone/split and world-size rules); window: views per no-contribution check (set
    by the caller to 2 × its views − 1; 0: every check); image_size: the longest image side (screen rule);
    seed: the split RNG (identical on every rank); dist: a ``Dist`` (statistics summed over ranks); start_num: the
    count the budget refers to (default ``num``)."""

    def __init__(self, config: DensityConfig | None = None, num: int = 0, device="cpu", dtype=torch.float32, *,
                 extent: float = 1.0, window: int = 0, image_size: int = 0, seed: int | None = None, dist=None,
                 start_num: int | None = None):
        super().__init__()  # views_per_step, events, tracked (every keep / append applies to the caller's tracked
        # tensors, e.g. the stylization's regularizer anchors, as to the parameters; a new row takes the new
        # Gaussian's value of the parameter field of the same name, zeros when the name is not a field)
        self.config = config or DensityConfig()
        self.device, self.dtype = torch.device(device), dtype
        self.extent, self.window, self.dist = float(extent), int(window), dist
        self.start_num = num if start_num is None else int(start_num)  # the budget's reference: the count the
        # run started with (``num`` is the count now, after a refinement)
        self.screen_limit = self.config.max_screen_size * max(1.0, image_size / SCREEN_SIZE_REFERENCE)
        self.reset_stats(num)
        self.contrib = torch.zeros(num, dtype=dtype, device=self.device)  # Σ αT since birth / last check
        self.contrib_views = torch.zeros(num, dtype=torch.int32, device=self.device)
        self.generator = None if seed is None else torch.Generator(device=self.device).manual_seed(seed)

    @property
    def budget(self) -> int | None:
        return self.config.budget(self.start_num)

    # accumulators ------------------------------------------------------------------------------------
    def reset_stats(self, num: int) -> None:
        self.grad_accum = torch.zeros(num, dtype=self.dtype, device=self.device)
        self.denom = torch.zeros(num, dtype=self.dtype, device=self.device)
        self.max_radii = torch.zeros(num, dtype=self.dtype, device=self.device)

    def begin_phase(self, num: int) -> None:
        """A phase starts: gradient statistics do not carry over from the previous one (contributions do)."""
        self.reset_stats(num)

    @property
    def num(self) -> int:
        return int(self.grad_accum.shape[0])

    def accumulate(self, out, width: int, height: int, grad_scale: float = 1.0) -> None:
        """Add one view's statistics (call after backward). Vectorized, no host sync."""
        vis = out.radii > 0
        visf = vis.to(self.dtype)
        with torch.no_grad():
            if out.means2d.grad is not None:
                g = out.means2d.grad.detach().to(self.dtype)
                sx, sy = 0.5 * width * grad_scale, 0.5 * height * grad_scale
                gn = torch.hypot(g[:, 0] * sx, g[:, 1] * sy)
                self.grad_accum += gn * visf
                self.denom += visf
            self.max_radii = torch.maximum(self.max_radii, out.radii.to(self.dtype) * visf)
            if out.weights is not None and out.weights.numel() == self.num:
                self.contrib += out.weights.detach().to(self.dtype)
                self.contrib_views += 1  # views whose weights were seen

    def mean_grads(self) -> torch.Tensor:
        return torch.where(self.denom > 0, self.grad_accum / self.denom.clamp_min(1), torch.zeros_like(self.denom))

    # schedule (s: 1-based step within the phase, n: the phase's length) ----------------------------------
    def accumulating(self, s: int) -> bool:
        return self.config.until <= 0 or s < self.config.until

    def is_densify_step(self, s: int, n: int | None = None) -> bool:
        c = self.config
        return (c.interval > 0 and c.start <= s and self.accumulating(s) and s % c.interval == 0
                and (n is None or s < n))

    def is_reset_step(self, s: int, n: int | None = None) -> bool:
        c = self.config
        return (c.opacity_reset_interval > 0 and self.accumulating(s) and s % c.opacity_reset_interval == 0
                and (n is None or s < n))

    def acts_at(self, s: int, n: int | None = None) -> bool:
        """Whether ``step(opt, s, n)`` densifies or resets the opacities (the loop times those steps)."""
        return self.is_densify_step(s, n) or self.is_reset_step(s, n)

    def wants_weights(self, s: int) -> bool:
        """Whether the render of step ``s`` should return Σ αT: only in the steps that hold the last window of
        views before each densify step (the weights cost an atomic add per contribution)."""
        c = self.config
        if not c.prune_unseen or not self.accumulating(s):
            return False
        steps = -(-self.window // max(1, self.views_per_step))
        if steps <= 0 or c.interval <= 0 or steps >= c.interval:
            return True
        nxt = -(-s // c.interval) * c.interval  # the next densify step at or after this one
        return nxt >= c.start and nxt - s < steps

    @torch.no_grad()
    def step(self, opt: GaussianOptimizer, s: int, n: int | None = None, tag: dict | None = None) -> dict | None:
        """After the optimizer step ``s`` of a phase of ``n``: densify / prune and reset the opacities when the
        schedule says so. Returns the densify event (counts, and ``tag``) or None."""
        ev = None
        if self.is_densify_step(s, n):
            self._reduce_stats()
            ev = dict(self.densify_and_prune(opt, self.extent, s), **(tag or {}))
            self.events.append(ev)
        if self.is_reset_step(s, n):
            self.reset_opacity(opt)
        return ev

    def _reduce_stats(self) -> None:
        d = self.dist
        if d is not None and d.world > 1:
            d.all_reduce_sum_([self.grad_accum, self.denom, self.contrib, self.contrib_views])
            d.all_reduce_max_([self.max_radii])

    # operations -----------------------------------------------------------------------------------------
    @torch.no_grad()
    def prune_mask(self, opt: GaussianOptimizer, extent: float, step: int) -> torch.Tensor:
        """Bool [N]: Gaussians removed at this densify step (before densification)."""
        c, p = self.config, opt.params
        opac = torch.sigmoid(p.opacity_logits.detach())
        prune = opac < c.min_opacity
        reset = c.opacity_reset_interval
        if c.size_rules == "always" or (reset > 0 and step > reset):  # graphdeco: after the first reset
            prune |= self.too_big(p, extent)
        if c.prune_unseen:
            done = self.contrib_views >= self.window if self.window > 0 else torch.zeros_like(prune)
            prune |= done & (self.contrib < c.min_contribution)
        return prune

    def too_big(self, p, extent: float) -> torch.Tensor:
        """Bool [N]: the two 3DGS size rules (too large on screen in a view of the window, or in the world)."""
        big = self.max_radii > self.screen_limit
        if self.config.max_world_size > 0:
            big |= p.log_scales.detach().exp().amax(dim=1) > self.config.max_world_size * extent
        return big

    @torch.no_grad()
    def densify_and_prune(self, opt: GaussianOptimizer, extent: float, step: int) -> dict:
        """Clone / split / prune once; resets the gradient statistics. Returns counts (host ints)."""
        c, p = self.config, opt.params
        n = p.num
        prune = self.prune_mask(opt, extent, step)
        grads = self.mean_grads()
        max_scale = p.log_scales.detach().exp().amax(dim=1)
        cand = (grads >= c.grad_threshold) & ~prune
        forced = torch.zeros_like(cand)
        if c.size_rules == "split":  # too-large splats are split (coverage kept), never deleted; they go first
            forced = self.too_big(p, extent) & ~prune
            cand |= forced
            grads = torch.where(forced, torch.full_like(grads, float("inf")), grads)
        budget = self.budget if self.budget is not None else 1 << 62
        # budget: each clone adds 1, each split adds SPLIT_CHILDREN - 1
        n_keep = n - int(prune.sum())
        over = max(0, n_keep - budget)
        if over:  # survivors alone exceed the budget: drop the least opaque survivors
            opac = torch.where(prune, torch.full_like(grads, -1.0), torch.sigmoid(p.opacity_logits.detach()))
            cut = torch.topk(opac, over, largest=False).indices  # pruned ones (-1) are not in this set
            prune[cut] = True
            cand &= ~prune
            n_keep -= over
        room = budget - n_keep
        is_clone = (max_scale <= c.percent_dense * extent) & ~forced
        cost = torch.where(is_clone, 1, SPLIT_CHILDREN - 1).to(torch.int64)
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
        opt.rebuild(keep, appended)  # parameters and Adam's moments
        self._apply(keep, appended)  # statistics and tracked tensors
        return {"cloned": int(clone_idx.numel()), "split": int(split_idx.numel()),
                "pruned": int(prune.sum()), "num": opt.params.num}

    def _new_gaussians(self, p, clone_idx, split_idx) -> dict:
        k = SPLIT_CHILDREN
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

    def _apply(self, keep: torch.Tensor, appended: dict) -> None:
        """The same keep / append on every per-Gaussian tensor density control holds."""
        n_new = appended["means"].shape[0]
        self.reset_stats(int(keep.sum()) + n_new)
        z = torch.zeros(n_new, dtype=self.contrib.dtype, device=self.device)
        self.contrib = torch.cat([self.contrib[keep], z])
        self.contrib_views = torch.cat([self.contrib_views[keep], z.to(torch.int32)])
        if self.window > 0:  # a full window has been checked: start the next one
            done = self.contrib_views >= self.window
            self.contrib = torch.where(done, torch.zeros_like(self.contrib), self.contrib)
            self.contrib_views = torch.where(done, torch.zeros_like(self.contrib_views), self.contrib_views)
        if self.dist is not None and self.dist.world > 1 and not self.dist.is_main:
            self.contrib.zero_()  # the carried (summed) part lives on the main rank only
            self.contrib_views.zero_()
        for name, t in list(self.tracked.items()):
            new = appended[name].to(t) if name in appended else t.new_zeros((n_new, *t.shape[1:]))
            self.tracked[name] = torch.cat([t[keep], new]).contiguous()

    @torch.no_grad()
    def reset_opacity(self, opt: GaussianOptimizer) -> None:
        """opacity ← min(opacity, reset_opacity), Adam moments of the opacities zeroed (graphdeco)."""
        p = opt.params
        cap = torch.logit(torch.tensor(self.config.reset_opacity, dtype=p.opacity_logits.dtype))
        new = torch.minimum(p.opacity_logits.detach(), cap.to(p.device))
        opt.replace("opacity_logits", new, reset_state=torch.ones(p.num, dtype=torch.bool, device=p.device))

    @torch.no_grad()
    def fit_budget(self, g):
        """``g`` within the budget from the start: its most opaque Gaussians when it has more."""
        if self.budget is None or g.num <= self.budget:
            return g
        keep = torch.topk(g.opacity_logits, self.budget).indices.sort().values
        return g.subset(keep)

    # state (checkpoint, last-good snapshot, resume) ----------------------------------------------------------
    STATS = ("grad_accum", "denom", "max_radii", "contrib", "contrib_views")

    def state_dict(self, global_stats: bool = False) -> dict:
        """Copies of everything that changes during a run. ``global_stats``: the statistics summed over the
        ranks (a collective: every rank calls it; for the checkpoint that one rank writes)."""
        sd = {k: getattr(self, k).detach().clone() for k in self.STATS}
        if global_stats and self.dist is not None and self.dist.world > 1:
            self.dist.all_reduce_sum_([sd[k] for k in ("grad_accum", "denom", "contrib", "contrib_views")])
            self.dist.all_reduce_max_([sd["max_radii"]])
        sd["tracked"] = {k: v.detach().clone() for k, v in self.tracked.items()}
        sd["rng"] = self.generator.get_state() if self.generator is not None else None
        sd["events"] = [dict(e) for e in self.events]
        sd["start_num"] = self.start_num  # the budget's reference (a resumed run starts from another count)
        return sd

    def load_state_dict(self, sd: dict, from_checkpoint: bool = False) -> None:
        """``from_checkpoint``: ``sd`` holds the statistics summed over the ranks, which only the main rank keeps."""
        for k in self.STATS:
            if k in sd:
                setattr(self, k, sd[k].to(self.device))
        self.tracked = {n: t.to(self.device) for n, t in sd.get("tracked", {}).items()}
        if sd.get("rng") is not None and self.generator is not None:
            self.generator.set_state(sd["rng"])
        self.events = [dict(e) for e in sd.get("events", [])]
        self.start_num = int(sd.get("start_num", self.start_num))
        if from_checkpoint and self.dist is not None and self.dist.world > 1 and not self.dist.is_main:
            for k in ("grad_accum", "denom", "contrib", "contrib_views"):
                getattr(self, k).zero_()


__all__ = ["DensityConfig", "DensityStrategy", "DensityControl", "DENSITY_RENAMED", "SPLIT_CHILDREN", "SCREEN_SIZE_REFERENCE"]
