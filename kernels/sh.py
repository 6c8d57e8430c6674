"""View-dependent color from spherical harmonics (SPEC §1): color = max(Σ_k b_k(d) sh_k + 0.5, 0), d the unit
direction from the camera center to the mean, and its hand-written backward (built per scalar type into the
raster module by ``make_sh``).

Work layout: on a GPU a Gaussian's (up to 16) coefficients are taken by 16 neighbouring lanes of one warp, lane
k the coefficient k, so the reads of ``sh`` and the writes of its gradient are coalesced (one thread per Gaussian
reads 16 vec3 192 bytes apart) and the sums over k are shuffles within the 16 lanes. On the CPU a group is one
lane that loops over the coefficients, so the same kernels run there."""
import warp as wp

from .projection import SH_C0, SH_C1, SH_C2, SH_C3

SH_LANES = 16  # lanes per Gaussian on a GPU (the most coefficients, degree 3); the launch is N · 16 threads

GROUP_LANES = """
#if defined(__CUDA_ARCH__)
    return 16;
#else
    return 1;
#endif
"""
GROUP_SUM = """
#if defined(__CUDA_ARCH__)
    for (int o = 8; o > 0; o >>= 1) x += __shfl_xor_sync(0xffffffffu, x, o);
#endif
    return x;
"""


@wp.func_native(GROUP_LANES)
def group_lanes() -> int: ...


@wp.func_native(GROUP_SUM)
def group_sum_f32(x: wp.float32) -> wp.float32:
    """The sum over the 16 lanes of a Gaussian (a full-warp shuffle: every lane of the warp must reach it)."""
    ...


@wp.func_native(GROUP_SUM)
def group_sum_f64(x: wp.float64) -> wp.float64: ...


def sh_threads(n: int, cuda: bool) -> int:
    """The launch size of the SH kernels for n Gaussians: 16 lanes each, whole warps, on a GPU; n on the CPU."""
    return (n * SH_LANES + 31) // 32 * 32 if cuda else n


