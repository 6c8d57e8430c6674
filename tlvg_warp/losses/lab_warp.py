"""The Lab chroma statistics loss as two Warp kernels (the stylize loop is bound by the host's kernel
launches; through torch this loss took ~50 launches per step, here ~8).

Forward: one kernel per pixel computes Lab (a, b) and their 2x3 Jacobian with respect to the sRGB input (the same
formulas and branches as color.rgb_to_lab: sRGB gamma with its linear toe, D65 white, the CIE cube root with its
linear segment); torch reduces (a, b) to mean and population standard deviation. Backward: one kernel per pixel
maps the loss gradient through the statistics and the stored Jacobian back to sRGB.
(No ``from __future__ import annotations`` here: Warp reads the kernels' annotations as objects.)"""
import functools
from types import SimpleNamespace

import torch
import warp as wp

from ..ops import ct, fast_launch, init_warp, warp_on

_RGB2XYZ = ((0.412453, 0.357580, 0.180423),
            (0.212671, 0.715160, 0.072169),
            (0.019334, 0.119193, 0.950227))
_WHITE = (0.950456, 1.0, 1.088754)
_EPS_T = (6.0 / 29.0) ** 3
_K_LIN = 1.0 / (3 * (6.0 / 29.0) ** 2)
_TINY = 1e-10
_M = [[_RGB2XYZ[r][c] / _WHITE[r] for c in range(3)] for r in range(3)]  # sRGB-linear -> XYZ / white
M00, M01, M02 = _M[0]
M10, M11, M12 = _M[1]
M20, M21, M22 = _M[2]
EPS_T, K_LIN, TINY = _EPS_T, _K_LIN, _TINY
FOUR_29 = 4.0 / 29.0
# constant expressions are computed here: Warp evaluates `1.0 / 3.0` inside a kernel in float32 even for float64
INV_12_92 = 1.0 / 12.92
THIRD = 1.0 / 3.0


@functools.lru_cache(maxsize=None)
def lab_kernels(scalar_name: str):
    init_warp()
    scalar = {"float32": wp.float32, "float64": wp.float64}[scalar_name]
    vec3 = wp.types.vector(3, scalar)
    vec8 = wp.types.vector(8, scalar)
    module = f"tlvg_lab_{scalar_name}"

    @wp.func
    def srgb_linear(x: scalar):
        # (linear value, its derivative in x); x < 0 is clamped to 0 (derivative 0 there, as clamp_min's)
        c = wp.max(x, scalar(0.0))
        lin = c / scalar(12.92)
        d = scalar(INV_12_92)
        if c > scalar(0.04045):
            cp = c + scalar(0.055)
            p = wp.pow(wp.max(cp / scalar(1.055), scalar(TINY)), scalar(2.4))
            lin = p
            d = scalar(2.4) * p / cp
        if x < scalar(0.0):
            d = scalar(0.0)
        return lin, d

    @wp.func
    def cie_f(t: scalar):
        # (f(t), f'(t)): cube root above (6/29)^3, the linear segment below
        f = t * scalar(K_LIN) + scalar(FOUR_29)
        d = scalar(K_LIN)
        if t > scalar(EPS_T):
            f = wp.pow(wp.max(t, scalar(TINY)), scalar(THIRD))
            d = scalar(1.0) / (scalar(3.0) * f * f)
        return f, d

    @wp.kernel(module=module)
    def lab_ab_forward(rgb: wp.array(dtype=vec3), out: wp.array(dtype=vec8)):
        """out[i] = (a, b, ∂a/∂rgb (3), ∂b/∂rgb (3))"""
        i = wp.tid()
        c = rgb[i]
        l0, d0 = srgb_linear(c[0])
        l1, d1 = srgb_linear(c[1])
        l2, d2 = srgb_linear(c[2])
        fx, gx = cie_f(scalar(M00) * l0 + scalar(M01) * l1 + scalar(M02) * l2)
        fy, gy = cie_f(scalar(M10) * l0 + scalar(M11) * l1 + scalar(M12) * l2)
        fz, gz = cie_f(scalar(M20) * l0 + scalar(M21) * l1 + scalar(M22) * l2)
        ka = scalar(500.0)
        kb = scalar(200.0)
        out[i] = vec8(ka * (fx - fy), kb * (fy - fz),
                      ka * (gx * scalar(M00) - gy * scalar(M10)) * d0,
                      ka * (gx * scalar(M01) - gy * scalar(M11)) * d1,
                      ka * (gx * scalar(M02) - gy * scalar(M12)) * d2,
                      kb * (gy * scalar(M10) - gz * scalar(M20)) * d0,
                      kb * (gy * scalar(M11) - gz * scalar(M21)) * d1,
                      kb * (gy * scalar(M12) - gz * scalar(M22)) * d2)

    @wp.func
    def sgn(x: scalar):
        s = scalar(0.0)
        if x > scalar(0.0):
            s = scalar(1.0)
        if x < scalar(0.0):
            s = scalar(-1.0)
        return s

    @wp.kernel(module=module)
    def lab_chroma_backward(out: wp.array(dtype=vec8), stats: wp.array(dtype=scalar),
                            target: wp.array(dtype=scalar), g: wp.array(dtype=scalar), n: int,
                            grad: wp.array(dtype=vec3)):
        """loss = ½ Σ |stats − target| with stats = (μ_a, μ_b, σ_a, σ_b); grad = ∂loss/∂rgb · g"""
        i = wp.tid()
        o = out[i]
        h = scalar(0.5) * g[0] / scalar(n)
        ga = h * sgn(stats[0] - target[0])
        gb = h * sgn(stats[1] - target[1])
        if stats[2] > scalar(0.0):  # ∂σ/∂x_p = (x_p − μ)/(N σ); 0 where σ = 0 (as torch's std backward)
            ga += h * sgn(stats[2] - target[2]) * (o[0] - stats[0]) / stats[2]
        if stats[3] > scalar(0.0):
            gb += h * sgn(stats[3] - target[3]) * (o[1] - stats[1]) / stats[3]
        grad[i] = vec3(ga * o[2] + gb * o[5], ga * o[3] + gb * o[6], ga * o[4] + gb * o[7])

    return SimpleNamespace(forward=lab_ab_forward, backward=lab_chroma_backward, vec3=vec3, vec8=vec8)


