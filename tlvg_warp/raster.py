"""The raster pipeline's stages on torch buffers (SPEC §2), each a few Warp launches: the camera struct the kernels
take, projection (and its Warp-generated adjoint, launched by hand with torch-allocated gradient buffers), tile
binning (depth order, keys, per-tile ranges) and blending. ``autograd`` wraps them in torch autograd Functions;
``launch`` runs them."""
from __future__ import annotations

import contextlib
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch
import warp as wp

from .launch import ct, ct_at, fast_launch, inclusive_scan_at, sort_pairs_at, wdevice
from .types import Camera

TILE = 16

SCAN_INT32_LIMIT = 2**31  # below this bound on the total the ends are scanned in int32 (the tests lower it)
CPU_WALK = True  # on the CPU, the blending kernels that walk one pixel's list without staging (3-5x faster there);
# False runs the GPU's staged kernels on the CPU too (the test comparing the two sets sets it)
CPU_THREADS = min(2, torch.get_num_threads())  # threads of the CPU blending (blend_cpu, blend_backward; 1: one launch)
CPU_HALVES = True  # the CPU blending's per-Gaussian sums (the backward's gradients, the forward's weights) are summed
# over the image's two halves of tiles apart, then added, on one thread as on two: they do not depend on CPU_THREADS
# (False: one launch, the staged kernels' order; tests)
_capture: dict | None = None  # set by capture_binning(): the next renders' binning state lands here


@contextlib.contextmanager
def capture_binning():
    """Within the block, each forward render stores its binning in the yielded dict (the last render's wins):
    ``proj`` (Projected), ``counts`` [N] tiles per Gaussian, ``total``, ``ranges`` [tiles, 2] per-tile [start,
    end) into ``ids`` [total] (Gaussian ids, each tile's list in depth order), ``last`` [H, W] one past each
    pixel's last contributor in ``ids``, ``tiles`` (tiles_x, tiles_y). For tests and the benchmark's statistics."""
    global _capture
    prev, _capture = _capture, {}
    try:
        yield _capture
    finally:
        _capture = prev


def packed_zeros(shapes, dtype, device) -> list[torch.Tensor]:
    """Zero tensors of the given shapes, as contiguous views of one buffer: one allocation and one memset
    instead of one each (the host, not the GPU, bounds these small steps)."""
    sizes = [math.prod(s) for s in shapes]
    buf = torch.zeros(sum(sizes), dtype=dtype, device=device)
    return [v.view(s) for v, s in zip(buf.split_with_sizes(sizes), shapes)]  # (ATen's op: Tensor.split is Python)


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities (torch views of the Warp outputs)."""

    means2d: torch.Tensor  # [N, 2]
    cov2d: torch.Tensor | None  # [N, 3] (a, b, c) of Σ2D (the reference only; the Warp path bins from the conic)
    conic: torch.Tensor  # [N, 3] (a, b, c) of Σ2D⁻¹
    depth: torch.Tensor  # [N]
    opacity: torch.Tensor  # [N]
    color: torch.Tensor  # [N, 3]
    radii: torch.Tensor  # [N] int32


@dataclass
class Projection:
    """The projection's outputs as the kernels see them: one buffer and its descriptors (torch views only on
    demand, ``tensors()``: each view is a host op, and the render's host time bounds its forward)."""

    buf: torch.Tensor  # [7N] means2d (N, 2) | conic (N, 3) | depth (N) | opacity (N)
    radii: torch.Tensor  # [N] int32
    colors: torch.Tensor  # [N, 3] ShadeFn's output, passed through
    outs: list  # descriptors [means2d, conic, depth, opacity, colors, radii]
    n: int

    def tensors(self) -> Projected:
        n, b = self.n, self.buf
        return Projected(b[:2 * n].view(n, 2), None, b[2 * n:5 * n].view(n, 3), b[5 * n:6 * n], b[6 * n:], self.colors,
                         self.radii)


def camera_values(cam: Camera):
    """(R rows, t, center) of the camera as Python floats, from one read of the 4x4 (no torch ops per value)."""
    m = cam.world_to_camera.tolist()
    R = [row[:3] for row in m[:3]]
    t = [row[3] for row in m[:3]]
    center = [-(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]) for j in range(3)]
    return R, t, center