def make_sh(scalar, mod: str):
    vec3 = wp.types.vector(3, scalar)
    C20, C21, C22, C23, C24 = SH_C2  # kernels capture plain floats, not tuples
    C30, C31, C32, C33, C34, C35, C36 = SH_C3

    @wp.func
    def view_dir(mu: vec3, cam_center: vec3) -> vec3:
        d = mu - cam_center
        n = wp.length(d)
        if n > scalar(0.0):
            d = d / n
        return d

    group_sum = group_sum_f32 if scalar == wp.float32 else group_sum_f64

    @wp.func
    def group_vec(v: vec3) -> vec3:
        return vec3(group_sum(v[0]), group_sum(v[1]), group_sum(v[2]))

    @wp.func
    def sh_basis(k: int, d: vec3) -> scalar:
        x = d[0]
        y = d[1]
        z = d[2]
        xx = x * x
        yy = y * y
        zz = z * z
        b = scalar(SH_C0)
        if k == 1:
            b = -scalar(SH_C1) * y
        elif k == 2:
            b = scalar(SH_C1) * z
        elif k == 3:
            b = -scalar(SH_C1) * x
        elif k == 4:
            b = scalar(C20) * x * y
        elif k == 5:
            b = scalar(C21) * y * z
        elif k == 6:
            b = scalar(C22) * (scalar(2.0) * zz - xx - yy)
        elif k == 7:
            b = scalar(C23) * x * z
        elif k == 8:
            b = scalar(C24) * (xx - yy)
        elif k == 9:
            b = scalar(C30) * y * (scalar(3.0) * xx - yy)
        elif k == 10:
            b = scalar(C31) * x * y * z
        elif k == 11:
            b = scalar(C32) * y * (scalar(4.0) * zz - xx - yy)
        elif k == 12:
            b = scalar(C33) * z * (scalar(2.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy)
        elif k == 13:
            b = scalar(C34) * x * (scalar(4.0) * zz - xx - yy)
        elif k == 14:
            b = scalar(C35) * z * (xx - yy)
        elif k == 15:
            b = scalar(C36) * x * (xx - scalar(3.0) * yy)
        return b

    @wp.func
    def sh_basis_grad(k: int, d: vec3) -> vec3:
        """∇_d b_k(d) (d before its normalization is undone by the caller)."""
        x = d[0]
        y = d[1]
        z = d[2]
        xx = x * x
        yy = y * y
        zz = z * z
        zero = scalar(0.0)
        g = vec3(zero, zero, zero)
        if k == 1:
            g = vec3(zero, -scalar(SH_C1), zero)
        elif k == 2:
            g = vec3(zero, zero, scalar(SH_C1))
        elif k == 3:
            g = vec3(-scalar(SH_C1), zero, zero)
        elif k == 4:
            g = scalar(C20) * vec3(y, x, zero)
        elif k == 5:
            g = scalar(C21) * vec3(zero, z, y)
        elif k == 6:
            g = scalar(C22) * vec3(scalar(-2.0) * x, scalar(-2.0) * y, scalar(4.0) * z)
        elif k == 7:
            g = scalar(C23) * vec3(z, zero, x)
        elif k == 8:
            g = scalar(C24) * vec3(scalar(2.0) * x, scalar(-2.0) * y, zero)
        elif k == 9:
            g = scalar(C30) * vec3(scalar(6.0) * x * y, scalar(3.0) * (xx - yy), zero)
        elif k == 10:
            g = scalar(C31) * vec3(y * z, x * z, x * y)
        elif k == 11:
            g = scalar(C32) * vec3(scalar(-2.0) * x * y, scalar(4.0) * zz - xx - scalar(3.0) * yy, scalar(8.0) * y * z)
        elif k == 12:
            g = scalar(C33) * vec3(scalar(-6.0) * x * z, scalar(-6.0) * y * z,
                                   scalar(6.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy)
        elif k == 13:
            g = scalar(C34) * vec3(scalar(4.0) * zz - scalar(3.0) * xx - yy, scalar(-2.0) * x * y, scalar(8.0) * x * z)
        elif k == 14:
            g = scalar(C35) * vec3(scalar(2.0) * x * z, scalar(-2.0) * y * z, xx - yy)
        elif k == 15:
            g = scalar(C36) * vec3(scalar(3.0) * (xx - yy), scalar(-6.0) * x * y, zero)
        return g

    @wp.kernel(enable_backward=False, module=mod)
    def sh_color_kernel(
        means: wp.array(dtype=vec3),  # [N]
        sh: wp.array2d(dtype=vec3),  # [N, K]
        cam_center: vec3,
        sh_degree: int,
        n: int,
        color: wp.array(dtype=vec3),  # [N] out max(SH(d) + 0.5, 0) (every Gaussian: culled ones are never blended)
    ):
        # sh_threads(n) threads: group i = Gaussian i; lanes past N join the shuffles only
        lanes = group_lanes()
        tid = wp.tid()
        i = tid / lanes
        lane = tid - i * lanes
        zero = scalar(0.0)
        part = vec3(zero, zero, zero)
        if i < n:
            d = view_dir(means[i], cam_center)
            for k in range(lane, (sh_degree + 1) * (sh_degree + 1), lanes):
                part += sh_basis(k, d) * sh[i, k]
        rgb = group_vec(part) + vec3(scalar(0.5), scalar(0.5), scalar(0.5))
        if i < n and lane == 0:
            color[i] = vec3(wp.max(rgb[0], zero), wp.max(rgb[1], zero), wp.max(rgb[2], zero))

    @wp.func
    def dot3(a: vec3, b: vec3) -> scalar:
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    @wp.kernel(enable_backward=False, module=mod)
    def sh_backward_kernel(
        means: wp.array(dtype=vec3),  # [N]
        sh: wp.array2d(dtype=vec3),  # [N, K]
        cam_center: vec3,
        sh_degree: int,
        n: int,
        g_color: wp.array(dtype=vec3),  # [N] dL/dcolor (exactly 0 for the Gaussians no pixel saw, culled ones too)
        g_means: wp.array(dtype=vec3),  # [N] out: the view-direction part of dL/dmeans (every row stored)
        g_sh: wp.array2d(dtype=vec3),  # [N, K] out dL/d sh[i, k] = b_k(d_i) g_rgb[i] (0 past the degree)
    ):
        # Hand-written: Warp's generated adjoint turns every array read into an atomic add. One pass gives the
        # coefficient gradients and the direction (mean) gradient Σ_k (gc·sh_k) ∇b_k(d); the layout
        # is sh_color_kernel's (no lane leaves before the last shuffle)
        lanes = group_lanes()
        tid = wp.tid()
        i = tid / lanes
        lane = tid - i * lanes
        zero = scalar(0.0)
        n_coeffs = (sh_degree + 1) * (sh_degree + 1)
        gc0 = vec3(zero, zero, zero)
        mu = vec3(zero, zero, zero)
        d = vec3(zero, zero, zero)
        live = False  # nothing to pass back where dL/dcolor is 0: also keeps a culled Gaussian's non-finite mean
        part = vec3(zero, zero, zero)  # out of every gradient (0 · NaN)
        if i < n:
            gc0 = g_color[i]
            if gc0[0] != zero or gc0[1] != zero or gc0[2] != zero:
                live = True
                mu = means[i]
                d = view_dir(mu, cam_center)
                for k in range(lane, n_coeffs, lanes):
                    part += sh_basis(k, d) * sh[i, k]
        rgb = group_vec(part) + vec3(scalar(0.5), scalar(0.5), scalar(0.5))
        # color = max(rgb, 0): the gradient passes where rgb > 0 (torch's clamp passes it at 0 too: measure zero)
        gc = vec3(wp.where(rgb[0] >= zero, gc0[0], zero), wp.where(rgb[1] >= zero, gc0[1], zero),
                  wp.where(rgb[2] >= zero, gc0[2], zero))
        gd = vec3(zero, zero, zero)
        if i < n:
            for k in range(lane, sh.shape[1], lanes):
                if live and k < n_coeffs:
                    g_sh[i, k] = sh_basis(k, d) * gc
                    gd += dot3(gc, sh[i, k]) * sh_basis_grad(k, d)
                else:
                    g_sh[i, k] = vec3(zero, zero, zero)
        gd = group_vec(gd)
        if i < n and lane == 0:
            g_mean = vec3(zero, zero, zero)
            # through d = v/|v|: dd/dv = (I - d dᵀ)/|v|
            norm = wp.length(mu - cam_center)
            if live and sh_degree > 0 and norm > zero:
                g_mean = (gd - dot3(gd, d) * d) / norm
            g_means[i] = g_mean

    return sh_color_kernel, sh_backward_kernel
