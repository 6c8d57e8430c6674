"""Tile binning (SPEC §2): the Gaussians are first put in depth order (one radix sort of N float32 depths);
then one int32 key per (Gaussian, touched 16x16 tile) = the tile id is placed in that order (each Gaussian's keys
at its depth rank's offset; the threads still take the Gaussians in index order) and stably radix sorted on the tile bits only, which leaves each tile's list in depth order, and the [start, end) range
of each tile is found in the sorted list. Sorting N depths plus ~12-bit tile keys moves far fewer bytes than
sorting (tile << 32 | depth) int64 keys, and the key buffers take 16 instead of 24 bytes per intersection.
float32 inputs only (the float64 path passes float32 copies), so one module serves both scalar types; nothing
here is differentiable.

Which tiles: a Gaussian is binned into the tiles of its 3σ box (SPEC §2) whose rectangle of pixel centers
meets its visible ellipse dᵀQd <= k2 (α >= 1/255, with a margin). The tiles left out hold only pixels the
blending would skip, so the image is exactly that of plain 3σ-box binning (the tests check it against the
brute-force reference); far fewer keys are sorted and far fewer splats are walked per pixel. The test is done
one tile row at a time, in closed form: the band of the row's pixel-center rows cuts the ellipse in a convex
piece whose x-extent [xl, xr] is found from the ellipse's leftmost/rightmost point in the band (float64, from
the float32 conic: its products are exact there), and the row's tiles are those whose pixel-center columns
meet [xl, xr]. That is the per-tile test of the exact minimum over the tile's pixel-center rectangle, for a
whole row at once.

Work layout (load balance): a fitted scene has a few Gaussians covering thousands of tiles among many
covering one or two. One thread per Gaussian would leave a warp waiting on its largest one, so the work is
cut into items of one tile row by at most CHUNK tiles: a Gaussian with at most SOLO_ITEMS items is binned by
its own thread; the larger ones of a warp pool their items and the warp's 32 lanes take them in rounds
(each lane finds its item's owner by a binary search over the warp's scan of item counts, and an item's
keys go after those of its owner's earlier items: a segmented scan of the round's key counts). On the CPU a
"warp" is one lane, so the same code bins every Gaussian by its own thread."""
import warp as wp

TILE = 16  # tile edge in pixels (graphdeco/gsplat)
CHUNK = 16  # tiles of one row per work item
SOLO_ITEMS = 2  # Gaussians with at most this many items are binned by their own thread

# Warp-level primitives as native snippets (full-warp masks: every launch pads its thread count to a
# multiple of 32 and no thread leaves before the cooperative part); on the CPU a warp has one lane.
LANES = """
#if defined(__CUDA_ARCH__)
    return 32;
#else
    return 1;
#endif
"""
LANE = """
#if defined(__CUDA_ARCH__)
    return threadIdx.x & 31;
#else
    return 0;
#endif
"""
SCAN = """
#if defined(__CUDA_ARCH__)
    const int lane = threadIdx.x & 31;
    for (int o = 1; o < 32; o <<= 1) {
        const int y = __shfl_up_sync(0xffffffffu, x, o);
        if (lane >= o) x += y;
    }
#endif
    return x;
"""
SHFL = """
#if defined(__CUDA_ARCH__)
    return __shfl_sync(0xffffffffu, x, src & 31);
#else
    return x;
#endif
"""
OWNER = """
#if defined(__CUDA_ARCH__)
    int lo = 0;
    for (int s = 16; s > 0; s >>= 1) {
        const int v = __shfl_sync(0xffffffffu, incl, lo + s - 1);
        if (v <= t) lo += s;
    }
    return lo;
#else
    return 0;
#endif
"""


@wp.func_native(LANES)
def warp_lanes() -> int: ...


@wp.func_native(LANE)
def warp_lane() -> int: ...


@wp.func_native(SCAN)
def warp_scan(x: int) -> int:
    """Inclusive prefix sum over the warp's lanes."""
    ...


@wp.func_native(SHFL)
def warp_shfl(x: int, src: int) -> int: ...


