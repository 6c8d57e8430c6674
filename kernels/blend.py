"""Alpha blending, front to back per pixel over its tile's sorted Gaussians (SPEC §2), and its
hand-written backward. The loop length depends on the data, which Warp's tape cannot replay, so the
backward walks the same list in reverse from the last contributor, rebuilding the transmittance by
dividing by (1 - α) (α ≤ 0.99, so at most a factor 100 per step).

Threads are laid out tile-major (one 16x16 tile = 256 consecutive threads) so that the threads of a GPU
block read the same Gaussians."""
import warp as wp

from .binning import TILE

ALPHA_MAX = 0.99  # α clamp: a single splat never makes a pixel fully opaque (keeps 1/(1-α) bounded)
ALPHA_MIN = 1.0 / 255.0  # contributions below one 8-bit level are skipped
T_MIN = 1e-4  # stop before a Gaussian that would drop transmittance below this


# Warp-level primitives as native snippets; on the CPU (one lane per block) they reduce to the identity.
WARP_SUM = """
#if defined(__CUDA_ARCH__)
    for (int o = 16; o > 0; o >>= 1) x += __shfl_xor_sync(0xffffffff, x, o);
#endif
    return x;
"""
WARP_MAX = """
#if defined(__CUDA_ARCH__)
    for (int o = 16; o > 0; o >>= 1) x = max(x, __shfl_xor_sync(0xffffffff, x, o));
#endif
    return x;
"""
LEAD_LANE = """
#if defined(__CUDA_ARCH__)
    return (threadIdx.x & 31) == 0 ? 1 : 0;
#else
    return 1;
#endif
"""


@wp.func_native(WARP_MAX)
def warp_max(x: int) -> int: ...


@wp.func_native(LEAD_LANE)
def lead_lane(tid: int) -> int: ...


