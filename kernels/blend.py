"""Alpha blending, front to back per pixel over its tile's sorted Gaussians (SPEC §2), and its
hand-written backward. The loop length depends on the data, which Warp's tape cannot replay, so the
backward walks the same list in reverse from the last contributor, rebuilding the transmittance by
dividing by (1 - α) (α ≤ 0.99, so at most a factor 100 per step).

Threads are laid out tile-major (one 16x16 tile = 256 consecutive threads = one GPU block), and a block
stages its tile's Gaussians in shared memory a batch at a time (see the block primitives below)."""
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


# Block-level primitives for the batched blending loops. On the GPU a block (one 16x16 tile, 256 threads) loads
# a batch of up to 256 of its Gaussians into shared memory with one coalesced gather, then every thread walks
# the batch from there (gsplat's scheme; Warp has no shared-memory scalar API outside tiles). On the CPU a block
# runs one lane, so a batch holds one Gaussian and the same code walks the list one by one.
LANE = """
#if defined(__CUDA_ARCH__)
    return threadIdx.x;
#else
    return 0;
#endif
"""
BATCH = """
#if defined(__CUDA_ARCH__)
    return blockDim.x;
#else
    return 1;
#endif
"""
SYNC = """
#if defined(__CUDA_ARCH__)
    __syncthreads();
#endif
    return x;
"""
BLOCK_ALL = """
#if defined(__CUDA_ARCH__)
    return __syncthreads_and(x);
#else
    return x;
#endif
"""
BLOCK_MAX = """
#if defined(__CUDA_ARCH__)
    __shared__ int block_max_v;
    if (threadIdx.x == 0) block_max_v = x;
    __syncthreads();
    atomicMax(&block_max_v, x);
    __syncthreads();
    int r = block_max_v;
    __syncthreads();
    return r;
#else
    return x;
#endif
"""
# one shared slab per element type: slot s of lane i lives at [s * 256 + i] (CPU: one lane, a static slab)
SLAB = """
#if defined(__CUDA_ARCH__)
    __shared__ {ctype} slab[{slots} * 256];
    {ctype}* e = slab + slot * 256 + lane;
#else
    static {ctype} slab[{slots}];
    {ctype}* e = slab + slot;
#endif
    if (write) *e = x;
    return *e;
"""
SLOTS = 10  # per Gaussian: mean (2), conic (3), opacity, color (3), depth


@wp.func_native(WARP_MAX)
def warp_max(x: int) -> int: ...


@wp.func_native(LANE)
def lane_id() -> int: ...


@wp.func_native(BATCH)
def batch_size() -> int: ...


@wp.func_native(SYNC)
def sync_block(x: int) -> int: ...


@wp.func_native(BLOCK_ALL)
def block_all(x: int) -> int: ...


@wp.func_native(BLOCK_MAX)
def block_max(x: int) -> int: ...


