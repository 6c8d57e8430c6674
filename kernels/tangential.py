"""The tangential update hook (paper eq. 3) as one Warp kernel per Gaussian: μ ← μ₀ + Δ − λ(Δ·n)n with Δ = μ − μ₀
the Adam step just taken and n = R(q)·e_k the footprint normal, k = argmin of the log-scales (the thinnest axis).
With ``cap`` > 0 the step that remains is then shortened to at most cap x the splat's footprint width (its middle
scale): a step sized to the splat, not to the scene (ours; a thin strut's splats no longer drift off it).
Through torch the hook was about 50 launches a step (rotation matrices, a gather, the projection); here one.
Its twin is ``tlvg_warp.train.optim.tangential_hook_torch`` (the tests compare them).
(No ``from __future__ import annotations`` here: Warp reads the kernel's annotations as objects.)"""
import functools
from types import SimpleNamespace

import warp as wp

QUAT_EPS = 1e-12  # as quat_to_rotmat's clamp: an all-zero quaternion gives the identity's columns times 0


@functools.lru_cache(maxsize=None)
def tangential_kernels(scalar_name: str) -> SimpleNamespace:
    """The kernel for one scalar type, with its vector types (``.kernel``, ``.scalar``, ``.vec3``, ``.vec4``)."""
    scalar = {"float32": wp.float32, "float64": wp.float64}[scalar_name]
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)

    @wp.func
    def footprint_normal(q: vec4, ls: vec3):
        """Column k = argmin(ls) of R(q / |q|) (the first minimum on ties, as torch.argmin)."""
        q = q / wp.max(wp.length(q), scalar(QUAT_EPS))
        w = q[0]
        x = q[1]
        y = q[2]
        z = q[3]
        one = scalar(1.0)
        two = scalar(2.0)
        n = vec3(two * (x * z + w * y), two * (y * z - w * x), one - two * (x * x + y * y))
        if ls[0] <= ls[1] and ls[0] <= ls[2]:
            n = vec3(one - two * (y * y + z * z), two * (x * y + w * z), two * (x * z - w * y))
        elif ls[1] <= ls[2]:
            n = vec3(two * (x * y - w * z), one - two * (x * x + z * z), two * (y * z + w * x))
        return n

    @wp.func
    def footprint_width(ls: vec3):
        """exp of the middle log-scale: the footprint's narrower in-plane axis (the thinnest is the normal)."""
        largest = wp.max(ls[0], wp.max(ls[1], ls[2]))
        smallest = wp.min(ls[0], wp.min(ls[1], ls[2]))
        return wp.exp(ls[0] + ls[1] + ls[2] - largest - smallest)

    @wp.kernel(enable_backward=False, module=f"tlvg_tangential_{scalar_name}")
    def tangential_kernel(
        means: wp.array(dtype=vec3),  # [N] in: after the Adam step; out: with λ of the normal part removed
        before: wp.array(dtype=vec3),  # [N] before the step
        quats: wp.array(dtype=vec4),  # [N]
        log_scales: wp.array(dtype=vec3),  # [N]
        lam: scalar,
        cap: scalar,  # the longest step in footprint widths; 0 = no limit
    ):
        i = wp.tid()
        mu0 = before[i]
        ls = log_scales[i]
        d = means[i] - mu0
        n = footprint_normal(quats[i], ls)
        t = d - lam * wp.dot(d, n) * n
        if cap > scalar(0.0):
            length = wp.length(t)
            limit = cap * footprint_width(ls)
            if length > limit:
                t = t * (limit / length)
        means[i] = mu0 + t

    return SimpleNamespace(kernel=tangential_kernel, scalar=scalar, vec3=vec3, vec4=vec4)