@wp.func_native(SHFL)
def warp_shfl64(x: wp.float64, src: int) -> wp.float64: ...


@wp.func_native(OWNER)
def warp_owner(incl: int, t: int) -> int:
    """The lane whose items hold the warp's item t: the number of lanes whose inclusive item count is <= t."""
    ...


geo_t = wp.types.vector(9, wp.float64)  # u, v, qb, 1/qa, det (0: no ellipse, whole rows), qa·k2, xmax, ymax, ys


@wp.func
def visible_level(opacity: float) -> float:
    # α = min(0.99, o·exp(-½ dᵀQd)) >= 1/255  <=>  dᵀQd <= 2 ln(255 o); the margin absorbs float32 rounding so
    # that the tiles dropped here only ever hold pixels the blending would skip anyway
    return 2.0 * wp.log(255.0 * opacity) * (1.0 + 1e-4) + 1e-3


@wp.func
def bin_setup(m: wp.vec2, r: int, q: wp.vec3, o: float, tiles_x: int, tiles_y: int, all_tiles: int):
    """The binning geometry of one Gaussian, its tile rectangle (x0, x1, y0, y1) and its number of work items
    (0: not visible). The rectangle is the 3σ box shrunk to the bounding box of the visible ellipse
    (|dx| <= xmax = sqrt(k2 Σxx), Σ = Q⁻¹: Σxx = Qyy / det Q, no Σ2D buffer needed)."""
    zero = wp.float64(0.0)
    u = wp.float64(m[0])
    v = wp.float64(m[1])
    qa = wp.float64(q[0])
    qb = wp.float64(q[1])
    qc = wp.float64(q[2])
    k2 = wp.float64(visible_level(wp.max(o, 1.0 / 255.0)))
    rf = wp.float64(r)
    det = qa * qc - qb * qb  # exact products of float32 values: one rounding
    inv_qa = zero
    xmax = rf
    ymax = rf
    ys = zero
    if det > zero and qa > zero and qc > zero and all_tiles == 0:
        inv_qa = wp.float64(1.0) / qa
        xmax = wp.sqrt(k2 * qc / det)
        ymax = wp.sqrt(k2 * qa / det)
        ys = -qb * xmax / qc  # y of the ellipse's rightmost point (the leftmost one is at -ys)
    else:
        det = zero  # degenerate conic (or brute-force binning): whole rows of the box
    rx = wp.min(rf, xmax)
    ry = wp.min(rf, ymax)
    tsz = wp.float64(16.0)  # TILE (wp.float64(TILE) would retype the TILE constant for later uses)
    x0 = int(wp.clamp(wp.floor((u - rx) / tsz), zero, wp.float64(tiles_x)))
    x1 = int(wp.clamp(wp.floor((u + rx) / tsz) + wp.float64(1.0), zero, wp.float64(tiles_x)))
    y0 = int(wp.clamp(wp.floor((v - ry) / tsz), zero, wp.float64(tiles_y)))
    y1 = int(wp.clamp(wp.floor((v + ry) / tsz) + wp.float64(1.0), zero, wp.float64(tiles_y)))
    if all_tiles != 0:
        x0 = 0
        x1 = tiles_x
        y0 = 0
        y1 = tiles_y
    items = int(0)
    if r > 0 and (all_tiles != 0 or o * 255.0 >= 1.0) and x1 > x0 and y1 > y0:
        items = (y1 - y0) * ((x1 - x0 + CHUNK - 1) // CHUNK)
    return geo_t(u, v, qb, inv_qa, det, qa * k2, xmax, ymax, ys), wp.vec4i(x0, x1, y0, y1), items


@wp.func
def row_span(geo: geo_t, ty: int, cx0: int, cx1: int, width: int, height: int) -> wp.vec2i:
    """[a, b): the tiles of [cx0, cx1) in tile row ty whose pixel-center rectangle meets the visible ellipse."""
    det = geo[4]
    a = cx0
    b = cx1
    if det > wp.float64(0.0):
        u = geo[0]
        v = geo[1]
        half = wp.float64(0.5)
        tsz = wp.float64(16.0)  # TILE (wp.float64(TILE) would retype the TILE constant for later uses)
        ylo = wp.float64(ty * TILE) - v + half
        yhi = wp.float64(wp.min(ty * TILE + TILE, height)) - v - half
        ymax = geo[7]
        ya = wp.max(ylo, -ymax)
        yb = wp.min(yhi, ymax)
        a = cx1
        if ya <= yb:
            # the ellipse's x-extent within the band: its right edge x(y) is concave, the left one convex, so
            # each extreme is at the clamped y of the ellipse's own rightmost / leftmost point
            qb = geo[2]
            ys = geo[8]
            yr = wp.clamp(ys, ya, yb)
            yl = wp.clamp(-ys, ya, yb)
            xr = (-qb * yr + wp.sqrt(wp.max(geo[5] - det * yr * yr, wp.float64(0.0)))) * geo[3]
            xl = (-qb * yl - wp.sqrt(wp.max(geo[5] - det * yl * yl, wp.float64(0.0)))) * geo[3]
            # tile tx spans pixel centers [16 tx + 0.5, min(16 tx + 16, width) - 0.5]
            fa = wp.ceil((xl + u - (tsz - half)) / tsz)
            a = int(wp.clamp(fa, wp.float64(cx0), wp.float64(cx1)))
            fb = wp.floor((xr + u - half) / tsz) + wp.float64(1.0)
            b = int(wp.clamp(fb, wp.float64(a), wp.float64(cx1)))
            last = (width + TILE - 1) // TILE - 1
            if a == last and a < b and wp.float64(width) - half - u < xl:  # the narrower last column
                a = b
        b = wp.max(a, b)
    return wp.vec2i(a, b)


@wp.func
def item_span(geo: geo_t, rect: wp.vec4i, chunks: int, li: int, width: int, height: int) -> wp.vec3i:
    """Item li of a Gaussian (row-major over its rows and CHUNK-tile pieces): (tile row, first tile, end)."""
    cr = li // chunks
    ty = rect[2] + cr
    cx0 = rect[0] + (li - cr * chunks) * CHUNK
    s = row_span(geo, ty, cx0, wp.min(cx0 + CHUNK, rect[1]), width, height)
    return wp.vec3i(ty, s[0], s[1])


@wp.func
def owner_geo(geo: geo_t, owner: int) -> geo_t:
    return geo_t(warp_shfl64(geo[0], owner), warp_shfl64(geo[1], owner), warp_shfl64(geo[2], owner),
                 warp_shfl64(geo[3], owner), warp_shfl64(geo[4], owner), warp_shfl64(geo[5], owner),
                 warp_shfl64(geo[6], owner), warp_shfl64(geo[7], owner), warp_shfl64(geo[8], owner))


@wp.func
def owner_rect(rect: wp.vec4i, owner: int) -> wp.vec4i:
    return wp.vec4i(warp_shfl(rect[0], owner), warp_shfl(rect[1], owner), warp_shfl(rect[2], owner),
                    warp_shfl(rect[3], owner))


@wp.func
def chunks_of(rect: wp.vec4i) -> int:
    return wp.max((rect[1] - rect[0] + CHUNK - 1) // CHUNK, 1)


@wp.func
def round_share(c: int, p_incl: int, p_items: int, base: int) -> int:
    """Warp-collective: this lane's Gaussian's share of the round's per-item values c (its pooled items that
    fall in round [base, base + lanes))."""
    lanes = warp_lanes()
    c_incl = warp_scan(c)
    f = wp.max(p_incl - p_items, base) - base
    e = wp.min(p_incl, base + lanes) - base
    hi = warp_shfl(c_incl, wp.clamp(e - 1, 0, lanes - 1))
    lo = warp_shfl(c_incl - c, wp.clamp(f, 0, lanes - 1))
    share = int(0)
    if f < e:
        share = hi - lo
    return share


@wp.kernel(enable_backward=False, module="tlvg_binning")
def count_tiles_kernel(
    means2d: wp.array(dtype=wp.vec2),  # [N] float32 copy of the screen means
    radii: wp.array(dtype=wp.int32),  # [N]
    conic: wp.array(dtype=wp.vec3),  # [N] Σ2D⁻¹ (a, b, c)
    opacity: wp.array(dtype=float),  # [N]
    depth: wp.array(dtype=float),  # [N] float32 view depths
    n: int,
    tiles_x: int,
    tiles_y: int,
    width: int,
    height: int,
    all_tiles: int,  # 1: every visible Gaussian touches every tile (brute-force reference binning)
    counts: wp.array(dtype=wp.int32),  # [N] out (their total is the last of their scan in depth order)
    depth_keys: wp.array(dtype=float),  # [2N] out: [:N] the depths, the depth sort's keys
    order: wp.array(dtype=wp.int32),  # [2N] out: [:N] the Gaussian ids, its values
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2] out: zeroed (tile_ranges_kernel fills the non-empty ones)
):
    # launched on max(N, tiles) rounded up to a multiple of 32 threads; the ones past N join the warp's
    # collectives only
    i = wp.tid()
    if i < ranges.shape[0]:
        ranges[i, 0] = 0
        ranges[i, 1] = 0
    geo = geo_t()
    rect = wp.vec4i()
    items = int(0)
    if i < n:
        geo, rect, items = bin_setup(means2d[i], radii[i], conic[i], opacity[i], tiles_x, tiles_y, all_tiles)
    chunks = chunks_of(rect)
    mine = int(0)
    if items <= SOLO_ITEMS:
        for li in range(items):
            s = item_span(geo, rect, chunks, li, width, height)
            mine += s[2] - s[1]
    # the larger Gaussians of the warp pool their items
    p_items = wp.where(items > SOLO_ITEMS, items, 0)
    p_incl = warp_scan(p_items)
    lanes = warp_lanes()
    p_total = warp_shfl(p_incl, lanes - 1)
    for base in range(0, p_total, lanes):
        t = base + warp_lane()
        owner = warp_owner(p_incl, t)
        o_geo = owner_geo(geo, owner)
        o_rect = owner_rect(rect, owner)
        o_first = warp_shfl(p_incl - p_items, owner)
        c = int(0)
        if t < p_total:
            s = item_span(o_geo, o_rect, chunks_of(o_rect), t - o_first, width, height)
            c = s[2] - s[1]
        mine += round_share(c, p_incl, p_items, base)
    if i < n:
        counts[i] = mine
        depth_keys[i] = depth[i]
        order[i] = i


@wp.kernel(enable_backward=False, module="tlvg_binning")
def emit_keys_kernel(
    means2d: wp.array(dtype=wp.vec2),  # [N]
    radii: wp.array(dtype=wp.int32),  # [N]
    conic: wp.array(dtype=wp.vec3),  # [N]
    opacity: wp.array(dtype=float),  # [N]
    rank: wp.array(dtype=wp.int32),  # [N] each Gaussian's position in depth order (depth_rank_kernel)
    ends: wp.array(dtype=wp.int32),  # [N] in depth order: one past each Gaussian's last key (the inclusive prefix
    # sum of the counts in depth order, so the keys land in depth order)
    counts: wp.array(dtype=wp.int32),  # [N] keys reserved per Gaussian (Gaussian order)
    n: int,
    tiles_x: int,
    tiles_y: int,
    width: int,
    height: int,
    all_tiles: int,
    cap: int,  # key slots: the total, or a capacity sized from a view's last count (keys past it are not written)
    keys: wp.array(dtype=wp.int32),  # [2M] out tile id (radix sort needs 2x room)
    values: wp.array(dtype=wp.int32),  # [2M] out Gaussian index
):
    # thread g: Gaussian g (threads past N join the warp's collectives only), in Gaussian order as counted: a warp
    # of depth neighbours would hold all the large background splats at once and keep the kernel waiting on it
    # (4x slower on fitted fern); where the keys go keeps them in depth order. The same tiles as
    # count_tiles_kernel; the bound keeps memory safe even if the GPU compiler contracted the two kernels'
    # arithmetic differently at a borderline tile, and no reserved slot is left unwritten (sentinels below).
    g = wp.tid()
    geo = geo_t()
    rect = wp.vec4i()
    items = int(0)
    start = int(0)
    stop = int(0)
    if g < n:
        geo, rect, items = bin_setup(means2d[g], radii[g], conic[g], opacity[g], tiles_x, tiles_y, all_tiles)
        stop = ends[rank[g]]
        start = stop - counts[g]
        stop = wp.min(stop, cap)  # a capacity below the total drops the last keys in depth order, nothing else
    chunks = chunks_of(rect)
    k = start
    if items <= SOLO_ITEMS:
        for li in range(items):
            s = item_span(geo, rect, chunks, li, width, height)
            for tx in range(s[1], s[2]):
                if k < stop:
                    keys[k] = s[0] * tiles_x + tx
                    values[k] = g
                k += 1
    p_items = wp.where(items > SOLO_ITEMS, items, 0)
    p_incl = warp_scan(p_items)
    lanes = warp_lanes()
    p_total = warp_shfl(p_incl, lanes - 1)
    for base in range(0, p_total, lanes):
        t = base + warp_lane()
        owner = warp_owner(p_incl, t)
        o_geo = owner_geo(geo, owner)
        o_rect = owner_rect(rect, owner)
        o_first = warp_shfl(p_incl - p_items, owner)
        o_next = warp_shfl(k, owner)  # where the owner's next key goes
        o_stop = warp_shfl(stop, owner)
        o_g = warp_shfl(g, owner)
        s = wp.vec3i(0, 0, 0)
        if t < p_total:
            s = item_span(o_geo, o_rect, chunks_of(o_rect), t - o_first, width, height)
        c = s[2] - s[1]
        # keys of the owner's earlier items of this round go first: a scan segmented at the owner's first lane
        c_excl = warp_scan(c) - c
        seg = c_excl - warp_shfl(c_excl, wp.clamp(wp.max(o_first, base) - base, 0, lanes - 1))
        kk = o_next + seg
        for tx in range(s[1], s[2]):
            if kk < o_stop:
                keys[kk] = s[0] * tiles_x + tx
                values[kk] = o_g
            kk += 1
        k += round_share(c, p_incl, p_items, base)
    while k < stop:  # ...and never leaves a slot unwritten: a sentinel tile past the grid, sorted last
        keys[k] = tiles_x * tiles_y
        values[k] = g
        k += 1


@wp.kernel(enable_backward=False, module="tlvg_binning")
def depth_rank_kernel(
    order: wp.array(dtype=wp.int32),  # [N] Gaussian ids in depth order (the depth sort's values)
    counts: wp.array(dtype=wp.int32),  # [N] keys per Gaussian (Gaussian order)
    sorted_counts: wp.array(dtype=wp.int32),  # [N] out: the counts in depth order (the scan's input)
    rank: wp.array(dtype=wp.int32),  # [N] out: the inverse permutation, each Gaussian's depth rank
):
    # one launch for what took a gather and a scatter in torch (each a launch and its host time)
    j = wp.tid()
    g = order[j]
    sorted_counts[j] = counts[g]
    rank[g] = j


@wp.kernel(enable_backward=False, module="tlvg_binning")
def tile_ranges_kernel(
    keys: wp.array(dtype=wp.int32),  # [M] sorted tile ids
    count: int,
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2] out [start, end), zero-initialized
):
    # start and end are separate elements: the threads that write them never race
    i = wp.tid()
    tile = keys[i]
    if tile >= ranges.shape[0]:  # sentinel keys (see emit_keys_kernel) sort after every real tile
        return
    if i == 0 or keys[i - 1] != tile:
        ranges[tile, 0] = i
    if i == count - 1 or keys[i + 1] != tile:
        ranges[tile, 1] = i + 1