@wp.func_native(SLAB.format(ctype="wp::int32", slots=1))
def slab_id(slot: int, lane: int, x: int, write: int) -> int: ...


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

    @wp.func_native(SLAB.format(ctype="wp::float64" if scalar == wp.float64 else "wp::float32", slots=SLOTS))
    def slab(slot: int, lane: int, x: scalar, write: int) -> scalar: ...

    @wp.func
    def stage_gaussian(k: int, lane: int, ids: wp.array(dtype=wp.int32), means2d: wp.array(dtype=vec2),
                       conic: wp.array(dtype=vec3), opacity: wp.array(dtype=scalar), color: wp.array(dtype=vec3),
                       depth: wp.array(dtype=scalar)):
        g = ids[k]
        m = means2d[g]
        q = conic[g]
        c = color[g]
        slab_id(0, lane, g, 1)
        slab(0, lane, m[0], 1)
        slab(1, lane, m[1], 1)
        slab(2, lane, q[0], 1)
        slab(3, lane, q[1], 1)
        slab(4, lane, q[2], 1)
        slab(5, lane, opacity[g], 1)
        slab(6, lane, c[0], 1)
        slab(7, lane, c[1], 1)
        slab(8, lane, c[2], 1)
        slab(9, lane, depth[g], 1)

    @wp.func
    def staged_mean(j: int) -> vec2:
        return vec2(slab(0, j, scalar(0.0), 0), slab(1, j, scalar(0.0), 0))

    @wp.func
    def staged_conic(j: int) -> vec3:
        return vec3(slab(2, j, scalar(0.0), 0), slab(3, j, scalar(0.0), 0), slab(4, j, scalar(0.0), 0))

    @wp.func
    def staged_color(j: int) -> vec3:
        return vec3(slab(6, j, scalar(0.0), 0), slab(7, j, scalar(0.0), 0), slab(8, j, scalar(0.0), 0))

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
        # Every thread of the block stays to the end (the batches need all of them to load and sync); threads
        # outside the image or already saturated only help load. The block stops when all are done.
        p = pixel_of(wp.tid(), tiles_x)
        inside = p[0] < width and p[1] < height
        px = scalar(p[0]) + scalar(0.5)
        py = scalar(p[1]) + scalar(0.5)
        start = ranges[p[2], 0]
        end = ranges[p[2], 1]
        lane = lane_id()
        B = batch_size()
        T = scalar(1.0)
        C = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        S = scalar(0.0)
        last = start
        done = int(0)
        if not inside:
            done = 1
        for base in range(start, end, B):
            if block_all(done) != 0:
                break
            if base + lane < end:
                stage_gaussian(base + lane, lane, ids, means2d, conic, opacity, color, depth)
            sync_block(0)
            # no break/continue: Warp writes loop-carried variables back at the end of the body, which a
            # break skips (a `done = 1; break` was lost, and every block walked its whole list)
            for j in range(wp.min(B, end - base)):
                if done == 0:
                    power = splat_power(staged_mean(j), staged_conic(j), px, py)
                    if power <= scalar(0.0):
                        alpha = wp.min(scalar(ALPHA_MAX), slab(5, j, scalar(0.0), 0) * wp.exp(power))
                        if alpha >= scalar(ALPHA_MIN):
                            T_next = T * (scalar(1.0) - alpha)
                            if T_next < scalar(T_MIN):
                                done = 1
                            else:
                                w = alpha * T
                                C += w * staged_color(j)
                                S += w * slab(9, j, scalar(0.0), 0)
                                if want_weights != 0:
                                    wp.atomic_add(weights, slab_id(0, j, 0, 0), w)
                                T = T_next
                                last = base + j + 1
            sync_block(0)  # the next batch overwrites the slab
        if inside:
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
        # On the GPU all lanes of a block walk the same Gaussians in lockstep (the loop runs from the block's
        # furthest last contributor; lanes past their own skip), so each Gaussian's gradient is summed over
        # a warp with shuffles and written with one atomic per warp instead of one per pixel.
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
        # the block walks back from its furthest last contributor, a batch of Gaussians at a time (as forward)
        lane = lane_id()
        B = batch_size()
        top = block_max(last)
        for b in range((top - start + B - 1) // B):
            hi = top - b * B
            lo = wp.max(start, hi - B)
            if hi - 1 - lane >= lo:  # slot i holds list entry hi - 1 - i: the walk order
                stage_gaussian(hi - 1 - lane, lane, ids, means2d, conic, opacity, color, depth)
            sync_block(0)
            for j in range(hi - lo):
                k = hi - 1 - j
                m = staged_mean(j)
                q = staged_conic(j)
                dx = px - m[0]
                dy = py - m[1]
                power = splat_power(m, q, px, py)  # the forward's exact expression: same skips, same α
                G = wp.exp(wp.min(power, zero))
                raw = slab(5, j, zero, 0) * G
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
                    shade = wp.dot(staged_color(j), gC) + slab(9, j, zero, 0) * gS
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
                        g = slab_id(0, j, 0, 0)
                        wp.atomic_add(d_means2d, g, d_m)
                        wp.atomic_add(d_conic, g, d_q)
                        wp.atomic_add(d_opacity, g, d_o)
                        wp.atomic_add(d_color, g, d_c)
                        wp.atomic_add(d_depth, g, d_z)
            sync_block(0)  # the next batch overwrites the slab

    return blend_forward_kernel, blend_backward_kernel
