"""Trainable Gaussian parameters, Adam with per-group learning rates (SPEC §3) and post-step hooks.

``GaussianParams`` holds the parameters as leaf tensors (``requires_grad=True``), with the SH split into
the DC band and the rest (they have different learning rates). ``GaussianOptimizer`` is one Adam
(``torch.optim.Adam``'s update, ``FunctionalAdam``; eps 1e-15) with one group per field, the exponential xyz decay, and hooks called
after every step. Density control adds and removes Gaussians through ``GaussianOptimizer.rebuild`` which
keeps Adam's ``exp_avg`` / ``exp_avg_sq`` aligned with the parameters (kept rows sliced, new rows zero).

Learning rates (3DGS defaults, SPEC §3): xyz 1.6e-4·extent decaying exponentially to 1.6e-6·extent,
SH DC 2.5e-3, SH rest 1.25e-4 (= DC/20), opacity 0.05, scale 5e-3, rotation 1e-3. Opacity: graphdeco's
original release (the one its paper numbers come from) and SPEC §3 use 0.05; their 2024 update lowered
it to 0.025 together with other changes. We use 0.05 for both reconstruction and stylization.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch.optim.adam import adam

from ..types import SH_C0, Gaussians, sh_coeffs

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


@dataclass
class LearningRates:
    """The ``lr`` section of every config: Adam's learning rate per parameter group (3DGS defaults)."""

    means: float = 1.6e-4  # xyz learning rate at the start, times the scene extent (3DGS)
    means_final: float = 1.6e-6  # xyz learning rate at the end of the exponential decay, times the extent (3DGS)
    means_steps: int = 30000  # steps of the xyz decay (then it stays at means_final); 0: the run's iterations
    sh_dc: float = 2.5e-3  # SH DC band (3DGS)
    sh_rest: float = 1.25e-4  # higher SH bands (3DGS: DC / 20)
    opacity: float = 0.05  # opacity logits (3DGS original release; its 2024 update uses 0.025)
    scales: float = 5e-3  # log scales (3DGS)
    quats: float = 1e-3  # rotations (3DGS)

    RULES = {"means": (">=", 0), "means_final": (">=", 0), "means_steps": (">=", 0), "sh_dc": (">=", 0),
             "sh_rest": (">=", 0), "opacity": (">=", 0), "scales": (">=", 0), "quats": (">=", 0)}

    def for_field(self, name: str, extent: float) -> float:
        return {"means": self.means * extent, "quats": self.quats, "log_scales": self.scales,
                "opacity_logits": self.opacity, "sh_dc": self.sh_dc, "sh_rest": self.sh_rest}[name]


# old flat config names of the ``lr`` section (they still load, with a note)
LR_RENAMED = {f"lr_{k}": f"lr.{k}" for k in ("means", "means_final", "means_steps", "sh_dc", "sh_rest", "opacity",
                                             "scales", "quats")}


def exp_decay(step: int, start: float, end: float, steps: int) -> float:
    """3DGS's log-linear interpolation from ``start`` (step 0) to ``end`` (step ``steps``), clamped."""
    if steps <= 0 or start <= 0 or end <= 0:
        return start
    t = min(max(step / steps, 0.0), 1.0)
    return math.exp((1 - t) * math.log(start) + t * math.log(end))


class GaussianParams:
    """The trainable tensors of a scene. ``sh_rest`` holds the coefficients of the **maximum** degree from
    the start (zeros above the active degree, which the renderer skips), as 3DGS does."""

    def __init__(self, g: Gaussians, max_sh_degree: int | None = None, frozen=()):
        max_sh_degree = g.sh_degree if max_sh_degree is None else int(max_sh_degree)
        g = g.with_sh_degree(max_sh_degree).detach()
        self.frozen = tuple(frozen)
        self.max_sh_degree = max_sh_degree
        tensors = {"means": g.means, "quats": g.quats, "log_scales": g.log_scales,
                   "opacity_logits": g.opacity_logits, "sh_dc": g.sh[:, :1], "sh_rest": g.sh[:, 1:]}
        for name, t in tensors.items():
            setattr(self, name, t.clone().contiguous().requires_grad_(name not in self.frozen))

    # views --------------------------------------------------------------------------------------
    def tensors(self) -> dict:
        return {f: getattr(self, f) for f in FIELDS}

    def gaussians(self) -> Gaussians:
        """A differentiable view (the SH bands concatenated)."""
        sh = self.sh_dc if self.sh_rest.shape[1] == 0 else torch.cat([self.sh_dc, self.sh_rest], dim=1)
        return Gaussians(self.means, self.quats, self.log_scales, self.opacity_logits, sh)

    def detached(self) -> Gaussians:
        return self.gaussians().clone()

    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self):
        return self.means.device

    def trainable(self) -> list[str]:
        return [f for f in FIELDS if f not in self.frozen]

    def set_trainable(self, fields) -> None:
        """Only ``fields`` get gradients from now on; the others keep their values (no gradient: Adam skips
        them, and the renderer does not compute one)."""
        for f in FIELDS:
            getattr(self, f).requires_grad_(f in fields and f not in self.frozen)

    def state_dict(self) -> dict:
        return {"tensors": {f: t.detach().clone() for f, t in self.tensors().items()},
                "frozen": list(self.frozen), "max_sh_degree": self.max_sh_degree}

    @staticmethod
    def from_state_dict(sd: dict, device=None) -> "GaussianParams":
        t = {k: v.to(device) if device is not None else v for k, v in sd["tensors"].items()}
        g = Gaussians(t["means"], t["quats"], t["log_scales"], t["opacity_logits"],
                      torch.cat([t["sh_dc"], t["sh_rest"]], dim=1))
        return GaussianParams(g, sd["max_sh_degree"], sd.get("frozen", ()))

    def all_finite(self) -> torch.Tensor:
        """A 0-dim bool tensor on the device (no host sync)."""
        ok = torch.ones((), dtype=torch.bool, device=self.device)
        for t in self.tensors().values():
            ok = ok & torch.isfinite(t).all()
        return ok


