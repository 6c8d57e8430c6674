"""Alpha blending, front to back per pixel over its tile's sorted Gaussians (SPEC §2), and its
hand-written backward. The loop length depends on the data, which Warp's tape cannot replay, so the
backward walks the same list in reverse from the last contributor, rebuilding the transmittance by
dividing by (1 - α) (α ≤ 0.99, so at most a factor 100 per step).

Threads are laid out tile-major (one 16x16 tile = 256 consecutive threads = one GPU block), and a block
stages its tile's Gaussians in shared memory a batch at a time (see the block primitives below)."""
import warp as wp

from .binning import TILE, warp_lane, warp_lanes

ALPHA_MAX = 0.99  # α clamp: a single splat never makes a pixel fully opaque (keeps 1/(1-α) bounded)
ALPHA_MIN = 1.0 / 255.0  # contributions below one 8-bit level are skipped
T_MIN = 1e-4  # stop before a Gaussian that would drop transmittance below this
# below this power α = opacity·exp(power) < ALPHA_MIN whatever the opacity (<= 1, a sigmoid): exp(-5.5425) =
# 0.0039179 < 1/255 = 0.0039216, a margin far above float rounding (and CUDA's fast exp). Tested first, it skips the
# exp for the pixels of a tile that a splat does not reach; the same splats are blended as without it
POWER_CUT = -5.5425
WARP_COLS = 8  # a 32-lane warp covers an 8x4 patch of its 16x16 tile (a small splat meets fewer warps than
# gsplat's 16x2 rows, so the backward does fewer per-warp sums)


# Warp-level primitives as native snippets; on the CPU (one lane per block) they reduce to the identity.
WARP_ANY = """
#if defined(__CUDA_ARCH__)
    return __any_sync(0xffffffff, x);
#else
    return x;
#endif
"""
# The blending backward's per-Gaussian sums over a warp, 16 values at once (10 used): instead of a butterfly per
# value (5 shuffles each), each stage sends half of a lane's values to its partner and keeps the other half, so
# after the stages at offsets 16, 8, 4, 2 a lane holds one value's partial sum (value lane / 2) and the stage at
# offset 1 completes it: 8 + 4 + 2 + 1 + 1 = 16 shuffles for up to 16 values (a butterfly: 50 for 10), and the
# atomics that follow come from 10 lanes in one instruction instead of 10 in a row from one lane. The CPU
# (one lane per warp) never calls it.
def _transpose_sum_source() -> str:
    """WARP_TRANSPOSE_SUM's CUDA, written out with constant indices (a loop whose trip count halves per stage is
    not unrolled, and an indexed array then lives in local memory)."""
    lines = ["#if defined(__CUDA_ARCH__)", "    const int lane = threadIdx.x & 31;"]
    lines += [f"    {{ctype}} v{i} = x[{i}];" for i in range(16)]
    c = 8
    for o in (16, 8, 4, 2):  # partner offset; c: values kept after the stage (a lane with bit o keeps the upper half)
        lines.append(f"    {{{{ const bool up = (lane & {o}) != 0;")
        for i in range(c):
            lines.append(f"      v{i} = (up ? v{i + c} : v{i}) + __shfl_xor_sync(0xffffffff, up ? v{i} : v{i + c}, {o});")
        lines.append("    }}")
        c //= 2
    lines += ["    return v0 + __shfl_xor_sync(0xffffffff, v0, 1);", "#else", "    return x[0];", "#endif", ""]
    return "\n" + "\n".join(lines)


