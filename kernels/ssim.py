"""Fused SSIM and photometric fit loss: a·mean|x − y| + b·mean SSIM(x, y) + c in four Warp kernels,
two forward and two backward, instead of ~30 torch launches forward and more backward.

SSIM as 3DGS: per channel, an 11x11 Gaussian window (σ 1.5, normalized) with zero padding, C1 = 0.01², C2 = 0.03²:

  μx = G∗x,  σxx = G∗x² − μx²,  σyy = G∗y² − μy²,  σxy = G∗(xy) − μxμy
  S = l·cs,  l = (2μxμy + C1)/(μx² + μy² + C1),  cs = (2σxy + C2)/(σxx + σyy + C2)

Forward: ``ssim_rows_kernel`` blurs the five moments (x, y, x², y², xy) along the rows; ``ssim_cols_kernel``
blurs them along the columns, forms S, writes the per-pixel value a·|x − y| + b·S + c (torch takes the mean) and,
for the backward, S's derivatives with respect to the blurred moments (μx, G∗x², G∗xy), the variance
definitions included:

  ∂S/∂(G∗x²) = ∂S/∂σxx = −S/D                       D = σxx + σyy + C2
  ∂S/∂(G∗xy) = ∂S/∂σxy = 2l/D
  ∂S/∂μx = cs·(2μy − 2μx·l)/(μx² + μy² + C1) − 2μx·∂S/∂σxx − μy·∂S/∂σxy

Backward: the blur with zero padding and a symmetric window is its own adjoint (Σ_p G(p − q) f(p) over the
image's pixels p is the same zero-padded blur of f, evaluated at q), so with the derivatives above as images
dμ, dxx, dxy:

  ∂ΣS/∂x(q) = (G∗dμ)(q) + 2x(q)·(G∗dxx)(q) + y(q)·(G∗dxy)(q)

``ssim_grad_rows_kernel`` / ``ssim_grad_cols_kernel`` are the same two blur passes over the three derivative
images; the last adds a·sign(x − y) (0 at x = y, as torch's abs) and scales by the upstream gradient / N.
The derivatives are written so that identical images give exactly l = cs = 1 and ∂S/∂μx = 0.

Images are [B, C, H, W] arrays of any strides (a channel-last [H, W, 3] image is its permuted view); the
intermediate buffers are [k, B·C, H, W], contiguous. Launches are 1D over B·C·H·W, the column index fastest.
(No ``from __future__ import annotations`` here: Warp reads the kernels' annotations as objects.)"""
import functools
import math
from types import SimpleNamespace

import warp as wp

WINDOW = 11
SIGMA = 1.5
RADIUS = WINDOW // 2
C1 = 0.01 ** 2  # the usual SSIM stabilizers for a dynamic range of 1
C2 = 0.03 ** 2


def gauss_window(size: int = WINDOW, sigma: float = SIGMA) -> list[float]:
    """The normalized 1D Gaussian window, in float64 (the torch twin's weights)."""
    w = [math.exp(-((i - (size - 1) / 2) ** 2) / (2 * sigma ** 2)) for i in range(size)]
    s = math.fsum(w)
    return [v / s for v in w]


def module_name(scalar) -> str:
    return f"tlvg_ssim_{scalar.__name__}"