def camera_arg(K, cam: Camera, values=None):
    """The camera as the kernels' struct value (``K.camera``: rotation, translation, center, intrinsics, image size,
    near and far planes), built once per render from ``camera_values(cam)`` (``values`` when the caller already has
    them). Kept per camera (by value): building it costs more host time than the launches that take it."""
    R, t, center = values or camera_values(cam)
    key = ("camera", K.scalar, *R[0], *R[1], *R[2], *t, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
           cam.near, cam.far)
    return _kept(key, lambda: _camera_struct(K, cam, R, t, center))


def _camera_struct(K, cam: Camera, R, t, center):
    s = K.scalar
    c = K.camera()
    c.R = K.mat33(*[s(v) for row in R for v in row])
    c.t = K.vec3(*map(s, t))
    c.center = K.vec3(*map(s, center))
    c.fx, c.fy, c.cx, c.cy = s(cam.fx), s(cam.fy), s(cam.cx), s(cam.cy)
    c.width, c.height = int(cam.width), int(cam.height)
    c.near, c.far = s(cam.near), s(cam.far)
    return c


def no_grad_camera(K):
    """A zero camera struct: the camera's adjoint argument in a by-hand adjoint launch (the camera gets no
    gradient)."""
    return _kept(("camera adjoint", K.scalar), K.camera)


_values: dict = {}  # key -> a kernel value built from it (camera structs, backgrounds)


def _kept(key, make):
    """``make()``, kept under ``key`` (bounded: a long orbit of cameras clears it now and then)."""
    v = _values.get(key)
    if v is None:
        if len(_values) > 2048:
            _values.clear()
        v = _values[key] = make()
    return v


def kernel_vec3(K, xyz):
    """``K.vec3(*xyz)`` in K's scalar type, kept per value (the background)."""
    return _kept((K.scalar, *xyz), lambda: K.vec3(*map(K.scalar, xyz)))


def project(K, args, colors: torch.Tensor, cam_arg, n: int, dtype, device) -> Projection:
    """Launch the projection into one uninitialized buffer (the kernel writes every output); the colors
    (``ShadeFn``'s output, ``args[4]``) pass through. The adjoint is launched by ``project_adjoint``."""
    buf = torch.empty(7 * n, dtype=dtype, device=device)
    radii = torch.empty(n, dtype=torch.int32, device=device)
    e = buf.element_size()
    outs = [ct_at(buf, 0, (n,), e, 2), ct_at(buf, 2 * n * e, (n,), e, 3), ct_at(buf, 5 * n * e, (n,), e),
            ct_at(buf, 6 * n * e, (n,), e), args[4], ct(radii)]
    fast_launch(K.project, n, args[:4] + [cam_arg] + outs[:4] + outs[5:], wdevice(device))
    return Projection(buf, radii, colors, outs, n)


def project_adjoint(K, args, pouts, grads, out_grads, cam_arg, n: int, device):
    """The projection's Warp-generated adjoint: dL/d(screen mean, conic, depth, opacity) (``out_grads``,
    descriptors) -> ``grads`` of the four
    geometric inputs (accumulated). What wp.Tape would launch, with the gradient buffers passed as adjoint
    arguments: the forward descriptors carry no gradient pointers, so no output gradient is zeroed on the way (the
    screen-mean one stays dL/d(screen mean))."""
    fast_launch(K.project, n, args[:4] + [cam_arg] + pouts[:4] + pouts[5:], wdevice(device),
                adj_args=[ct(g, a) for g, a in zip(grads, (K.vec3, K.vec4, K.vec3, None))] + [no_grad_camera(K)]
                + list(out_grads) + [None])


def binning_inputs(pr: Projection):
    """float32 descriptors of what the binning kernels read: [means2d, radii, conic, opacity] and the depths (copies
    only on the float64 path)."""
    if pr.buf.dtype == torch.float32:
        o = pr.outs
        return [o[0], o[5], o[1], o[3]], o[2]
    p = pr.tensors()
    return [ct(p.means2d.float(), wp.vec2), ct(p.radii), ct(p.conic.float(), wp.vec3),
            ct(p.opacity.float())], ct(p.depth.float())


_dummies: dict = {}