WARP_TRANSPOSE_SUM = _transpose_sum_source()


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
# float32 vectors staged as CUDA float4/float2: one 128/64-bit shared load per read instead of one per component
SLAB_VEC_CUDA = """
#if defined(__CUDA_ARCH__)
    __shared__ {cuda}{n} slab[{slots} * 256];
    {cuda}{n}* e = slab + slot * 256 + lane;
    if (write) *e = make_{cuda}{n}({pack});
    const {cuda}{n} r = *e;
    return wp::vec_t<{n}, {ctype}>({unpack});
#else
    static {ctype} slab[{slots} * {n}];  // plain scalars: a static of a class type would need a guard
    {ctype}* e = slab + slot * {n};
    if (write) for (int c = 0; c < {n}; ++c) e[c] = x[c];
    return wp::vec_t<{n}, {ctype}>({unpack_e});
#endif
"""
SLAB_VEC_ANY = """
#if defined(__CUDA_ARCH__)
    __shared__ {ctype} slab[{slots} * 256 * {n}];
    {ctype}* e = slab + (slot * 256 + lane) * {n};
#else
    static {ctype} slab[{slots} * {n}];
    {ctype}* e = slab + slot * {n};
#endif
    if (write) for (int c = 0; c < {n}; ++c) e[c] = x[c];
    return wp::vec_t<{n}, {ctype}>({unpack_e});
"""


def slab_vec_source(n: int, ctype: str, slots: int) -> str:
    unpack_e = ", ".join(f"e[{i}]" for i in range(n))
    if ctype == "float":
        comps = "xyzw"[:n]
        return SLAB_VEC_CUDA.format(cuda="float", n=n, ctype=ctype, slots=slots,
                                    pack=", ".join(f"x[{i}]" for i in range(n)),
                                    unpack=", ".join(f"r.{c}" for c in comps), unpack_e=unpack_e)
    return SLAB_VEC_ANY.format(n=n, ctype=ctype, slots=slots, unpack_e=unpack_e)


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


@wp.func_native(WARP_ANY)
def warp_any(x: int) -> int: ...


# The blending backward's per-batch gradient sums in shared memory: slot s (a staged Gaussian) holds its values
# k = 0..9 at [s * 11 + k] (an odd stride: the flush, one slot per lane, reads without bank conflicts). op 0 zeroes
# a value, 1 adds x (a shared atomic: the block's warps add to the same slot), 2 reads it. The CPU never calls it
# (one lane per warp adds to the global sums directly).
ACC = """
#if defined(__CUDA_ARCH__)
    __shared__ {ctype} acc[256 * 11];
    {ctype}* e = acc + slot * 11 + k;
    if (op == 0) {{ *e = ({ctype})0; return ({ctype})0; }}  // C casts: Warp's header defines float(x) as a macro
    if (op == 1) {{ atomicAdd(e, x); return ({ctype})0; }}
    return *e;
#else
    return x;
#endif
"""


# the largest x over a warp's lanes (a butterfly of 5 shuffles, every lane gets it); all 32 lanes must be active
WARP_MAX = """
#if defined(__CUDA_ARCH__)
    int v = x;
    for (int o = 16; o > 0; o >>= 1) v = max(v, __shfl_xor_sync(0xffffffff, v, o));
    return v;
#else
    return x;
#endif
"""


@wp.func_native(WARP_MAX)
def warp_max(x: int) -> int: ...