def _scalar_name(dtype: torch.dtype) -> str:
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"Lab kernels take float32 or float64, got {dtype}")
    return "float32" if dtype == torch.float32 else "float64"


def lab_ab_jacobian(rgb: torch.Tensor) -> torch.Tensor:
    """[N,8] per pixel of rgb [...,3]: (a, b, ∂a/∂rgb, ∂b/∂rgb), no autograd."""
    x = rgb.detach().reshape(-1, 3)
    x = x if x.is_contiguous() else x.contiguous()
    K = lab_kernels(_scalar_name(x.dtype))
    out = torch.empty(x.shape[0], 8, dtype=x.dtype, device=x.device)
    if x.shape[0]:
        with warp_on(x.device) as wdev:
            fast_launch(K.forward, x.shape[0], [ct(x, K.vec3), ct(out, K.vec8)], wdev)
    return out


def chroma_stats_of(out: torch.Tensor) -> torch.Tensor:
    """[4] = (μ_a, μ_b, σ_a, σ_b) (population σ) of ``lab_ab_jacobian``'s output."""
    sd, mu = torch.std_mean(out[:, :2], dim=0, correction=0)
    return torch.cat([mu, sd])


class LabChromaLossFn(torch.autograd.Function):
    """½(‖Δμ_ab‖₁ + ‖Δσ_ab‖₁) of an sRGB render [...,3] against target statistics [4] (constant)."""

    @staticmethod
    def forward(ctx, rgb, target_stats):
        out = lab_ab_jacobian(rgb)
        stats = chroma_stats_of(out)
        t = target_stats.to(stats).reshape(4).contiguous()
        ctx.save_for_backward(out, stats, t)
        ctx.shape = rgb.shape
        return 0.5 * torch.linalg.vector_norm(stats - t, ord=1)

    @staticmethod
    def backward(ctx, g):
        out, stats, t = ctx.saved_tensors
        K = lab_kernels(_scalar_name(out.dtype))
        n = out.shape[0]
        grad = torch.empty(n, 3, dtype=out.dtype, device=out.device)
        gs = g.reshape(1).to(out.dtype).contiguous()
        if n:
            with warp_on(out.device) as wdev:
                fast_launch(K.backward, n, [ct(out, K.vec8), ct(stats), ct(t), ct(gs), n, ct(grad, K.vec3)], wdev)
        return grad.reshape(ctx.shape), None