def dummy_buffer(dtype, device) -> torch.Tensor:
    """A one-element buffer for kernel outputs that a render does not ask for (never read)."""
    key = (dtype, device)
    t = _dummies.get(key)
    if t is None:
        t = _dummies[key] = torch.zeros(1, dtype=dtype, device=device)
    return t


def zero_upstream(shape: tuple, dtype, device) -> torch.Tensor:
    """A kept read-only zero of ``shape`` that owns one row (stride 0 over the others): the upstream gradient of
    an output that got none (no [H, W] buffer, no memset, no view op per backward)."""
    key = (shape, dtype, device)
    t = _dummies.get(key)
    if t is None:
        t = _dummies[key] = torch.zeros(shape[-1], dtype=dtype, device=device).expand(shape)
    return t


def tile_grid(width: int, height: int) -> tuple[int, int]:
    return (width + TILE - 1) // TILE, (height + TILE - 1) // TILE


def warp_padded(n: int) -> int:
    """Thread count for the binning kernels: n rounded up to whole warps (their lanes cooperate)."""
    return (n + 31) // 32 * 32


@dataclass
class DepthOrder:
    """The binning up to its one host sync: tiles per Gaussian, the depth order and the intersections' total."""

    geometry: list  # binning_inputs' descriptors
    work: torch.Tensor | None  # [8N] int32: counts N | depth keys 2N | order 2N | counts in depth order N | ranks N |
    # their inclusive scan N (each Gaussian's end in depth order)
    ranges: torch.Tensor  # [tiles, 2] int32, zeroed by the tile count (tile_ranges_kernel fills the non-empty ones)
    counts: object  # descriptors into work (None without Gaussians): the counts,
    rank: object  # the depth ranks
    ends: object  # and the scan
    total: int  # key slots: the intersections' total, or a capacity given for them (then ``found`` holds the total)
    tiles: tuple  # (tiles_x, tiles_y)
    found: torch.Tensor | None = None  # [1] int32 on the device: the total, where a capacity sized the buffers


def count_intersections(K, pr: Projection, width: int, height: int, all_tiles: bool = False,
                        capacity: int | None = None) -> DepthOrder:
    """Tiles touched per Gaussian, the Gaussians in depth order (one radix sort of their depths), each one's
    depth rank and the end of its keys in depth order. Their total (the last end) sizes the key buffers: read
    back, the one host sync of a render; or, given a ``capacity`` (``IntersectionBudget``), the buffers take that
    many keys and the total stays on the device (``DepthOrder.found``), read later without waiting."""
    n, device, wdev = pr.n, pr.buf.device, wdevice(pr.buf.device)
    geometry, depth = binning_inputs(pr)
    tiles_x, tiles_y = tile_grid(width, height)
    ranges = torch.empty(tiles_x * tiles_y, 2, dtype=torch.int32, device=device)
    if n == 0:
        return DepthOrder(geometry, None, ranges.zero_(), None, None, None, 0, (tiles_x, tiles_y))
    # the per-Gaussian buffers are one allocation, seen through descriptors at offsets (all go when the forward
    # ends); the depth sort's keys and values have the radix sort's 2x room. The last end is the total
    work = torch.empty(8 * n, dtype=torch.int32, device=device)
    at = work.data_ptr()
    counts, rank = ct_at(work, 0, (n,), 4), ct_at(work, 24 * n, (n,), 4)
    fast_launch(K.count_tiles, warp_padded(max(n, tiles_x * tiles_y)),
                [*geometry, depth, n, tiles_x, tiles_y, width, height, int(all_tiles), counts,
                 ct_at(work, 4 * n, (2 * n,), 4), ct_at(work, 12 * n, (2 * n,), 4), ct(ranges)], wdev)
    # the depth sort (culled Gaussians sort anywhere: they emit no keys)
    sort_pairs_at(torch.float32, device, at + 4 * n, at + 12 * n, n)
    fast_launch(K.depth_rank, n, [ct_at(work, 12 * n, (n,), 4), counts, ct_at(work, 20 * n, (n,), 4), rank], wdev)
    if n * tiles_x * tiles_y < SCAN_INT32_LIMIT:  # a Gaussian touches at most every tile: no int32 end can wrap
        inclusive_scan_at(at + 20 * n, at + 28 * n, n, device)
        if capacity is not None:  # int32 totals only: a capacity is a past total, below 2**31
            return DepthOrder(geometry, work, ranges, counts, rank, ct_at(work, 28 * n, (n,), 4), int(capacity),
                              (tiles_x, tiles_y), work[8 * n - 1:])
        total = int(work[8 * n - 1].item())
    else:  # in int64, so that a total past int32 is caught rather than wrapped
        ends64 = torch.cumsum(work[5 * n:6 * n], 0, dtype=torch.int64)
        total = int(ends64[-1].item())
        if total < 2**31:
            work[7 * n:].copy_(ends64)
    if total >= 2**31:
        raise RuntimeError(f"{total} tile intersections exceed the int32 index range; render at a lower resolution")
    return DepthOrder(geometry, work, ranges, counts, rank, ct_at(work, 28 * n, (n,), 4), total, (tiles_x, tiles_y))


