"""Tile binning (SPEC §2): the Gaussians are first put in depth order (one radix sort of N float32 depths);
then one int32 key per (Gaussian, touched 16x16 tile) = the tile id is emitted in that order and stably
radix sorted on the tile bits only, which leaves each tile's list in depth order, and the [start, end) range
of each tile is found in the sorted list. Sorting N depths plus ~12-bit tile keys moves far fewer bytes than
sorting (tile << 32 | depth) int64 keys, and the key buffers take 16 instead of 24 bytes per intersection.
float32 only (the float64 path passes float32 copies), so one module serves both scalar types; nothing here
is differentiable.

A Gaussian is binned into the tiles of its 3σ box (SPEC §2) that also hold a pixel center where its α can
reach 1/255. The tiles left out hold only pixels the blending would skip, so the image is exactly that of
plain 3σ-box binning (the tests check it against the brute-force reference); far fewer keys are sorted
and far fewer splats are walked per pixel."""
import warp as wp

TILE = 16  # tile edge in pixels (graphdeco/gsplat)


@wp.func
def min_quad_on_segment(qa: float, qb: float, qc: float, fixed: float, lo: float, hi: float, fixed_is_x: int) -> float:
    # min over t in [lo, hi] of the quadratic form at (fixed, t) (or (t, fixed)): a 1D convex parabola
    if fixed_is_x != 0:
        t = wp.clamp(-qb * fixed / wp.max(qc, 1e-30), lo, hi)
        return qa * fixed * fixed + 2.0 * qb * fixed * t + qc * t * t
    t = wp.clamp(-qb * fixed / wp.max(qa, 1e-30), lo, hi)
    return qa * t * t + 2.0 * qb * t * fixed + qc * fixed * fixed


@wp.func
def tile_reachable(u: float, v: float, q: wp.vec3, k2: float, tx: int, ty: int, width: int, height: int) -> bool:
    """Does any pixel center of tile (tx, ty) have dᵀQd <= k2 (i.e. α >= 1/255)? Exact for the rectangle
    spanned by the tile's pixel centers: min of a convex quadratic is at the center or on an edge."""
    x0 = float(tx * TILE) + 0.5 - u
    x1 = float(wp.min(tx * TILE + TILE, width)) - 0.5 - u
    y0 = float(ty * TILE) + 0.5 - v
    y1 = float(wp.min(ty * TILE + TILE, height)) - 0.5 - v
    if x0 <= 0.0 and x1 >= 0.0 and y0 <= 0.0 and y1 >= 0.0:
        return True
    m = wp.min(min_quad_on_segment(q[0], q[1], q[2], x0, y0, y1, 1), min_quad_on_segment(q[0], q[1], q[2], x1, y0, y1, 1))
    m = wp.min(m, wp.min(min_quad_on_segment(q[0], q[1], q[2], y0, x0, x1, 0),
                         min_quad_on_segment(q[0], q[1], q[2], y1, x0, x1, 0)))
    return m <= k2


@wp.func
def visible_level(opacity: float) -> float:
    # α = min(0.99, o·exp(-½ dᵀQd)) >= 1/255  <=>  dᵀQd <= 2 ln(255 o); the margin absorbs float32 rounding so
    # that the tiles dropped here only ever hold pixels the blending would skip anyway
    return 2.0 * wp.log(255.0 * opacity) * (1.0 + 1e-4) + 1e-3


@wp.func
def tight_rect(u: float, v: float, r: float, q: wp.vec3, k2: float, tiles_x: int, tiles_y: int) -> wp.vec4i:
    # the 3σ box, shrunk to the bounding box of the visible ellipse dᵀQd <= k2 (|dx| <= sqrt(k2 Σxx), ...);
    # Σ = Q⁻¹, so Σxx = Qyy / det Q and Σyy = Qxx / det Q (no Σ2D buffer needed)
    det = wp.max(q[0] * q[2] - q[1] * q[1], 1e-30)
    rx = wp.min(r, wp.sqrt(wp.max(k2, 0.0) * q[2] / det))
    ry = wp.min(r, wp.sqrt(wp.max(k2, 0.0) * q[0] / det))
    x0 = wp.clamp(int(wp.floor((u - rx) / float(TILE))), 0, tiles_x)
    x1 = wp.clamp(int(wp.floor((u + rx) / float(TILE))) + 1, 0, tiles_x)
    y0 = wp.clamp(int(wp.floor((v - ry) / float(TILE))), 0, tiles_y)
    y1 = wp.clamp(int(wp.floor((v + ry) / float(TILE))) + 1, 0, tiles_y)
    return wp.vec4i(x0, x1, y0, y1)