@functools.lru_cache(maxsize=None)
def ssim_kernels(scalar_name: str) -> SimpleNamespace:
    """The four SSIM kernels for ``"float32"`` or ``"float64"``, one Warp module per type, built once."""
    scalar = {"float32": wp.float32, "float64": wp.float64}[scalar_name]
    module = module_name(scalar)
    weights = wp.types.vector(WINDOW, scalar)(*gauss_window())  # a constant of the kernels (literals, exact)

    @wp.func
    def pixel_of(tid: int, width: int, height: int):
        # (plane p = b·C + c, row i, column j) of a 1D thread index
        j = tid % width
        r = tid / width
        return r / height, r % height, j

    @wp.kernel(module=module)
    def ssim_rows_kernel(
        x: wp.array4d(dtype=scalar),  # [B, C, H, W] render
        y: wp.array4d(dtype=scalar),  # [B, C, H, W] reference
        rows: wp.array4d(dtype=scalar),  # [5, B·C, H, W] out: row-blurred x, y, x², y², xy
    ):
        tid = wp.tid()
        C = x.shape[1]
        H = x.shape[2]
        W = x.shape[3]
        p, i, j = pixel_of(tid, W, H)
        b = p / C
        c = p % C
        sx = scalar(0.0)
        sy = scalar(0.0)
        sxx = scalar(0.0)
        syy = scalar(0.0)
        sxy = scalar(0.0)
        for t in range(WINDOW):
            jj = j + t - RADIUS
            if jj >= 0 and jj < W:
                g = weights[t]
                u = x[b, c, i, jj]
                v = y[b, c, i, jj]
                sx += g * u
                sy += g * v
                sxx += g * (u * u)
                syy += g * (v * v)
                sxy += g * (u * v)
        rows[0, p, i, j] = sx
        rows[1, p, i, j] = sy
        rows[2, p, i, j] = sxx
        rows[3, p, i, j] = syy
        rows[4, p, i, j] = sxy

    @wp.kernel(module=module)
    def ssim_cols_kernel(
        x: wp.array4d(dtype=scalar),  # [B, C, H, W]
        y: wp.array4d(dtype=scalar),  # [B, C, H, W]
        rows: wp.array4d(dtype=scalar),  # [5, B·C, H, W] from ssim_rows_kernel
        a: scalar,  # weight of |x − y|
        bw: scalar,  # weight of S
        cw: scalar,  # constant added per pixel
        need_grad: int,
        value: wp.array3d(dtype=scalar),  # [B·C, H, W] out: a·|x − y| + bw·S + cw
        dS: wp.array4d(dtype=scalar),  # [3, B·C, H, W] out (need_grad): ∂S/∂μx, ∂S/∂(G∗x²), ∂S/∂(G∗xy)
    ):
        tid = wp.tid()
        C = x.shape[1]
        H = x.shape[2]
        W = x.shape[3]
        p, i, j = pixel_of(tid, W, H)
        b = p / C
        c = p % C
        mx = scalar(0.0)
        my = scalar(0.0)
        exx = scalar(0.0)
        eyy = scalar(0.0)
        exy = scalar(0.0)
        for t in range(WINDOW):
            ii = i + t - RADIUS
            if ii >= 0 and ii < H:
                g = weights[t]
                mx += g * rows[0, p, ii, j]
                my += g * rows[1, p, ii, j]
                exx += g * rows[2, p, ii, j]
                eyy += g * rows[3, p, ii, j]
                exy += g * rows[4, p, ii, j]
        sxx = exx - mx * mx
        syy = eyy - my * my
        sxy = exy - mx * my
        num_l = scalar(2.0) * mx * my + scalar(C1)
        den_l = mx * mx + my * my + scalar(C1)
        num_cs = scalar(2.0) * sxy + scalar(C2)
        den_cs = sxx + syy + scalar(C2)
        S = (num_l * num_cs) / (den_l * den_cs)  # the torch twin's expression
        value[p, i, j] = a * wp.abs(x[b, c, i, j] - y[b, c, i, j]) + bw * S + cw
        if need_grad != 0:
            lum = num_l / den_l
            cs = num_cs / den_cs
            d_xx = -(lum * cs) / den_cs
            d_xy = scalar(2.0) * lum / den_cs
            d_mu = cs * (scalar(2.0) * my - scalar(2.0) * mx * lum) / den_l - scalar(2.0) * mx * d_xx - my * d_xy
            dS[0, p, i, j] = d_mu
            dS[1, p, i, j] = d_xx
            dS[2, p, i, j] = d_xy

    @wp.kernel(module=module)
    def ssim_grad_rows_kernel(
        dS: wp.array4d(dtype=scalar),  # [3, B·C, H, W] from ssim_cols_kernel
        rows: wp.array4d(dtype=scalar),  # [3, B·C, H, W] out: dS blurred along the rows
    ):
        tid = wp.tid()
        H = dS.shape[2]
        W = dS.shape[3]
        p, i, j = pixel_of(tid, W, H)
        s0 = scalar(0.0)
        s1 = scalar(0.0)
        s2 = scalar(0.0)
        for t in range(WINDOW):
            jj = j + t - RADIUS
            if jj >= 0 and jj < W:
                g = weights[t]
                s0 += g * dS[0, p, i, jj]
                s1 += g * dS[1, p, i, jj]
                s2 += g * dS[2, p, i, jj]
        rows[0, p, i, j] = s0
        rows[1, p, i, j] = s1
        rows[2, p, i, j] = s2

    @wp.kernel(module=module)
    def ssim_grad_cols_kernel(
        x: wp.array4d(dtype=scalar),  # [B, C, H, W]
        y: wp.array4d(dtype=scalar),  # [B, C, H, W]
        rows: wp.array4d(dtype=scalar),  # [3, B·C, H, W] from ssim_grad_rows_kernel
        g_out: wp.array(dtype=scalar),  # [1] upstream gradient of the mean
        a: scalar,
        bw: scalar,
        inv_n: scalar,  # 1 / (B·C·H·W)
        grad: wp.array4d(dtype=scalar),  # [B, C, H, W] out: ∂loss/∂x
    ):
        tid = wp.tid()
        C = x.shape[1]
        H = x.shape[2]
        W = x.shape[3]
        p, i, j = pixel_of(tid, W, H)
        b = p / C
        c = p % C
        s0 = scalar(0.0)
        s1 = scalar(0.0)
        s2 = scalar(0.0)
        for t in range(WINDOW):
            ii = i + t - RADIUS
            if ii >= 0 and ii < H:
                g = weights[t]
                s0 += g * rows[0, p, ii, j]
                s1 += g * rows[1, p, ii, j]
                s2 += g * rows[2, p, ii, j]
        u = x[b, c, i, j]
        v = y[b, c, i, j]
        sgn = scalar(0.0)
        if u > v:
            sgn = scalar(1.0)
        if u < v:
            sgn = scalar(-1.0)
        grad[b, c, i, j] = g_out[0] * inv_n * (a * sgn + bw * (s0 + scalar(2.0) * u * s1 + v * s2))

    return SimpleNamespace(scalar=scalar, rows=ssim_rows_kernel, cols=ssim_cols_kernel,
                           grad_rows=ssim_grad_rows_kernel, grad_cols=ssim_grad_cols_kernel)