def bin_tiles(K, pr: Projection, order: DepthOrder, width: int, height: int, all_tiles: bool = False):
    """Keys in depth order, stably sorted by tile -> the per-tile [start, end) ranges descriptor and the sorted
    Gaussian ids (descriptor, and the buffer it views)."""
    device, wdev, n, total = pr.buf.device, wdevice(pr.buf.device), pr.n, order.total
    if total == 0:
        ids = dummy_buffer(torch.int32, device)
        return ct(order.ranges), ct(ids), ids
    tiles_x, tiles_y = order.tiles
    # two allocations, not one: the sorted ids outlive the keys until the blending backward, and on a wide image
    # (beer, 720x1280) that stage holds the backward's peak
    keys = torch.empty(2 * total, dtype=torch.int32, device=device)  # each with the radix sort's 2x room
    ids = torch.empty(2 * total, dtype=torch.int32, device=device)
    if order.found is not None:  # a capacity: the slots past the true total hold the sentinel tile, sorted last
        keys[:total].fill_(tiles_x * tiles_y)
    fast_launch(K.emit_keys, warp_padded(n), [*order.geometry, order.rank, order.ends, order.counts, n, tiles_x,
                                              tiles_y, width, height, int(all_tiles), total, ct(keys), ct(ids)], wdev)
    tile_bits = max(1, (tiles_x * tiles_y).bit_length())  # room for the sentinel tile id
    # stable: each tile's list stays in depth order
    sort_pairs_at(torch.int32, device, keys.data_ptr(), ids.data_ptr(), total, 0, tile_bits)
    ranges = ct(order.ranges)
    fast_launch(K.tile_ranges, total, [ct(keys), total, ranges], wdev)
    # the sort's second half lives until the blending backward has run (no copy per render; the backward's peak
    # comes later, at the SH gradients, after these are freed)
    return ranges, ct_at(ids, 0, (total,), 4), ids