@wp.kernel(enable_backward=False, module="tlvg_binning")
def count_tiles_kernel(
    means2d: wp.array(dtype=wp.vec2),  # [N] float32 copy of the screen means
    radii: wp.array(dtype=wp.int32),  # [N]
    conic: wp.array(dtype=wp.vec3),  # [N] Σ2D⁻¹ (a, b, c)
    opacity: wp.array(dtype=float),  # [N]
    tiles_x: int,
    tiles_y: int,
    width: int,
    height: int,
    all_tiles: int,  # 1: every visible Gaussian touches every tile (brute-force reference binning)
    counts: wp.array(dtype=wp.int32),  # [N] out
):
    i = wp.tid()
    r = radii[i]
    counts[i] = 0
    if r <= 0:
        return
    if all_tiles != 0:
        counts[i] = tiles_x * tiles_y
        return
    o = opacity[i]
    if o * 255.0 < 1.0:  # never reaches α = 1/255 anywhere
        return
    m = means2d[i]
    k2 = visible_level(o)
    rect = tight_rect(m[0], m[1], float(r), conic[i], k2, tiles_x, tiles_y)
    n = int(0)
    for ty in range(rect[2], rect[3]):
        for tx in range(rect[0], rect[1]):
            if tile_reachable(m[0], m[1], conic[i], k2, tx, ty, width, height):
                n += 1
    counts[i] = n


@wp.kernel(enable_backward=False, module="tlvg_binning")
def emit_keys_kernel(
    order: wp.array(dtype=wp.int32),  # [N] Gaussian ids in depth order
    means2d: wp.array(dtype=wp.vec2),  # [N]
    radii: wp.array(dtype=wp.int32),  # [N]
    conic: wp.array(dtype=wp.vec3),  # [N]
    opacity: wp.array(dtype=float),  # [N]
    offsets: wp.array(dtype=wp.int32),  # [N] exclusive prefix sum of the counts in depth order (offsets[j]: order[j])
    counts: wp.array(dtype=wp.int32),  # [N] keys reserved per Gaussian (Gaussian order)
    tiles_x: int,
    tiles_y: int,
    width: int,
    height: int,
    all_tiles: int,
    keys: wp.array(dtype=wp.int32),  # [2M] out tile id (radix sort needs 2x room)
    values: wp.array(dtype=wp.int32),  # [2M] out Gaussian index
):
    j = wp.tid()
    i = order[j]
    r = radii[i]
    if r <= 0:
        return
    m = means2d[i]
    o = opacity[i]
    k2 = visible_level(wp.max(o, 1.0 / 255.0))
    rect = wp.vec4i(0, tiles_x, 0, tiles_y)
    if all_tiles == 0:
        if o * 255.0 < 1.0:
            return
        rect = tight_rect(m[0], m[1], float(r), conic[i], k2, tiles_x, tiles_y)
    k = offsets[j]
    stop = k + counts[i]
    for ty in range(rect[2], rect[3]):
        for tx in range(rect[0], rect[1]):
            # the same test as count_tiles_kernel; the bound keeps memory safe even if the GPU compiler
            # contracted the two kernels' arithmetic differently at a borderline tile
            if k < stop and (all_tiles != 0 or tile_reachable(m[0], m[1], conic[i], k2, tx, ty, width, height)):
                keys[k] = ty * tiles_x + tx
                values[k] = i
                k += 1
    while k < stop:  # ...and never leaves a slot unwritten: a sentinel tile past the grid, sorted last
        keys[k] = tiles_x * tiles_y
        values[k] = i
        k += 1


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
