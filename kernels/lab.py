"""The Lab chroma statistics loss's two per-pixel kernels (SPEC §3: sRGB -> Lab, D65); their torch side is
tlvg_warp.losses.lab_warp.

``lab_ab_forward`` computes Lab (a, b) and their 2x3 Jacobian with respect to the sRGB input (the same formulas and
branches as tlvg_warp.losses.color.rgb_to_lab: sRGB gamma with its linear toe, D65 white, the CIE cube root with its
linear segment); ``lab_chroma_backward`` maps the loss gradient through the statistics and the stored Jacobian back
to sRGB.
(No ``from __future__ import annotations`` here: Warp reads the kernels' annotations as objects.)"""
import functools
from types import SimpleNamespace

import warp as wp

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
def lab_kernels(scalar_name: str) -> SimpleNamespace:
    """The Lab chroma kernels for one scalar type (``.forward``, ``.backward``, ``.vec3``, ``.vec8``), one Warp module
    per type, built once per process."""
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
