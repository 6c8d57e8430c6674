"""View-dependent color from spherical harmonics (SPEC §1): color = max(Σ_k b_k(d) sh_k + 0.5, 0), d the unit
direction from the camera center to the mean, and its hand-written backward (built per scalar type into the
raster module by ``make_sh``)."""
import warp as wp

from .projection import SH_C0, SH_C1, SH_C2, SH_C3


def make_sh(scalar, mod: str, camera_t):
    """The SH kernels for ``scalar`` in module ``mod``; ``camera_t``: ``camera.camera_struct`` of that type."""
    vec3 = wp.types.vector(3, scalar)
    C20, C21, C22, C23, C24 = SH_C2  # kernels capture plain floats, not tuples
    C30, C31, C32, C33, C34, C35, C36 = SH_C3

    @wp.func
    def eval_sh(sh: wp.array2d(dtype=vec3), i: int, degree: int, d: vec3) -> vec3:
        """Σ_k b_k(d) sh[i, k] up to ``degree``. Written out, not summed over sh_basis_all: the branches skip the
        higher degrees' loads and products (sh_backward on fern, on the GPU: 0.073 ms against 0.080 for the loop)."""
        c = scalar(SH_C0) * sh[i, 0]
        if degree > 0:
            x = d[0]
            y = d[1]
            z = d[2]
            c1 = scalar(SH_C1)
            c += -c1 * y * sh[i, 1] + c1 * z * sh[i, 2] - c1 * x * sh[i, 3]
            if degree > 1:
                xx = x * x
                yy = y * y
                zz = z * z
                c += scalar(C20) * (x * y) * sh[i, 4]
                c += scalar(C21) * (y * z) * sh[i, 5]
                c += scalar(C22) * (scalar(2.0) * zz - xx - yy) * sh[i, 6]
                c += scalar(C23) * (x * z) * sh[i, 7]
                c += scalar(C24) * (xx - yy) * sh[i, 8]
                if degree > 2:
                    c += scalar(C30) * y * (scalar(3.0) * xx - yy) * sh[i, 9]
                    c += scalar(C31) * (x * y * z) * sh[i, 10]
                    c += scalar(C32) * y * (scalar(4.0) * zz - xx - yy) * sh[i, 11]
                    c += scalar(C33) * z * (scalar(2.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy) * sh[i, 12]
                    c += scalar(C34) * x * (scalar(4.0) * zz - xx - yy) * sh[i, 13]
                    c += scalar(C35) * z * (xx - yy) * sh[i, 14]
                    c += scalar(C36) * x * (xx - scalar(3.0) * yy) * sh[i, 15]
        return c

    @wp.func
    def view_dir(mu: vec3, cam_center: vec3) -> vec3:
        d = mu - cam_center
        n = wp.length(d)
        if n > scalar(0.0):
            d = d / n
        return d

    vec16 = wp.types.vector(16, scalar)

    @wp.func
    def sh_basis_all(d: vec3) -> vec16:
        """(b_0(d), ..., b_15(d)): every basis value up to degree 3."""
        x = d[0]
        y = d[1]
        z = d[2]
        xx = x * x
        yy = y * y
        zz = z * z
        c1 = scalar(SH_C1)
        return vec16(scalar(SH_C0), -c1 * y, c1 * z, -c1 * x,
                     scalar(C20) * x * y, scalar(C21) * y * z, scalar(C22) * (scalar(2.0) * zz - xx - yy),
                     scalar(C23) * x * z, scalar(C24) * (xx - yy),
                     scalar(C30) * y * (scalar(3.0) * xx - yy), scalar(C31) * x * y * z,
                     scalar(C32) * y * (scalar(4.0) * zz - xx - yy),
                     scalar(C33) * z * (scalar(2.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy),
                     scalar(C34) * x * (scalar(4.0) * zz - xx - yy), scalar(C35) * z * (xx - yy),
                     scalar(C36) * x * (xx - scalar(3.0) * yy))

    @wp.kernel(enable_backward=False, module=mod)
    def sh_color_kernel(
        means: wp.array(dtype=vec3),  # [N]
        sh: wp.array3d(dtype=scalar),  # [N, K, 3]
        cam: camera_t,
        n_coeffs: int,  # (degree + 1)² <= K
        color: wp.array(dtype=scalar),  # [3N] out max(SH(d) + 0.5, 0), flat (every Gaussian: culled ones are
        # never blended)
    ):
        # One thread per (Gaussian, channel), as gsplat: a warp's loads of coefficient k span 11 Gaussians' rows,
        # not 32 (a thread per Gaussian read 3 scalars of each of 16 vec3s from 32 rows 192 bytes apart: 2.28 ms
        # at 20M Gaussians on the GPU against gsplat's 1.23). The loop has a constant trip count, so Warp unrolls
        # it and b[k] stays in registers.
        tid = wp.tid()
        i = tid / 3
        c = tid - 3 * i
        b = sh_basis_all(view_dir(means[i], cam.center))
        v = scalar(0.5)
        for k in range(16):
            if k < n_coeffs:
                v += b[k] * sh[i, k, c]
        color[tid] = wp.max(v, scalar(0.0))

    @wp.func
    def dot3(a: vec3, b: vec3) -> scalar:
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    @wp.func
    def sh_basis(k: int, d: vec3) -> scalar:
        """b_k(d), branch free: the 32 lanes of a warp hold two Gaussians' 16 coefficients, so an if-chain on k
        would run all 16 branches one after another; here every lane evaluates the 16 cheap products and selects.
        Selecting from sh_basis_all instead measured 4% slower in sh_coeff_grad_kernel (1.72 against 1.65 ms at 20M
        Gaussians, 0.041 against 0.040 on fern; on the GPU, 2026-11-23), so the products are written out here too."""
        x = d[0]
        y = d[1]
        z = d[2]
        xx = x * x
        yy = y * y
        zz = z * z
        b = wp.where(k == 0, scalar(SH_C0), scalar(0.0))
        b = wp.where(k == 1, -scalar(SH_C1) * y, b)
        b = wp.where(k == 2, scalar(SH_C1) * z, b)
        b = wp.where(k == 3, -scalar(SH_C1) * x, b)
        b = wp.where(k == 4, scalar(C20) * x * y, b)
        b = wp.where(k == 5, scalar(C21) * y * z, b)
        b = wp.where(k == 6, scalar(C22) * (scalar(2.0) * zz - xx - yy), b)
        b = wp.where(k == 7, scalar(C23) * x * z, b)
        b = wp.where(k == 8, scalar(C24) * (xx - yy), b)
        b = wp.where(k == 9, scalar(C30) * y * (scalar(3.0) * xx - yy), b)
        b = wp.where(k == 10, scalar(C31) * x * y * z, b)
        b = wp.where(k == 11, scalar(C32) * y * (scalar(4.0) * zz - xx - yy), b)
        b = wp.where(k == 12, scalar(C33) * z * (scalar(2.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy), b)
        b = wp.where(k == 13, scalar(C34) * x * (scalar(4.0) * zz - xx - yy), b)
        b = wp.where(k == 14, scalar(C35) * z * (xx - yy), b)
        b = wp.where(k == 15, scalar(C36) * x * (xx - scalar(3.0) * yy), b)
        return b

    @wp.kernel(enable_backward=False, module=mod)
    def sh_backward_kernel(
        means: wp.array(dtype=vec3),  # [N]
        sh: wp.array2d(dtype=vec3),  # [N, K]
        cam: camera_t,
        sh_degree: int,
        g_color: wp.array(dtype=vec3),  # [N] dL/dcolor (exactly 0 for the Gaussians no pixel saw, culled ones too)
        g_rgb: wp.array(dtype=vec3),  # [N] out dL/d(SH sum) (0 when culled); may alias g_color
        g_means: wp.array(dtype=vec3),  # [N] out: the view-direction part of dL/dmeans (every row stored)
    ):
        # Hand-written: Warp's generated adjoint turns every array read into an atomic add, which made SH the
        # bulk of the projection backward. This pass gives the direction (mean) gradient and dL/d(SH sum);
        # sh_coeff_grad_kernel expands the latter to the coefficients.
        i = wp.tid()
        zero = scalar(0.0)
        gc0 = g_color[i]
        if gc0[0] == zero and gc0[1] == zero and gc0[2] == zero:  # nothing to pass back: also keeps a culled
            g_rgb[i] = gc0  # Gaussian's non-finite mean out of every gradient (0 · NaN)
            g_means[i] = gc0
            return
        mu = means[i]
        d = view_dir(mu, cam.center)
        rgb = eval_sh(sh, i, sh_degree, d) + vec3(scalar(0.5), scalar(0.5), scalar(0.5))
        # color = max(rgb, 0): the gradient passes where rgb > 0 (torch's clamp passes it at 0 too: measure zero)
        gc = vec3(wp.where(rgb[0] >= zero, gc0[0], zero), wp.where(rgb[1] >= zero, gc0[1], zero),
                  wp.where(rgb[2] >= zero, gc0[2], zero))
        g_rgb[i] = gc
        g_mean = vec3(zero, zero, zero)
        if sh_degree > 0:
            x = d[0]
            y = d[1]
            z = d[2]
            c1 = scalar(SH_C1)
            # dL/d(basis k) = gc·sh_k; the direction gradient is Σ_k (gc·sh_k) ∇b_k(d)
            w1 = dot3(gc, sh[i, 1])
            w2 = dot3(gc, sh[i, 2])
            w3 = dot3(gc, sh[i, 3])
            gx = -c1 * w3
            gy = -c1 * w1
            gz = c1 * w2
            if sh_degree > 1:
                xx = x * x
                yy = y * y
                zz = z * z
                w4 = scalar(C20) * dot3(gc, sh[i, 4])
                w5 = scalar(C21) * dot3(gc, sh[i, 5])
                w6 = scalar(C22) * dot3(gc, sh[i, 6])
                w7 = scalar(C23) * dot3(gc, sh[i, 7])
                w8 = scalar(C24) * dot3(gc, sh[i, 8])
                gx += w4 * y - scalar(2.0) * w6 * x + w7 * z + scalar(2.0) * w8 * x
                gy += w4 * x + w5 * z - scalar(2.0) * w6 * y - scalar(2.0) * w8 * y
                gz += w5 * y + scalar(4.0) * w6 * z + w7 * x
                if sh_degree > 2:
                    w9 = scalar(C30) * dot3(gc, sh[i, 9])
                    w10 = scalar(C31) * dot3(gc, sh[i, 10])
                    w11 = scalar(C32) * dot3(gc, sh[i, 11])
                    w12 = scalar(C33) * dot3(gc, sh[i, 12])
                    w13 = scalar(C34) * dot3(gc, sh[i, 13])
                    w14 = scalar(C35) * dot3(gc, sh[i, 14])
                    w15 = scalar(C36) * dot3(gc, sh[i, 15])
                    gx += (w9 * scalar(6.0) * x * y + w10 * y * z - w11 * scalar(2.0) * x * y
                           - w12 * scalar(6.0) * x * z + w13 * (scalar(4.0) * zz - scalar(3.0) * xx - yy)
                           + w14 * scalar(2.0) * x * z + w15 * scalar(3.0) * (xx - yy))
                    gy += (w9 * scalar(3.0) * (xx - yy) + w10 * x * z + w11 * (scalar(4.0) * zz - xx - scalar(3.0) * yy)
                           - w12 * scalar(6.0) * y * z - w13 * scalar(2.0) * x * y - w14 * scalar(2.0) * y * z
                           - w15 * scalar(6.0) * x * y)
                    gz += (w10 * x * y + w11 * scalar(8.0) * y * z
                           + w12 * (scalar(6.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy)
                           + w13 * scalar(8.0) * x * z + w14 * (xx - yy))
            # through d = v/|v|: dd/dv = (I - d dᵀ)/|v|
            n = wp.length(mu - cam.center)
            if n > zero:
                gd = vec3(gx, gy, gz)
                g_mean = (gd - dot3(gd, d) * d) / n
        g_means[i] = g_mean

    @wp.kernel(enable_backward=False, module=mod)
    def sh_coeff_grad_kernel(
        means: wp.array(dtype=vec3),  # [N]
        cam: camera_t,
        n_coeffs: int,  # (degree + 1)²
        g_rgb: wp.array(dtype=vec3),  # [N] from sh_backward_kernel
        g_sh: wp.array2d(dtype=vec3),  # [N, Kmax] out dL/d sh[i, k] = b_k(d_i) g_rgb[i] for k < n_coeffs
    ):
        # one thread per (Gaussian, coefficient) in memory order: neighbouring threads store neighbouring vec3s
        # (coalesced). Measured on the GPU at 1M Gaussians, degree 3: 0.33 ms; grouping a warp's threads by k
        # (no branch divergence, strided stores) 0.72 ms; indexing a vector of all 16 basis values 0.49 ms.
        tid = wp.tid()
        i = tid / n_coeffs
        k = tid - i * n_coeffs
        zero = scalar(0.0)
        gr = g_rgb[i]
        if gr[0] == zero and gr[1] == zero and gr[2] == zero:  # as sh_backward: no 0 · NaN from a culled mean
            g_sh[i, k] = gr
            return
        g_sh[i, k] = sh_basis(k, view_dir(means[i], cam.center)) * gr

    return sh_color_kernel, sh_backward_kernel, sh_coeff_grad_kernel
