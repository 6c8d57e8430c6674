"""Projection stage: 3D Gaussian -> screen-space mean, EWA 2D covariance (and its inverse, the conic),
radius, depth, activated opacity and view-dependent SH color (SPEC §1, §2).

The kernels are built per scalar type (float32 for speed, float64 for the gradcheck oracle) by
``make_projection``; all raster kernels of one scalar type share one Warp module so they compile once.
Warp generates the adjoint of this kernel; the blending backward is hand-written (blend.py).
"""
import warp as wp

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

EWA_BLUR = 0.3  # low-pass added to Σ2D (graphdeco/gsplat): every splat covers at least ~one pixel
FOV_CLAMP = 1.3  # x/z, y/z clamped to ±1.3·tan(half fov) inside the Jacobian, as both peers do
SIGMA_CUTOFF = 3.0  # radius = ceil(3·sqrt(λmax(Σ2D)))


def module_name(scalar) -> str:
    return f"tlvg_raster_{scalar.__name__}"


def make_projection(scalar):
    vec2 = wp.types.vector(2, scalar)
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    mat23 = wp.types.matrix((2, 3), scalar)
    mat22 = wp.types.matrix((2, 2), scalar)
    mod = module_name(scalar)
    C20, C21, C22, C23, C24 = SH_C2  # kernels capture plain floats, not tuples
    C30, C31, C32, C33, C34, C35, C36 = SH_C3

    @wp.func
    def quat_to_rotation(q: vec4) -> mat33:
        # q = (w, x, y, z); a zero quaternion falls back to identity instead of dividing by zero
        n2 = wp.dot(q, q)
        w = scalar(1.0)
        x = scalar(0.0)
        y = scalar(0.0)
        z = scalar(0.0)
        if n2 > scalar(1e-24):
            inv = scalar(1.0) / wp.sqrt(n2)
            w = q[0] * inv
            x = q[1] * inv
            y = q[2] * inv
            z = q[3] * inv
        one = scalar(1.0)
        two = scalar(2.0)
        return mat33(
            one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
            two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
            two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y),
        )

    @wp.func
    def eval_sh(sh: wp.array2d(dtype=vec3), i: int, degree: int, d: vec3) -> vec3:
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
    def ewa_cov2d(p: vec3, q: vec4, s: vec3, R: mat33, fx: scalar, fy: scalar, width: int, height: int) -> mat22:
        """Σ2D = J W Σ Wᵀ Jᵀ (before the blur) of a Gaussian at camera-space p with rotation q, scales s."""
        M = quat_to_rotation(q) * wp.diag(s)
        Sigma = M * wp.transpose(M)
        # EWA: Jacobian of the perspective map at the (clamped) mean
        lim_x = scalar(FOV_CLAMP) * scalar(0.5) * scalar(width) / fx
        lim_y = scalar(FOV_CLAMP) * scalar(0.5) * scalar(height) / fy
        z = p[2]
        inv_z = scalar(1.0) / z
        tx = wp.clamp(p[0] * inv_z, -lim_x, lim_x) * z
        ty = wp.clamp(p[1] * inv_z, -lim_y, lim_y) * z
        J = mat23(fx * inv_z, scalar(0.0), -fx * tx * inv_z * inv_z,
                  scalar(0.0), fy * inv_z, -fy * ty * inv_z * inv_z)
        T = J * R
        return T * Sigma * wp.transpose(T)

    @wp.kernel(module=mod)
    def project_kernel(
        means: wp.array(dtype=vec3),  # [N]
        quats: wp.array(dtype=vec4),  # [N]
        log_scales: wp.array(dtype=vec3),  # [N]
        opacity_logits: wp.array(dtype=scalar),  # [N]
        R: mat33,
        t: vec3,
        fx: scalar,
        fy: scalar,
        cx: scalar,
        cy: scalar,
        width: int,
        height: int,
        near: scalar,
        far: scalar,
        means2d: wp.array(dtype=vec2),  # [N] out
        cov2d: wp.array(dtype=vec3),  # [N] out (a, b, c) of Σ2D = [[a, b], [b, c]]
        conic: wp.array(dtype=vec3),  # [N] out (a, b, c) of Σ2D⁻¹
        depth: wp.array(dtype=scalar),  # [N] out camera-space z
        opacity: wp.array(dtype=scalar),  # [N] out sigmoid(logit)
        radii: wp.array(dtype=wp.int32),  # [N] out, 0 = culled
    ):
        i = wp.tid()
        radii[i] = 0
        mu = means[i]
        q = quats[i]
        ls = log_scales[i]
        ol = opacity_logits[i]
        # one non-finite parameter culls only its own Gaussian (never NaN in the image or other gradients)
        if not (wp.isfinite(mu) and wp.isfinite(q) and wp.isfinite(ls) and wp.isfinite(ol)):
            return
        p = R * mu + t
        z = p[2]
        if z <= near or z >= far:
            return
        s = vec3(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
        if not wp.isfinite(s):
            return
        S2 = ewa_cov2d(p, q, s, R, fx, fy, width, height)
        a = S2[0, 0] + scalar(EWA_BLUR)
        b = S2[0, 1]
        c = S2[1, 1] + scalar(EWA_BLUR)
        det = a * c - b * b
        if not (det > scalar(0.0)) or not wp.isfinite(det):
            return
        mid = scalar(0.5) * (a + c)
        lam_max = mid + wp.sqrt(wp.max(mid * mid - det, scalar(0.0)))
        r = wp.ceil(scalar(SIGMA_CUTOFF) * wp.sqrt(lam_max))
        inv_z = scalar(1.0) / z
        u = fx * p[0] * inv_z + cx
        v = fy * p[1] * inv_z + cy
        # cull when the 3σ bounding box misses the image (pixel centers lie in [0.5, W-0.5])
        if u + r <= scalar(0.0) or u - r >= scalar(width) or v + r <= scalar(0.0) or v - r >= scalar(height):
            return
        if r > scalar(1.0e7):  # a footprint this large is a degenerate Gaussian, not a splat
            return
        inv_det = scalar(1.0) / det
        radii[i] = wp.int32(r)
        means2d[i] = vec2(u, v)
        cov2d[i] = vec3(a, b, c)
        conic[i] = vec3(c * inv_det, -b * inv_det, a * inv_det)
        depth[i] = z
        opacity[i] = scalar(1.0) / (scalar(1.0) + wp.exp(-ol))

    @wp.func
    def view_dir(mu: vec3, cam_center: vec3) -> vec3:
        d = mu - cam_center
        n = wp.length(d)
        if n > scalar(0.0):
            d = d / n
        return d

    @wp.kernel(enable_backward=False, module=mod)
    def sh_color_kernel(
        means: wp.array(dtype=vec3),  # [N]
        sh: wp.array2d(dtype=vec3),  # [N, K]
        radii: wp.array(dtype=wp.int32),  # [N] from project_kernel; 0 = culled (color stays 0)
        cam_center: vec3,
        sh_degree: int,
        color: wp.array(dtype=vec3),  # [N] out max(SH(d) + 0.5, 0)
    ):
        i = wp.tid()
        if radii[i] <= 0:
            return
        rgb = eval_sh(sh, i, sh_degree, view_dir(means[i], cam_center)) + vec3(scalar(0.5), scalar(0.5), scalar(0.5))
        color[i] = vec3(wp.max(rgb[0], scalar(0.0)), wp.max(rgb[1], scalar(0.0)), wp.max(rgb[2], scalar(0.0)))

    @wp.func
    def dot3(a: vec3, b: vec3) -> scalar:
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

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

    @wp.kernel(enable_backward=False, module=mod)
    def sh_backward_kernel(
        means: wp.array(dtype=vec3),  # [N]
        sh: wp.array2d(dtype=vec3),  # [N, K]
        radii: wp.array(dtype=wp.int32),  # [N]
        cam_center: vec3,
        sh_degree: int,
        g_color: wp.array(dtype=vec3),  # [N] dL/dcolor
        g_rgb: wp.array(dtype=vec3),  # [N] out dL/d(SH sum) (0 when culled)
        basis: wp.array2d(dtype=scalar),  # [N, (degree+1)²] out SH basis at the view direction (0 when culled)
        g_means: wp.array(dtype=vec3),  # [N] out, plain store: runs before the projection adjoint adds to it
    ):
        # Hand-written: Warp's generated adjoint turns every array read into an atomic add, which made SH the
        # bulk of the projection backward. This pass gives the direction (mean) gradient and the basis; the
        # coefficient gradients basis ⊗ g_rgb are one torch broadcast product (coalesced stores, 3x fewer bytes
        # written from here than storing them per Gaussian).
        i = wp.tid()
        zero = scalar(0.0)
        if radii[i] <= 0:
            g_rgb[i] = vec3(zero, zero, zero)
            for k in range(basis.shape[1]):
                basis[i, k] = zero
            return
        mu = means[i]
        d = view_dir(mu, cam_center)
        for k in range(basis.shape[1]):
            basis[i, k] = sh_basis(k, d)
        rgb = eval_sh(sh, i, sh_degree, d) + vec3(scalar(0.5), scalar(0.5), scalar(0.5))
        gc0 = g_color[i]
        # color = max(rgb, 0): the gradient passes where rgb > 0 (torch's clamp passes it at 0 too: measure zero)
        gc = vec3(wp.where(rgb[0] >= zero, gc0[0], zero), wp.where(rgb[1] >= zero, gc0[1], zero),
                  wp.where(rgb[2] >= zero, gc0[2], zero))
        g_rgb[i] = gc
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
            n = wp.length(mu - cam_center)
            if n > zero:
                gd = vec3(gx, gy, gz)
                g_means[i] = (gd - dot3(gd, d) * d) / n

    return project_kernel, sh_color_kernel, sh_backward_kernel, ewa_cov2d