class IntersectionBudget:
    """Key buffers sized from each view's last intersection count, so that a training render reads nothing back.

    The count is the one value a render needs on the host before it can bin (it sizes the key buffers), and
    reading it waits for the GPU to finish every earlier step. A training loop renders the same few views again and
    again, and between two visits of a view the count moves little (fern, 3000 stylize steps: at most 1.008x in
    the stylize phase, 1.127x in the pre-process, whose density control grows the scene). So a view's render
    takes ``headroom`` x its last known count as its capacity (``count_intersections(capacity=...)``) and copies
    the true total to pinned host memory without waiting; the view's next render reads it (long since arrived)
    and sizes itself from it. The first render of a view, and any render after the number of Gaussians changed
    (density control), count exactly. A total above the capacity drops that render's last keys in depth order
    (behind everything else on their tiles); it is counted in ``overflows`` (a run reports it) and the next
    render of the view is sized from the true total. ``scene`` is the caller's mark of a structural change that
    keeps the number of Gaussians (a training loop sets it to its count of density events): a new mark counts
    exactly too."""

    def __init__(self, headroom: float = 1.25):
        if not headroom > 1.0:
            raise ValueError(f"headroom must be above 1, got {headroom}")
        self.headroom = float(headroom)
        self.scene = 0  # the caller's mark of the scene's structure (above)
        self.known: dict = {}  # key -> (Gaussians, scene mark, intersections) of the view's last render
        self.pending: dict = {}  # key -> (Gaussians, scene mark, capacity, event or None): a total on its way to ...
        self.host: dict = {}  # key -> ... the view's pinned [1] int32 (kept for its next render)
        self.overflows = self.exact = self.sized = 0  # renders: over their capacity, counted exactly, sized

    def capacity(self, key, n: int) -> int | None:
        """Key slots for the next render of view ``key`` with ``n`` Gaussians; None: count it exactly."""
        self._settle(key)
        last = self.known.get(key)
        if last is None or last[:2] != (n, self.scene) or last[2] == 0:
            return None
        cap = math.ceil(last[2] * self.headroom)
        return cap if cap < 2**31 else None

    def observe(self, key, n: int, order: DepthOrder) -> None:
        """Record the render's count: known at once when exact, else on its way to the host."""
        if order.found is None:
            self.exact += 1
            self.known[key] = (n, self.scene, order.total)
            return
        self.sized += 1
        host = self.host.get(key)
        if host is None:
            host = self.host[key] = torch.empty(1, dtype=torch.int32, pin_memory=order.found.is_cuda)
        host.copy_(order.found, non_blocking=True)
        event = None
        if order.found.is_cuda:
            event = torch.cuda.Event()
            event.record()
        self.pending[key] = (n, self.scene, order.total, event)

    def counts(self) -> dict:
        """Renders so far: counted exactly, sized from the view's last count, and over their capacity."""
        for key in list(self.pending):
            self._settle(key)
        return {"exact": self.exact, "sized": self.sized, "over_capacity": self.overflows}

    def _settle(self, key) -> None:
        got = self.pending.pop(key, None)
        if got is None:
            return
        n, scene, cap, event = got
        if event is not None:
            event.synchronize()  # recorded a step or more ago: long since done
        total = int(self.host[key][0])
        self.overflows += total > cap
        self.known[key] = (n, scene, total)


_helper: tuple | None = None  # (process id, pool): the second CPU thread of the blending, made on first use
# in each process (a forked child inherits the pool without its thread)