class FunctionalAdam:
    """``torch.optim.Adam``'s update through its functional form (``torch.optim.adam.adam``, fused on CUDA)
    without ``torch.optim.Optimizer``, whose constructor imports ``torch._dynamo``: 2.5-3.8 s of every run's
    setup (the largest part of a fern stylization's). The same arithmetic, the same state per parameter
    (``step``, ``exp_avg``, ``exp_avg_sq``), ``param_groups`` and ``defaults``; betas (0.9, 0.999), no weight
    decay, no amsgrad (what 3DGS uses)."""

    BETAS = (0.9, 0.999)

    def __init__(self, groups: list, lr: float, eps: float, fused: bool):
        self.defaults = {"lr": lr, "betas": self.BETAS, "eps": eps, "weight_decay": 0.0, "amsgrad": False,
                         "fused": bool(fused)}
        self.param_groups = [{"lr": lr, **g, "params": list(g["params"])} for g in groups]
        self.state: dict = {}  # parameter -> {"step", "exp_avg", "exp_avg_sq"}, created at its first step

    def _state(self, p: torch.Tensor) -> dict:
        st = self.state.get(p)
        if not st:  # as torch.optim.Adam: the step on the device when fused, a CPU scalar otherwise
            fused = self.defaults["fused"]
            st = self.state[p] = {
                "step": torch.zeros((), dtype=torch.float32, device=p.device) if fused else torch.tensor(0.0),
                "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
        return st

    @torch.no_grad()
    def step(self) -> None:
        d = self.defaults
        for g in self.param_groups:
            ps = [p for p in g["params"] if p.grad is not None]
            if not ps:
                continue
            st = [self._state(p) for p in ps]
            adam(ps, [p.grad for p in ps], [s["exp_avg"] for s in st], [s["exp_avg_sq"] for s in st], [],
                 [s["step"] for s in st], foreach=None, fused=d["fused"] or None, amsgrad=False,
                 beta1=self.BETAS[0], beta2=self.BETAS[1], lr=g["lr"], weight_decay=0.0, eps=d["eps"],
                 maximize=False)

    def zero_grad(self, set_to_none: bool = True) -> None:
        for g in self.param_groups:
            for p in g["params"]:
                p.grad = None


class GaussianOptimizer:
    """Adam (eps 1e-15) with one parameter group per field, xyz decay and post-step hooks.

    A hook is ``fn(params, before)`` where ``before`` maps field names to the values before the step
    (only the fields asked for at registration are snapshotted). Hooks run under ``torch.no_grad``
    and may modify the parameters in place."""

    def __init__(self, params: GaussianParams, lrs: LearningRates | None = None, extent: float = 1.0,
                 decay_steps: int | None = None):
        self.params, self.lrs, self.extent = params, lrs or LearningRates(), float(extent)
        self.decay_steps = self.lrs.means_steps if decay_steps is None else int(decay_steps)
        groups = [{"params": [getattr(params, f)], "lr": self.lrs.for_field(f, self.extent), "name": f}
                  for f in params.trainable()]
        # fused: one kernel for every group on CUDA instead of a dozen launches per group each step
        fused = all(g["params"][0].is_cuda for g in groups) and len(groups) > 0
        self.adam = FunctionalAdam(groups, lr=0.0, eps=1e-15, fused=fused)
        self.hooks: list = []  # (fn, fields)

    # learning rates ------------------------------------------------------------------------------
    def set_step(self, step: int) -> float:
        """Set the xyz learning rate for ``step`` (0-based); returns it."""
        lr = exp_decay(step, self.lrs.means * self.extent, self.lrs.means_final * self.extent, self.decay_steps)
        for g in self.adam.param_groups:
            if g["name"] == "means":
                g["lr"] = lr
        return lr

    def lr(self, name: str) -> float:
        return next(g["lr"] for g in self.adam.param_groups if g["name"] == name)

    def clear_moments(self, fields) -> None:
        """Forget Adam's state (step count and both moments) of the groups named in ``fields``: their next step
        starts as Adam's first."""
        for g in self.adam.param_groups:
            if g["name"] in fields:
                for p in g["params"]:
                    self.adam.state.pop(p, None)

    # hooks -----------------------------------------------------------------------------------------
    def register_post_step_hook(self, fn, fields=("means",)):
        """Call ``fn(params, before)`` after each Adam step. Returns a handle with ``.remove()``."""
        entry = (fn, tuple(fields))
        self.hooks.append(entry)

        class _Handle:
            def remove(_self):
                if entry in self.hooks:
                    self.hooks.remove(entry)
        return _Handle()

    # stepping --------------------------------------------------------------------------------------
    def step(self) -> None:
        before = {}
        with torch.no_grad():
            for _, fields in self.hooks:
                for f in fields:
                    if f not in before:
                        before[f] = getattr(self.params, f).detach().clone()
        self.adam.step()
        if self.hooks:
            with torch.no_grad():
                for fn, _ in self.hooks:
                    fn(self.params, before)

    def zero_grad(self) -> None:
        self.adam.zero_grad(set_to_none=True)

    # structural changes ------------------------------------------------------------------------------
    def _group(self, name):
        return next((g for g in self.adam.param_groups if g["name"] == name), None)

    def replace(self, name: str, new: torch.Tensor, reset_state: torch.Tensor | None = None) -> None:
        """Swap field ``name`` for ``new`` (same shape). ``reset_state``: bool mask [N] of rows whose Adam
        moments are zeroed (e.g. the opacity reset), None to keep them all."""
        old = getattr(self.params, name)
        new = new.detach().contiguous().requires_grad_(old.requires_grad)
        group = self._group(name)
        if group is not None:
            state = self.adam.state.pop(old, {})
            if reset_state is not None:
                for k in ("exp_avg", "exp_avg_sq"):
                    if k in state:
                        m = reset_state.view(-1, *([1] * (state[k].dim() - 1)))
                        state[k] = torch.where(m, torch.zeros_like(state[k]), state[k])
            group["params"][0] = new
            if state:
                self.adam.state[new] = state
        setattr(self.params, name, new)

    def rebuild(self, keep: torch.Tensor | None, appended: dict | None) -> None:
        """New parameters = ``cat(old[keep], appended[field])`` for every field; Adam moments likewise
        (kept rows sliced, appended rows zero). ``keep`` is a bool mask or an index tensor (None: all)."""
        for name in FIELDS:
            old = getattr(self.params, name)
            parts = [old.detach() if keep is None else old.detach()[keep]]
            if appended:
                parts.append(appended[name].to(dtype=old.dtype, device=old.device))
            new = torch.cat(parts, dim=0).contiguous().requires_grad_(old.requires_grad)
            group = self._group(name)
            if group is not None:
                state = self.adam.state.pop(old, {})
                for k in ("exp_avg", "exp_avg_sq"):
                    if k in state:
                        s = [state[k] if keep is None else state[k][keep]]
                        if appended:
                            s.append(torch.zeros_like(parts[1]))
                        state[k] = torch.cat(s, dim=0).contiguous()
                group["params"][0] = new
                if state:
                    self.adam.state[new] = state
            setattr(self.params, name, new)

    # checkpoints -------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        out = {"lr": {g["name"]: g["lr"] for g in self.adam.param_groups}, "state": {}}
        for g in self.adam.param_groups:
            st = self.adam.state.get(g["params"][0], {})
            out["state"][g["name"]] = {k: (v.detach().clone() if torch.is_tensor(v) else v) for k, v in st.items()}
        return out

    def load_state_dict(self, sd: dict) -> None:
        for g in self.adam.param_groups:
            g["lr"] = sd["lr"].get(g["name"], g["lr"])
            st = sd["state"].get(g["name"])
            if st:
                p = g["params"][0]
                self.adam.state[p] = {k: (v.to(p.device) if torch.is_tensor(v) and k != "step" else v)
                                      for k, v in st.items()}


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """[N,4] w,x,y,z (any norm) -> [N,3,3] rotation matrices."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).view(*q.shape[:-1], 3, 3)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """[K, 3, 3] rotation matrices -> [K, 4] unit quaternions (w, x, y, z). Shepperd's method: each row is
    solved from its largest of 4w², 4x², 4y², 4z², so no division comes near zero."""
    R = np.asarray(R, dtype=np.float64)
    d0, d1, d2 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    big = np.stack([1 + d0 + d1 + d2, 1 + d0 - d1 - d2, 1 - d0 + d1 - d2, 1 - d0 - d1 + d2], 1)  # 4 x [4q_i²]
    s = np.sqrt(np.maximum(big.max(1), 1e-300))  # 2|q_k| for the largest component k
    a, b, c = R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]  # 4w(x, y, z)
    e, f, g = R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1]  # 4(xy, xz, yz)
    cases = np.stack([np.stack([s * s, a, b, c], 1), np.stack([a, s * s, e, f], 1),
                      np.stack([b, e, s * s, g], 1), np.stack([c, f, g, s * s], 1)], 1) / (2 * s[:, None, None])
    q = cases[np.arange(len(R)), big.argmax(1)]  # [K, 4]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def footprint_normals(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """n_i = R(q_i)·e_k with k = argmin scale: the axis of the Gaussian's thinnest extent. [N,3]."""
    R = quat_to_rotmat(quats)
    k = log_scales.argmin(dim=-1)
    return torch.gather(R, 2, k.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(-1)  # column k


def tangential_hook(lam: float = 1.0, cap: float = 0.0):
    """Post-step hook (paper eq. 3): μ ← μ_before + Δμ − λ(Δμ·n)n, Δμ the Adam step just taken and n the
    footprint normal (from the parameters after the step). λ=1 removes the normal component entirely. ``cap`` > 0
    then shortens what remains to at most cap x the footprint's width (the middle scale), so each splat's step is
    sized to the splat. One Warp kernel (kernels/tangential.py) for float32/float64 parameters;
    ``tangential_hook_torch`` is its twin."""
    lam, cap = float(lam), float(cap)
    twin = tangential_hook_torch(lam, cap)

    def hook(params: GaussianParams, before: dict) -> None:
        # lazy: imports Warp (config loading imports this module; stylize.config reads LearningRates here)
        from ..kernels.tangential import tangential_kernels
        from ..launch import ct, fast_launch, init_warp, warp_on

        mu, mu0 = params.means.detach(), before["means"]
        q, ls = params.quats.detach(), params.log_scales.detach()
        if (mu.dtype not in (torch.float32, torch.float64) or mu.device.type not in ("cpu", "cuda")
                or any(t.dtype != mu.dtype or t.device != mu.device or not t.is_contiguous() for t in (mu, mu0, q, ls))):
            return twin(params, before)
        init_warp()
        K = tangential_kernels("float32" if mu.dtype == torch.float32 else "float64")
        with warp_on(mu.device) as wdev:  # in place on the parameter's storage (hooks run without grad)
            fast_launch(K.kernel, mu.shape[0], [ct(mu, K.vec3), ct(mu0, K.vec3), ct(q, K.vec4), ct(ls, K.vec3),
                                                K.scalar(lam), K.scalar(cap)], wdev)

    hook.fields = ("means",)
    return hook


def colour_floor_hook():
    """A post-step hook: SH-0 colours (SH_C0·dc + 0.5) below 0 lifted to just above 0. The renderer outputs
    max(colour, 0) and passes no gradient where colour < 0 (kernels/sh.py), so without the floor a channel pushed
    under 0 never moves again. A no-op where view-dependent bands are kept (the colour then depends on the view)."""
    floor = (-0.5 + 1e-6) / SH_C0  # a hair above 0: the gradient passes where colour >= 0

    def hook(params: "GaussianParams", before: dict) -> None:
        if params.sh_rest.shape[1] == 0:
            params.sh_dc.clamp_(min=floor)
    return hook


def tangential_hook_torch(lam: float = 1.0, cap: float = 0.0):
    """The hook in torch (``tangential_hook``'s twin, and its path for anything the kernel does not take)."""
    lam, cap = float(lam), float(cap)

    def hook(params: GaussianParams, before: dict) -> None:
        mu0 = before["means"]
        delta = params.means.detach() - mu0
        ls = params.log_scales.detach()
        n = footprint_normals(params.quats.detach(), ls).to(delta.dtype)
        delta = delta - lam * (delta * n).sum(-1, keepdim=True) * n
        if cap > 0:
            limit = cap * ls.median(dim=-1, keepdim=True).values.exp().to(delta.dtype)  # [N,1] the footprint's width
            delta = delta * (limit / delta.norm(dim=-1, keepdim=True).clamp_min(1e-30)).clamp(max=1.0)
        params.means.data.copy_(mu0 + delta)

    hook.fields = ("means",)
    return hook


__all__ = ["FIELDS", "LR_RENAMED", "LearningRates", "exp_decay", "GaussianParams", "GaussianOptimizer",
           "quat_to_rotmat", "rotmat_to_quat", "footprint_normals", "tangential_hook", "tangential_hook_torch",
           "colour_floor_hook", "sh_coeffs"]