def make_blend(scalar, module: str, min_blocks=(0, 0)):
    """(forward, backward, forward on the CPU, backward on the CPU) kernels for ``scalar``; ``min_blocks``: CUDA
    __launch_bounds__ minimum resident blocks per SM of the first two (0: none), which caps their registers (65536 /
    (256 · blocks) per thread)."""
    vec2 = wp.types.vector(2, scalar)
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    vec16 = wp.types.vector(16, scalar)
    ctype = "double" if scalar == wp.float64 else "float"
    bounds = [{"launch_bounds": (TILE * TILE, b)} if b else {} for b in min_blocks]
    warp_w = WARP_COLS  # a compile-time constant of the kernels

    @wp.func
    def pixel_of(tid: int, tiles_x: int) -> wp.vec3i:
        tile = tid // (TILE * TILE)
        local = tid - tile * (TILE * TILE)
        ty = tile // tiles_x
        tx = tile - ty * tiles_x
        # local = warp * 32 + lane; the tile is a (16 / warp_w) x (32 * warp_w / 256) grid of warp_w x (32 / warp_w)
        # patches
        w = local // 32
        lane = local - w * 32
        wx = w % (TILE // warp_w)
        wy = w // (TILE // warp_w)
        lx = lane % warp_w
        ly = lane // warp_w
        return wp.vec3i(tx * TILE + wx * warp_w + lx, ty * TILE + wy * (32 // warp_w) + ly, tile)

    @wp.func
    def splat_power(a: vec4, qc: scalar, px: scalar, py: scalar) -> scalar:
        # a = (mean x, mean y, conic a, conic b): -½ dᵀQd at the pixel center (the forward's and backward's
        # one expression, so both make the same skips)
        dx = px - a[0]
        dy = py - a[1]
        return scalar(-0.5) * (a[2] * dx * dx + qc * dy * dy) - a[3] * dx * dy

    # the staged batch: per Gaussian (mean, conic a, b), (conic c, opacity), (color, depth) and its id, as
    # vectors (one 128/64/128-bit shared load each)
    @wp.func_native(slab_vec_source(4, ctype, 2))
    def slab4(slot: int, lane: int, x: vec4, write: int) -> vec4: ...

    @wp.func_native(slab_vec_source(2, ctype, 1))
    def slab2(slot: int, lane: int, x: vec2, write: int) -> vec2: ...

    @wp.func
    def stage_values(lane: int, a: vec4, b: vec2, c: vec4):
        slab4(0, lane, a, 1)
        slab2(0, lane, b, 1)
        slab4(1, lane, c, 1)

    @wp.func
    def staged_geometry(j: int) -> vec4:
        return slab4(0, j, vec4(), 0)

    @wp.func
    def staged_conic_c_opacity(j: int) -> vec2:
        return slab2(0, j, vec2(), 0)

    @wp.func
    def staged_color_depth(j: int) -> vec4:
        return slab4(1, j, vec4(), 0)

    @wp.func
    def stage_gaussian(k: int, lane: int, ids: wp.array(dtype=wp.int32), means2d: wp.array(dtype=vec2),
                       conic: wp.array(dtype=vec3), opacity: wp.array(dtype=scalar), color: wp.array(dtype=vec3),
                       depth: wp.array(dtype=scalar), want_depth: int):
        g = ids[k]
        m = means2d[g]
        q = conic[g]
        c = color[g]
        z = scalar(0.0)
        if want_depth != 0:
            z = depth[g]
        slab_id(0, lane, g, 1)
        stage_values(lane, vec4(m[0], m[1], q[0], q[1]), vec2(q[2], opacity[g]), vec4(c[0], c[1], c[2], z))

    @wp.func
    def blend_step(j: int, base: int, px: scalar, py: scalar, want_depth: int, want_weights: int,
                   weights: wp.array(dtype=scalar), T: scalar, C: vec3, S: scalar, last: int, done: int):
        """One staged splat over one pixel (front to back): the carried (T, C, S, last, done)."""
        co = staged_conic_c_opacity(j)
        power = splat_power(staged_geometry(j), co[0], px, py)
        if power <= scalar(0.0) and power >= scalar(POWER_CUT):
            alpha = wp.min(scalar(ALPHA_MAX), co[1] * wp.exp(power))
            if alpha >= scalar(ALPHA_MIN):
                T_next = T * (scalar(1.0) - alpha)
                if T_next < scalar(T_MIN):
                    done = 1
                else:
                    w = alpha * T
                    cz = staged_color_depth(j)
                    C += w * vec3(cz[0], cz[1], cz[2])
                    if want_depth != 0:
                        S += w * cz[3]
                    if want_weights != 0:
                        wp.atomic_add(weights, slab_id(0, j, 0, 0), w)
                    T = T_next
                    last = base + j + 1
        return T, C, S, last, done

    @wp.func
    def write_pixel(p: wp.vec3i, T: scalar, C: vec3, S: scalar, last: int, background: vec3, want_depth: int,
                    out_color: wp.array2d(dtype=vec3), out_alpha: wp.array2d(dtype=scalar),
                    out_depth: wp.array2d(dtype=scalar), out_T: wp.array2d(dtype=scalar),
                    out_last: wp.array2d(dtype=wp.int32)):
        """A blended pixel's outputs, and the state its backward reads (both forwards)."""
        A = scalar(1.0) - T
        out_color[p[1], p[0]] = C + T * background
        out_alpha[p[1], p[0]] = A
        if want_depth != 0:
            D = scalar(0.0)
            if A > scalar(0.0):
                D = S / A
            out_depth[p[1], p[0]] = D
        out_T[p[1], p[0]] = T
        out_last[p[1], p[0]] = last

    @wp.func
    def pixel_upstream(p: wp.vec3i, want_depth: int, out_T: wp.array2d(dtype=scalar),
                       out_depth: wp.array2d(dtype=scalar), g_color: wp.array2d(dtype=vec3),
                       g_alpha: wp.array2d(dtype=scalar), g_depth: wp.array2d(dtype=scalar)):
        """(T, dL/dC, dL/dA, dL/dS) of a pixel for the backward walk (both backwards): the final transmittance and
        the upstream gradients, the depth's routed to S and A."""
        zero = scalar(0.0)
        T = out_T[p[1], p[0]]
        gA = g_alpha[p[1], p[0]]
        gS = zero
        A = scalar(1.0) - T
        if want_depth != 0 and A > zero:
            # depth = S / A: route its gradient to S = Σ zαT and to A
            gD = g_depth[p[1], p[0]]
            gS = gD / A
            gA = gA - gD * out_depth[p[1], p[0]] / A
        return T, g_color[p[1], p[0]], gA, gS

    @wp.kernel(enable_backward=False, module=module, **bounds[0])
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
        want_depth: int,  # 0: no expected depth (out_depth is not written)
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
                stage_gaussian(base + lane, lane, ids, means2d, conic, opacity, color, depth, want_depth)
            sync_block(0)
            # no break/continue: Warp writes loop-carried variables back at the end of the body, which a
            # break skips (a `done = 1; break` was lost, and every block walked its whole list); the loop's own
            # condition lets a saturated pixel leave the batch (a warp leaves once all its lanes have)
            nb = wp.min(B, end - base)
            j = int(0)
            while j < nb and done == 0:
                T, C, S, last, done = blend_step(j, base, px, py, want_depth, want_weights, weights, T, C, S, last, done)
                j += 1
            sync_block(0)  # the next batch overwrites the slab
        if inside:
            write_pixel(p, T, C, S, last, background, want_depth, out_color, out_alpha, out_depth, out_T, out_last)

    @wp.func_native(WARP_TRANSPOSE_SUM.format(ctype=ctype))
    def warp_transpose_sum(x: vec16) -> scalar: ...

    @wp.func_native(ACC.format(ctype=ctype))
    def batch_acc(slot: int, k: int, x: scalar, op: int) -> scalar: ...

    @wp.func
    def add_grad(k: int, g: int, n: int, value: scalar, grad_kept: wp.array(dtype=scalar),
                 grad_geo: wp.array(dtype=scalar)):
        """Adds value k of Gaussian g: 0-1 screen mean, 2-4 conic, 5 opacity, 6-8 color, 9 depth; ``grad_kept`` starts
        [means2d (N, 2) | color (N, 3)] and ``grad_geo`` is [conic (N, 3) | opacity (N) | depth (N)], flat. The one
        place that maps a value to its address."""
        if k < 2:
            wp.atomic_add(grad_kept, 2 * g + k, value)
        elif k < 5:
            wp.atomic_add(grad_geo, 3 * g + k - 2, value)
        elif k == 5:
            wp.atomic_add(grad_geo, 3 * n + g, value)
        elif k < 9:
            wp.atomic_add(grad_kept, 2 * n + 3 * g + k - 6, value)
        else:
            wp.atomic_add(grad_geo, 4 * n + g, value)

    @wp.func
    def add_grads(g: int, n: int, v: vec16, want_depth: int, grad_kept: wp.array(dtype=scalar),
                  grad_geo: wp.array(dtype=scalar)):
        """Every value of Gaussian g from one lane. The loop has a constant trip count, so Warp unrolls it and each
        v[k] is a constant index (a dynamic one would put v in local memory)."""
        for k in range(9):
            add_grad(k, g, n, v[k], grad_kept, grad_geo)
        if want_depth != 0:
            add_grad(9, g, n, v[9], grad_kept, grad_geo)

    @wp.kernel(enable_backward=False, module=module, **bounds[1])
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
        want_depth: int,
        out_depth: wp.array2d(dtype=scalar),
        out_T: wp.array2d(dtype=scalar),
        out_last: wp.array2d(dtype=wp.int32),
        g_color: wp.array2d(dtype=vec3),  # [H, W] upstream dL/dcolor
        g_alpha: wp.array2d(dtype=scalar),  # [H, W] upstream dL/dalpha
        g_depth: wp.array2d(dtype=scalar),  # [H, W] upstream dL/ddepth (read only if want_depth)
        grad_kept: wp.array(dtype=scalar),  # [>= 5N] accumulated dL/d(screen mean) [N, 2], then dL/dcolor [N, 3]
        grad_geo: wp.array(dtype=scalar),  # [5N] accumulated dL/d(conic) [N, 3], then opacity [N], depth [N]
    ):
        # On the GPU all lanes of a block walk the same Gaussians in lockstep (the loop runs from the block's
        # furthest last contributor; lanes past their own skip), so each Gaussian's gradient is summed over
        # a warp with shuffles, over the block's warps in shared memory, and written with one atomic per value and
        # tile instead of one per pixel.
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
            T, gC, gA, gS = pixel_upstream(p, want_depth, out_T, out_depth, g_color, g_alpha, g_depth)
            last = out_last[p[1], p[0]]
        n = means2d.shape[0]
        n_values = 9 + want_depth  # the sums per Gaussian (add_grad's numbering)
        # everything behind the current Gaussian, as seen through it: starts with the background term
        behind = T * (wp.dot(gC, background) - gA)
        # the block walks back from its furthest last contributor, a batch of Gaussians at a time (as forward)
        lane = lane_id()
        B = batch_size()
        many_lanes = wp.where(warp_lanes() == 1, 0, 1)  # the GPU: warps of 32 lanes sum through shared memory
        top = block_max(last)
        # a warp walks only from its own furthest last contributor (its lanes stay in step for the shuffle sums;
        # every lane of the block still helps stage each batch): on fitted beer 8% of the block's walk is past
        # every lane of its warp, but those were cheap steps (no lane contributes, no sums): about 1% of the time
        warp_top = warp_max(last)
        for b in range((top - start + B - 1) // B):
            hi = top - b * B
            lo = wp.max(start, hi - B)
            staged = hi - 1 - lane >= lo
            if staged:  # slot i holds list entry hi - 1 - i: the walk order
                stage_gaussian(hi - 1 - lane, lane, ids, means2d, conic, opacity, color, depth, want_depth)
                if many_lanes != 0:
                    for z in range(10):
                        batch_acc(lane, z, zero, 0)
            sync_block(0)
            for j in range(wp.max(0, hi - warp_top), hi - lo):  # entry k = hi - 1 - j < warp_top
                k = hi - 1 - j
                a4 = staged_geometry(j)
                co = staged_conic_c_opacity(j)
                dx = px - a4[0]
                dy = py - a4[1]
                power = splat_power(a4, co[0], px, py)  # the forward's exact expression: same skips, same α
                G = zero  # beyond the cut the forward skipped it (α < ALPHA_MIN): no exp
                if power >= scalar(POWER_CUT):
                    G = wp.exp(wp.min(power, zero))
                raw = co[1] * G
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
                    cz = staged_color_depth(j)
                    shade = cz[0] * gC[0] + cz[1] * gC[1] + cz[2] * gC[2] + cz[3] * gS
                    d_c = w * gC
                    d_z = w * gS
                    g_alpha_k = T * shade - behind / one_minus
                    behind += shade * w
                    if raw < scalar(ALPHA_MAX):  # the clamp has zero derivative
                        d_o = g_alpha_k * G
                        gp = g_alpha_k * raw
                        d_q = vec3(scalar(-0.5) * dx * dx * gp, -dx * dy * gp, scalar(-0.5) * dy * dy * gp)
                        d_m = vec2(gp * (a4[2] * dx + a4[3] * dy), gp * (a4[3] * dx + co[0] * dy))
                if warp_any(wp.where(valid, 1, 0)) != 0:
                    g = slab_id(0, j, 0, 0)
                    v = vec16(d_m[0], d_m[1], d_q[0], d_q[1], d_q[2], d_o, d_c[0], d_c[1], d_c[2], d_z,
                              zero, zero, zero, zero, zero, zero)
                    if many_lanes == 0:  # the CPU: the lane is the warp
                        add_grads(g, n, v, want_depth, grad_kept, grad_geo)
                    else:  # the warp's sums go to the batch's shared sums (global atomics once per tile below)
                        total = warp_transpose_sum(v)  # value lane / 2, in lanes 2k and 2k + 1
                        lane_w = warp_lane()
                        k = lane_w // 2
                        if lane_w % 2 == 0 and k < n_values:
                            batch_acc(j, k, total, 1)
            if many_lanes != 0:
                sync_block(0)
                if staged:  # each lane adds its slot's sums to the Gaussian's gradient: one atomic per value and
                    g = slab_id(0, lane, 0, 0)  # tile instead of one per value and warp
                    for z in range(10):
                        if z < n_values:
                            acc_v = batch_acc(lane, z, zero, 2)
                            if acc_v != zero:
                                add_grad(z, g, n, acc_v, grad_kept, grad_geo)
            sync_block(0)  # the next batch overwrites the slab and its sums

    # --- the CPU's walks: one pixel at a time, so nothing is staged. The kernels above on the CPU run one lane per
    # block and stage every Gaussian of a pixel's list (all of its values, through the slab) before testing it; these
    # read a Gaussian's mean and conic first and the rest only where it is blended: the same float operations in the
    # same order, so the same images, T, last and gradients (tests/test_raster.py compares the two bit for bit).
    @wp.kernel(enable_backward=False, module=module)
    def blend_forward_cpu_kernel(
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
        want_depth: int,
        want_weights: int,
        out_color: wp.array2d(dtype=vec3),  # [H, W]
        out_alpha: wp.array2d(dtype=scalar),  # [H, W]
        out_depth: wp.array2d(dtype=scalar),  # [H, W]
        out_T: wp.array2d(dtype=scalar),  # [H, W]
        out_last: wp.array2d(dtype=wp.int32),  # [H, W]
        weights: wp.array(dtype=scalar),  # [N]
        first_thread: int,  # this launch's part of the image starts at thread first_thread (raster.blend splits it)
    ):
        p = pixel_of(wp.tid() + first_thread, tiles_x)
        if p[0] >= width or p[1] >= height:
            return
        px = scalar(p[0]) + scalar(0.5)
        py = scalar(p[1]) + scalar(0.5)
        end = ranges[p[2], 1]
        T = scalar(1.0)
        C = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        S = scalar(0.0)
        k = ranges[p[2], 0]
        last = k
        while k < end:
            g = ids[k]
            m = means2d[g]
            q = conic[g]
            power = splat_power(vec4(m[0], m[1], q[0], q[1]), q[2], px, py)
            if power <= scalar(0.0) and power >= scalar(POWER_CUT):
                alpha = wp.min(scalar(ALPHA_MAX), opacity[g] * wp.exp(power))
                if alpha >= scalar(ALPHA_MIN):
                    T_next = T * (scalar(1.0) - alpha)
                    if T_next < scalar(T_MIN):
                        k = end  # saturated: this one and every one behind it are left out
                    else:
                        w = alpha * T
                        C += w * color[g]
                        if want_depth != 0:
                            S += w * depth[g]
                        if want_weights != 0:
                            wp.atomic_add(weights, g, w)
                        T = T_next
                        last = k + 1
            k += 1
        write_pixel(p, T, C, S, last, background, want_depth, out_color, out_alpha, out_depth, out_T, out_last)

    @wp.kernel(enable_backward=False, module=module)
    def blend_backward_cpu_kernel(
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
        want_depth: int,
        out_depth: wp.array2d(dtype=scalar),
        out_T: wp.array2d(dtype=scalar),
        out_last: wp.array2d(dtype=wp.int32),
        g_color: wp.array2d(dtype=vec3),  # [H, W] upstream dL/dcolor
        g_alpha: wp.array2d(dtype=scalar),  # [H, W] upstream dL/dalpha
        g_depth: wp.array2d(dtype=scalar),  # [H, W] upstream dL/ddepth (read only if want_depth)
        grad_kept: wp.array(dtype=scalar),  # as blend_backward_kernel's
        grad_geo: wp.array(dtype=scalar),
        first_thread: int,  # as blend_forward_cpu_kernel's (each part of the image sums into its own gradients)
    ):
        p = pixel_of(wp.tid() + first_thread, tiles_x)
        if p[0] >= width or p[1] >= height:
            return
        px = scalar(p[0]) + scalar(0.5)
        py = scalar(p[1]) + scalar(0.5)
        start = ranges[p[2], 0]
        zero = scalar(0.0)
        T, gC, gA, gS = pixel_upstream(p, want_depth, out_T, out_depth, g_color, g_alpha, g_depth)
        n = means2d.shape[0]
        behind = T * (wp.dot(gC, background) - gA)
        k = out_last[p[1], p[0]] - 1
        while k >= start:
            g = ids[k]
            m = means2d[g]
            q = conic[g]
            a4 = vec4(m[0], m[1], q[0], q[1])
            power = splat_power(a4, q[2], px, py)
            if power <= zero and power >= scalar(POWER_CUT):
                G = wp.exp(power)
                raw = opacity[g] * G
                alpha = wp.min(scalar(ALPHA_MAX), raw)
                if alpha >= scalar(ALPHA_MIN):
                    dx = px - a4[0]
                    dy = py - a4[1]
                    one_minus = scalar(1.0) - alpha
                    T = T / one_minus
                    w = alpha * T
                    c = color[g]
                    z = zero
                    if want_depth != 0:
                        z = depth[g]
                    shade = c[0] * gC[0] + c[1] * gC[1] + c[2] * gC[2] + z * gS
                    d_c = w * gC
                    d_z = w * gS
                    g_alpha_k = T * shade - behind / one_minus
                    behind += shade * w
                    d_m = vec2(zero, zero)
                    d_q = vec3(zero, zero, zero)
                    d_o = zero
                    if raw < scalar(ALPHA_MAX):  # the clamp has zero derivative
                        d_o = g_alpha_k * G
                        gp = g_alpha_k * raw
                        d_q = vec3(scalar(-0.5) * dx * dx * gp, -dx * dy * gp, scalar(-0.5) * dy * dy * gp)
                        d_m = vec2(gp * (a4[2] * dx + a4[3] * dy), gp * (a4[3] * dx + q[2] * dy))
                    v = vec16(d_m[0], d_m[1], d_q[0], d_q[1], d_q[2], d_o, d_c[0], d_c[1], d_c[2], d_z,
                              zero, zero, zero, zero, zero, zero)
                    add_grads(g, n, v, want_depth, grad_kept, grad_geo)
            k -= 1

    return blend_forward_kernel, blend_backward_kernel, blend_forward_cpu_kernel, blend_backward_cpu_kernel
