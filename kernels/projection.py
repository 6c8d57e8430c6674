"""Projection stage: 3D Gaussian -> screen-space mean, EWA 2D covariance (and its inverse, the conic),
radius, depth and activated opacity (SPEC §1, §2); view-dependent color is in sh.py.

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


def make_projection(scalar, camera_t):
    """The projection kernel and ``ewa_cov2d`` for ``scalar``; ``camera_t``: ``camera.camera_struct`` of that type."""
    vec2 = wp.types.vector(2, scalar)
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    mat23 = wp.types.matrix((2, 3), scalar)
    mat22 = wp.types.matrix((2, 2), scalar)
    mod = module_name(scalar)

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
        cam: camera_t,
        means2d: wp.array(dtype=vec2),  # [N] out
        conic: wp.array(dtype=vec3),  # [N] out (a, b, c) of Σ2D⁻¹, Σ2D = [[a, b], [b, c]]
        depth: wp.array(dtype=scalar),  # [N] out camera-space z
        opacity: wp.array(dtype=scalar),  # [N] out sigmoid(logit)
        radii: wp.array(dtype=wp.int32),  # [N] out, 0 = culled
    ):
        i = wp.tid()
        # every output is written, the culled Gaussians' with zeros: the buffers come uninitialized (no memset
        # launch per render, whose host time the forward waits on)
        radii[i] = 0
        means2d[i] = vec2(scalar(0.0), scalar(0.0))
        conic[i] = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        depth[i] = scalar(0.0)
        opacity[i] = scalar(0.0)
        mu = means[i]
        q = quats[i]
        ls = log_scales[i]
        ol = opacity_logits[i]
        # one non-finite parameter culls only its own Gaussian (never NaN in the image or other gradients)
        if not (wp.isfinite(mu) and wp.isfinite(q) and wp.isfinite(ls) and wp.isfinite(ol)):
            return
        p = cam.R * mu + cam.t
        z = p[2]
        if z <= cam.near or z >= cam.far:
            return
        s = vec3(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
        if not wp.isfinite(s):
            return
        S2 = ewa_cov2d(p, q, s, cam.R, cam.fx, cam.fy, cam.width, cam.height)
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
        u = cam.fx * p[0] * inv_z + cam.cx
        v = cam.fy * p[1] * inv_z + cam.cy
        # cull when the 3σ bounding box misses the image (pixel centers lie in [0.5, W-0.5])
        if (u + r <= scalar(0.0) or u - r >= scalar(cam.width) or v + r <= scalar(0.0)
                or v - r >= scalar(cam.height)):
            return
        if r > scalar(1.0e7):  # a footprint this large is a degenerate Gaussian, not a splat
            return
        inv_det = scalar(1.0) / det
        radii[i] = wp.int32(r)
        means2d[i] = vec2(u, v)
        conic[i] = vec3(c * inv_det, -b * inv_det, a * inv_det)
        depth[i] = z
        opacity[i] = scalar(1.0) / (scalar(1.0) + wp.exp(-ol))

    return project_kernel, ewa_cov2d