def _halves(kernel, tiles: int, args_first, args_rest, wdev) -> None:
    """Launch ``kernel`` over the first half of the tiles and over the rest, each with its own arguments: with
    CPU_THREADS > 1 the first on the helper thread (its own recorded launch) beside the rest on this one, else one
    after the other; return when both are done."""
    global _helper
    first = (tiles // 2) * TILE * TILE
    if CPU_THREADS < 2:
        fast_launch(kernel, first, args_first + [0], wdev)
        fast_launch(kernel, tiles * TILE * TILE - first, args_rest + [first], wdev)
        return
    if _helper is None or _helper[0] != os.getpid():
        _helper = (os.getpid(), ThreadPoolExecutor(max_workers=1, thread_name_prefix="tlvg-blend"))
    other = _helper[1].submit(fast_launch, kernel, first, args_first + [0], wdev, None, None, 1)
    try:
        fast_launch(kernel, tiles * TILE * TILE - first, args_rest + [first], wdev)
    finally:  # the helper's half writes into this render's buffers: it ends before they can go
        other.result()


def blend_cpu(K, args: list, tiles: int, weights: torch.Tensor | None, wdev) -> None:
    """The CPU blending forward: Warp runs a CPU launch on one core, so with CPU_THREADS > 1 the tiles are split in two
    halves launched from two threads at once (Warp releases the GIL in the call). Each pixel writes only its own
    outputs, so the halves are independent, except the per-Gaussian ``weights`` (the last argument) when asked for:
    Warp's CPU atomic_add is a plain add, so the first half sums into a buffer of its own, added after, on one thread
    as on two (CPU_HALVES, as the backward)."""
    if tiles < 2 or (weights is None and CPU_THREADS < 2) or (weights is not None and not CPU_HALVES):
        fast_launch(K.blend_forward_cpu, tiles * TILE * TILE, args + [0], wdev)
    elif weights is None:
        _halves(K.blend_forward_cpu, tiles, args, args, wdev)
    else:
        own = torch.zeros_like(weights)
        _halves(K.blend_forward_cpu, tiles, args[:-1] + [ct(own)], args, wdev)
        weights += own


def blend_backward(K, st: dict, upstream: list, grads: list, wdev) -> None:
    """The blending backward into ``grads`` (flat per-Gaussian sums, zeroed). On the CPU the tiles are split in two
    halves (CPU_HALVES), on two threads with CPU_THREADS > 1 as in the forward; Warp's CPU atomic_add is a plain add,
    so the first half sums into gradient buffers of its own, added to ``grads`` after. The order of the sums is the
    same on one thread as on two, so a run's gradients do not depend on the machine's cores (a process with one
    thread and one with two, e.g. the ranks of a run and a single process, give the same bits)."""
    args = st["args"] + st["saved"] + upstream
    threads = st["threads"]
    tiles = threads // (TILE * TILE)
    if st["backward"] is not K.blend_backward_cpu:
        fast_launch(st["backward"], threads, args + [ct(g) for g in grads], wdev, block_dim=TILE * TILE)
    elif not CPU_HALVES or tiles < 2:
        fast_launch(K.blend_backward_cpu, threads, args + [ct(g) for g in grads] + [0], wdev)
    else:
        own = [torch.zeros_like(g) for g in grads]
        _halves(K.blend_backward_cpu, tiles, args + [ct(g) for g in own], args + [ct(g) for g in grads], wdev)
        for g, o in zip(grads, own):
            g += o


def blend(K, pr: Projection, order: DepthOrder, cam: Camera, settings: dict):
    """Bin, then blend front to back: the images, and the per-pixel state the blending backward reads."""
    device, dtype, n = pr.buf.device, pr.buf.dtype, pr.n
    H, W = cam.height, cam.width
    ranges, ids, ids_buf = bin_tiles(K, pr, order, W, H, settings["all_tiles"])
    tiles_x, tiles_y = order.tiles
    color = torch.empty(H, W, 3, dtype=dtype, device=device)
    alpha = torch.empty(H, W, dtype=dtype, device=device)
    want_depth = settings.get("depth", True)
    # without depth: a one-element buffer, never written
    depth = torch.empty(H, W, dtype=dtype, device=device) if want_depth else dummy_buffer(dtype, device)
    # transmittance T [H, W] and one past each pixel's last contributor [H, W] int32: one allocation, one lifetime
    e = color.element_size()
    state_px = torch.empty(H * W * (e + 4), dtype=torch.uint8, device=device)
    T, last = ct_at(state_px, 0, (H, W), e), ct_at(state_px, H * W * e, (H, W), 4)
    weights = torch.zeros(n, dtype=dtype, device=device) if settings["weights"] else dummy_buffer(dtype, device)
    bg = kernel_vec3(K, settings["background"])
    w_means2d, w_conic, w_depth, w_opacity, w_color, _w_radii = pr.outs
    args = [ranges, ids, w_means2d, w_conic, w_opacity, w_color, w_depth, bg, W, H, tiles_x, int(want_depth)]
    out_depth = ct(depth) if want_depth else ct_at(depth, 0, (1, 1), e)
    cpu_walk = device.type == "cpu" and CPU_WALK
    outs = args + [int(settings["weights"]), ct(color, K.vec3), ct(alpha), out_depth, T, last, ct(weights)]
    if cpu_walk:
        blend_cpu(K, outs, tiles_x * tiles_y, weights if settings["weights"] else None, wdevice(device))
    else:
        fast_launch(K.blend_forward, tiles_x * tiles_y * TILE * TILE, outs, wdevice(device), block_dim=TILE * TILE)
    state = {"args": args, "saved": [out_depth, T, last], "threads": tiles_x * tiles_y * TILE * TILE,
             "backward": K.blend_backward_cpu if cpu_walk else K.blend_backward}
    if _capture is not None:  # (a host read where a capacity sized the keys: tests and statistics only)
        total = order.total if order.found is None else min(order.total, int(order.found.item()))
        _capture.update(proj=pr.tensors(), counts=order.work[:n] if order.work is not None else
                        torch.empty(0, dtype=torch.int32, device=device), total=total, ranges=order.ranges,
                        ids=ids_buf[:total], last=state_px[H * W * e:].view(torch.int32).view(H, W),
                        tiles=order.tiles)
    return color, alpha, depth if want_depth else None, weights, state