def make_blend(scalar, module: str):
    vec2 = wp.types.vector(2, scalar)
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def pixel_of(tid: int, tiles_x: int) -> wp.vec3i:
        tile = tid // (TILE * TILE)
        local = tid - tile * (TILE * TILE)
        ty = tile // tiles_x
        tx = tile - ty * tiles_x
        return wp.vec3i(tx * TILE + local % TILE, ty * TILE + local // TILE, tile)

    @wp.func
    def splat_power(m: vec2, q: vec3, px: scalar, py: scalar) -> scalar:
        dx = px - m[0]
        dy = py - m[1]
        return scalar(-0.5) * (q[0] * dx * dx + q[2] * dy * dy) - q[1] * dx * dy

    @wp.kernel(enable_backward=False, module=module)
    def blend_forward_kernel(
        ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
        ids: wp.array(dtype=wp.int32),  # [M] sorted Gaussian indices
        means2d: wp.array(dtype=vec2),  # [N]
        conic: wp.array(dtype=vec3),  # [N]
        opacity: wp.array(dtype=scalar),  # [N]
        color: wp.array(dtype=vec3),  # [N]
        depth: wp.array(dtype=scalar),  # [N]
        background: vec3,
        width: int,
        height: int,
        tiles_x: int,
        want_weights: int,
        out_color: wp.array2d(dtype=vec3),  # [H, W]
        out_alpha: wp.array2d(dtype=scalar),  # [H, W]
        out_depth: wp.array2d(dtype=scalar),  # [H, W] expected depth Σ zαT / alpha
        out_T: wp.array2d(dtype=scalar),  # [H, W] final transmittance (for the backward)
        out_last: wp.array2d(dtype=wp.int32),  # [H, W] one past the last contributor in ids
        weights: wp.array(dtype=scalar),  # [N] Σ_p αT per Gaussian (only if want_weights)
    ):
        p = pixel_of(wp.tid(), tiles_x)
        if p[0] >= width or p[1] >= height:
            return
        px = scalar(p[0]) + scalar(0.5)
        py = scalar(p[1]) + scalar(0.5)
        start = ranges[p[2], 0]
        end = ranges[p[2], 1]
        T = scalar(1.0)
        C = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        S = scalar(0.0)
        last = start
        for k in range(start, end):
            g = ids[k]
            power = splat_power(means2d[g], conic[g], px, py)
            if power > scalar(0.0):
                continue
            alpha = wp.min(scalar(ALPHA_MAX), opacity[g] * wp.exp(power))
            if alpha < scalar(ALPHA_MIN):
                continue
            T_next = T * (scalar(1.0) - alpha)
            if T_next < scalar(T_MIN):
                break
            w = alpha * T
            C += w * color[g]
            S += w * depth[g]
            if want_weights != 0:
                wp.atomic_add(weights, g, w)
            T = T_next
            last = k + 1
        A = scalar(1.0) - T
        out_color[p[1], p[0]] = C + T * background
        out_alpha[p[1], p[0]] = A
        D = scalar(0.0)
        if A > scalar(0.0):
            D = S / A
        out_depth[p[1], p[0]] = D
        out_T[p[1], p[0]] = T
        out_last[p[1], p[0]] = last

    @wp.func_native(WARP_SUM)
    def warp_sum(x: scalar) -> scalar: ...

    @wp.func
    def warp_sum2(v: vec2) -> vec2:
        return vec2(warp_sum(v[0]), warp_sum(v[1]))

    @wp.func
    def warp_sum3(v: vec3) -> vec3:
        return vec3(warp_sum(v[0]), warp_sum(v[1]), warp_sum(v[2]))

    @wp.kernel(enable_backward=False, module=module)
    def blend_backward_kernel(
        ranges: wp.array2d(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=vec2),
        conic: wp.array(dtype=vec3),
        opacity: wp.array(dtype=scalar),
        color: wp.array(dtype=vec3),
        depth: wp.array(dtype=scalar),
        background: vec3,
        width: int,
        height: int,
        tiles_x: int,
        out_depth: wp.array2d(dtype=scalar),
        out_T: wp.array2d(dtype=scalar),
        out_last: wp.array2d(dtype=wp.int32),
        g_color: wp.array2d(dtype=vec3),  # [H, W] upstream dL/dcolor
        g_alpha: wp.array2d(dtype=scalar),  # [H, W] upstream dL/dalpha
        g_depth: wp.array2d(dtype=scalar),  # [H, W] upstream dL/ddepth
        d_means2d: wp.array(dtype=vec2),  # [N] accumulated dL/d(screen mean)
        d_conic: wp.array(dtype=vec3),  # [N]
        d_opacity: wp.array(dtype=scalar),  # [N]
        d_color: wp.array(dtype=vec3),  # [N]
        d_depth: wp.array(dtype=scalar),  # [N]
    ):
        # On the GPU the 32 lanes of a warp walk the same Gaussians in lockstep (the loop runs to the warp's
        # furthest last contributor; lanes past their own skip), so each Gaussian's gradient is summed over
        # the warp with shuffles and written with one atomic per warp instead of one per pixel.
        tid = wp.tid()
        p = pixel_of(tid, tiles_x)
        inside = p[0] < width and p[1] < height
        px = scalar(p[0]) + scalar(0.5)
        py = scalar(p[1]) + scalar(0.5)
        start = ranges[p[2], 0]
        zero = scalar(0.0)
        T = scalar(1.0)
        last = start
        gC = vec3(zero, zero, zero)
        gA = zero
        gS = zero
        if inside:
            T = out_T[p[1], p[0]]
            last = out_last[p[1], p[0]]
            gC = g_color[p[1], p[0]]
            gA = g_alpha[p[1], p[0]]
            A = scalar(1.0) - T
            if A > zero:
                # depth = S / A: route its gradient to S = Σ zαT and to A
                gD = g_depth[p[1], p[0]]
                gS = gD / A
                gA = gA - gD * out_depth[p[1], p[0]] / A
        # everything behind the current Gaussian, as seen through it: starts with the background term
        behind = T * (wp.dot(gC, background) - gA)
        count = warp_max(last - start)
        for j in range(count):
            k = start + count - 1 - j
            g = ids[k]
            m = means2d[g]
            q = conic[g]
            dx = px - m[0]
            dy = py - m[1]
            power = splat_power(m, q, px, py)  # the forward's exact expression: same skips, same α
            G = wp.exp(wp.min(power, zero))
            o = opacity[g]
            raw = o * G
            alpha = wp.min(scalar(ALPHA_MAX), raw)
            d_m = vec2(zero, zero)
            d_q = vec3(zero, zero, zero)
            d_o = zero
            d_c = vec3(zero, zero, zero)
            d_z = zero
            valid = k < last and power <= zero and alpha >= scalar(ALPHA_MIN)
            if valid:
                one_minus = scalar(1.0) - alpha
                T = T / one_minus
                w = alpha * T
                shade = wp.dot(color[g], gC) + depth[g] * gS
                d_c = w * gC
                d_z = w * gS
                g_alpha_k = T * shade - behind / one_minus
                behind += shade * w
                if raw < scalar(ALPHA_MAX):  # the clamp has zero derivative
                    d_o = g_alpha_k * G
                    gp = g_alpha_k * raw
                    d_q = vec3(scalar(-0.5) * dx * dx * gp, -dx * dy * gp, scalar(-0.5) * dy * dy * gp)
                    d_m = vec2(gp * (q[0] * dx + q[1] * dy), gp * (q[1] * dx + q[2] * dy))
            if warp_max(wp.where(valid, 1, 0)) > 0:
                d_m = warp_sum2(d_m)
                d_q = warp_sum3(d_q)
                d_o = warp_sum(d_o)
                d_c = warp_sum3(d_c)
                d_z = warp_sum(d_z)
                if lead_lane(tid) != 0:
                    wp.atomic_add(d_means2d, g, d_m)
                    wp.atomic_add(d_conic, g, d_q)
                    wp.atomic_add(d_opacity, g, d_o)
                    wp.atomic_add(d_color, g, d_c)
                    wp.atomic_add(d_depth, g, d_z)

    return blend_forward_kernel, blend_backward_kernel
