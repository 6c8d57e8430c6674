"""Tile binning: one key per (Gaussian, touched 16x16 tile) = tile_id << 32 | float32 depth bits, radix
sorted, then the [start, end) range of each tile in the sorted list (SPEC §2). Integer-only, so one module
serves both scalar types; nothing here is differentiable."""
import warp as wp

TILE = 16  # tile edge in pixels (graphdeco/gsplat)


@wp.func
def tile_rect(u: float, v: float, r: float, tiles_x: int, tiles_y: int) -> wp.vec4i:
    # tiles overlapped by the bounding box [u - r, u + r] x [v - r, v + r], clamped to the grid;
    # x1/y1 are exclusive
    x0 = wp.clamp(int(wp.floor((u - r) / float(TILE))), 0, tiles_x)
    x1 = wp.clamp(int(wp.floor((u + r) / float(TILE))) + 1, 0, tiles_x)
    y0 = wp.clamp(int(wp.floor((v - r) / float(TILE))), 0, tiles_y)
    y1 = wp.clamp(int(wp.floor((v + r) / float(TILE))) + 1, 0, tiles_y)
    return wp.vec4i(x0, x1, y0, y1)


@wp.kernel(enable_backward=False, module="tlvg_binning")
def count_tiles_kernel(
    means2d: wp.array(dtype=wp.vec2),  # [N] float32 copy of the screen means
    radii: wp.array(dtype=wp.int32),  # [N]
    tiles_x: int,
    tiles_y: int,
    all_tiles: int,  # 1: every visible Gaussian touches every tile (brute-force reference binning)
    counts: wp.array(dtype=wp.int32),  # [N] out
):
    i = wp.tid()
    r = radii[i]
    if r <= 0:
        counts[i] = 0
        return
    if all_tiles != 0:
        counts[i] = tiles_x * tiles_y
        return
    m = means2d[i]
    rect = tile_rect(m[0], m[1], float(r), tiles_x, tiles_y)
    counts[i] = wp.max(rect[1] - rect[0], 0) * wp.max(rect[3] - rect[2], 0)


@wp.kernel(enable_backward=False, module="tlvg_binning")
def emit_keys_kernel(
    means2d: wp.array(dtype=wp.vec2),  # [N]
    radii: wp.array(dtype=wp.int32),  # [N]
    depth_bits: wp.array(dtype=wp.int32),  # [N] float32 depth reinterpreted as int (monotone for z > 0)
    offsets: wp.array(dtype=wp.int32),  # [N] exclusive prefix sum of counts
    tiles_x: int,
    tiles_y: int,
    all_tiles: int,
    keys: wp.array(dtype=wp.int64),  # [2M] out (radix sort needs 2x room)
    values: wp.array(dtype=wp.int32),  # [2M] out Gaussian index
):
    i = wp.tid()
    r = radii[i]
    if r <= 0:
        return
    rect = wp.vec4i(0, tiles_x, 0, tiles_y)
    if all_tiles == 0:
        m = means2d[i]
        rect = tile_rect(m[0], m[1], float(r), tiles_x, tiles_y)
    k = offsets[i]
    d = wp.int64(depth_bits[i])
    for ty in range(rect[2], rect[3]):
        for tx in range(rect[0], rect[1]):
            keys[k] = (wp.int64(ty * tiles_x + tx) << wp.int64(32)) | d
            values[k] = i
            k += 1


@wp.kernel(enable_backward=False, module="tlvg_binning")
def tile_ranges_kernel(
    keys: wp.array(dtype=wp.int64),  # [M] sorted
    count: int,
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2] out [start, end), zero-initialized
):
    # start and end are separate elements: the threads that write them never race
    i = wp.tid()
    tile = int(keys[i] >> wp.int64(32))
    if i == 0 or int(keys[i - 1] >> wp.int64(32)) != tile:
        ranges[tile, 0] = i
    if i == count - 1 or int(keys[i + 1] >> wp.int64(32)) != tile:
        ranges[tile, 1] = i + 1
