"""Bridge between torch tensors and the Warp raster kernels: one function per pipeline stage (project, bin,
blend) and two autograd Functions over them, ``ShadeFn`` (SH colours) and ``RasterizeFn`` (projection, binning,
blending).

Kernels get bare array descriptors of torch tensors (``ct``), launched through recorded ``wp.Launch``es
(``fast_launch``): a render's host time, not its GPU time, bounds small and sparse scenes. Gradients: the
blending and SH backwards are hand-written; the projection's adjoint is Warp-generated, launched by hand with the
torch-allocated gradient buffers as its adjoint arguments (``project_adjoint``)."""
from __future__ import annotations

import contextlib
import ctypes
import math
import os
import weakref
from dataclasses import dataclass

import torch
import warp as wp

from .types import Camera

TILE = 16

_initialized = False


def init_warp() -> None:
    global _initialized
    if not _initialized:
        if os.environ.get("TLVG_WARP_VERBOSE", "") == "":  # no banner, no per-module load lines
            wp.config.quiet = True  # Warp before 1.19
            if hasattr(wp, "LOG_WARNING"):
                wp.config.log_level = wp.LOG_WARNING  # Warp 1.19 replaced `quiet` by a log level
        wp.init()
        _initialized = True


def kernels_for(dtype: torch.dtype):
    init_warp()
    from .kernels import raster_kernels

    return raster_kernels({torch.float32: "float32", torch.float64: "float64"}[dtype])


_wdevs: dict = {}  # torch device -> its Warp device


def wdevice(device: torch.device):
    """``wp.device_from_torch(device)``, cached (a few microseconds a call, several calls a render)."""
    d = _wdevs.get(device)
    if d is None:
        d = _wdevs[device] = wp.device_from_torch(device)
    return d


_streams: dict = {}  # torch stream handle -> its wp.Stream (wrapping one registers it with Warp: not per call)


@contextlib.contextmanager
def warp_on(device: torch.device):
    """Run Warp launches on torch's current stream so no extra synchronization is needed. The stream stays the
    Warp device's current stream after the render (set once, with one wait on Warp's previous stream; a render
    on another torch stream switches it again): entering and leaving a ScopedStream per render cost two
    cross-stream synchronizations of host time each."""
    if device.type == "cuda":
        ts = torch.cuda.current_stream(device)
        stream = _streams.get(ts.cuda_stream)
        if stream is None:
            stream = _streams[ts.cuda_stream] = wp.stream_from_torch(ts)  # keeps ts alive: its handle stays unique
        wdev = stream.device
        if wdev.stream is not stream:
            wdev.set_stream(stream, sync=True)
        with wp.ScopedDevice(wdev):
            yield wdev
    else:
        yield wdevice(device)


def warp_array_ctype():
    """Warp's C array descriptor class (``array_t``): what ``wp.from_torch(..., return_ctype=True)`` builds.

    The one place this module touches Warp's private API (``warp._src.types``; ``warp.types`` before 1.10).
    tests/test_raster.py checks that it still is the class from_torch returns, with the fields ``ct`` fills,
    so a Warp upgrade that moves or changes it fails there by name rather than as a crash in a kernel."""
    global _ARRAY_T
    if _ARRAY_T is None:
        try:
            from warp._src.types import array_t
        except ImportError:
            try:
                from warp.types import array_t
            except ImportError as e:
                raise ImportError(f"this Warp ({wp.config.version}) has no array_t in warp._src.types or "
                                  f"warp.types: tlvg_warp.ops.warp_array_ctype needs updating") from e
        _ARRAY_T = array_t
    return _ARRAY_T


_ARRAY_T = None


def ct(t: torch.Tensor, dtype=None):
    """A bare array descriptor for launches outside the tape: what ``wp.from_torch(t, dtype, return_ctype=True)``
    builds, without its per-call checks (a few microseconds each, dozens per render). Callers pass tensors whose
    dtype matches and whose vector dimension is innermost and contiguous."""
    shape, strides = t.shape, t.stride()
    vec = dtype is not None and hasattr(dtype, "_shape_")
    key = (shape, strides, t.element_size(), vec)
    template = _templates.get(key)
    if template is None:
        if len(_templates) > 4096:  # shapes vary per render (the sorted ids): keep the cache bounded
            _templates.clear()
        elem = key[2]
        if vec:  # vector dtype: the last torch dim is the vector
            shape, strides = shape[:-1] or (1,), strides[:-1] or (1,)
        template = _templates[key] = warp_array_ctype()(0, 0, len(shape), tuple(shape), tuple(x * elem for x in strides))
    a = _ARRAY_T.from_buffer_copy(template)  # (array_t's own constructor fills the fields in Python: 3x slower)
    a.data = t.data_ptr()
    a._ref = t  # keeps the memory alive as long as the descriptor
    return a


_templates: dict = {}  # (shape, strides, element size, vector dtype) -> a descriptor with a null data pointer


class _Site:
    """One recorded ``wp.Launch`` per (kernel, device, block_dim, forward/adjoint) and how to refill it: per
    parameter slot a setter kind (descriptor, ctypes scalar, vector/matrix copied by bytes), found once; the
    launch's dimensions, reset only when they change (``Launch.set_dim`` validates in Python each time)."""

    __slots__ = ("launch", "dim", "kinds", "addrs", "sizes", "hook", "smem")

    def __init__(self, launch, dim: int, adjoint: bool):
        self.launch, self.dim = launch, dim
        params = launch.params  # [0] is the launch bounds; the slots are never replaced (written in place)
        self.kinds = [_slot_kind(p) for p in params]
        self.addrs = [ctypes.addressof(p) for p in params]
        self.sizes = [ctypes.sizeof(p) for p in params]
        hooks = launch.hooks
        self.hook, self.smem = ((hooks.backward, hooks.backward_smem_bytes) if adjoint
                                else (hooks.forward, hooks.forward_smem_bytes))


def _slot_kind(p) -> int:
    if isinstance(p, (ctypes.Structure, ctypes.Array)):
        return _BYTES  # an array descriptor, a vector or a matrix: its bytes copied into the slot
    return _SCALAR  # a ctypes scalar: its .value set


_BYTES, _SCALAR = 1, 2
_sites: dict = {}  # (kernel, device alias, block_dim, adjoint) -> _Site


def fast_launch(kernel, dim: int, args, device, block_dim: int | None = None, adj_args=None) -> None:
    """``wp.launch(kernel, dim, inputs=args, device=device, block_dim=block_dim, record_tape=False)`` for the
    per-render launches, with less host time: the first call per (kernel, device, block_dim, forward/adjoint)
    records a ``wp.Launch``; later calls write its parameter slots directly (array descriptors from ``ct``,
    ``wp.array``s, scalars, vectors) and, on CUDA, enqueue it through Warp's runtime, skipping ``wp.launch``'s
    per-argument checks and packing and ``Launch``'s per-call bookkeeping (a render's host time bounds its
    forward: the GPU waits on the host for most of it). ``adj_args``: launch the kernel's adjoint with these
    adjoint arguments (None for an array: no gradient). The Launch keeps no tensor alive between renders: it
    stores bare copies of the descriptors; the caller's own references cover the enqueue (the allocator is
    stream-ordered)."""
    if dim <= 0:
        return
    adjoint = adj_args is not None
    key = (kernel, device.alias, block_dim, adjoint)
    site = _sites.get(key)
    if site is None:
        bare = [_bare(a) for a in args]
        bare_adj = [_bare(a) if a is not None else _null_array() for a in adj_args] if adjoint else []
        launch = wp.launch(kernel, dim=dim, inputs=bare, adj_inputs=bare_adj, adjoint=adjoint, device=device,
                           block_dim=block_dim, record_tape=False, record_cmd=True)
        site = _sites[key] = _Site(launch, dim, adjoint)
        launch.launch()
        return
    launch = site.launch
    _fill(site, 1, args)
    if adjoint:
        _fill(site, len(args) + 1, [a if a is not None else _null_array() for a in adj_args])
    if dim != site.dim:
        launch.set_dim(dim)
        site.dim = dim
    if device.is_cuda:
        if _runtime().core.wp_cuda_launch_kernel(device.context, site.hook, launch.bounds.size, launch.max_blocks,
                                                 launch.block_dim, int(launch.grid_stride), launch.cluster_dim,
                                                 site.smem, launch.params_addr, device.stream.cuda_stream, None):
            launch.launch()  # the failure again, through Warp's own error report
    else:
        launch.launch()
    del args, adj_args


def _fill(site: _Site, first: int, values) -> None:
    """Write the arguments into the launch's own parameter slots (by value: the launch keeps no reference to
    them, so no tensor outlives its render through a descriptor's ``_ref``)."""
    params, kinds, addrs, sizes = site.launch.params, site.kinds, site.addrs, site.sizes
    for i, a in enumerate(values, first):
        if kinds[i] == _SCALAR:
            params[i].value = a
        else:
            if isinstance(a, wp.array):
                a = a.__ctype__()
            ctypes.memmove(addrs[i], ctypes.addressof(a), sizes[i])


_RUNTIME = None


def _runtime():
    global _RUNTIME
    if _RUNTIME is None:
        try:
            from warp._src.context import runtime
        except ImportError:  # Warp before 1.10
            from warp.context import runtime
        _RUNTIME = runtime
    return _RUNTIME


def _null_array():
    return (_ARRAY_T or warp_array_ctype())()


def _bare(a):
    if isinstance(a, wp.array):
        return a.__ctype__()
    if isinstance(a, _ARRAY_T or warp_array_ctype()):
        return type(a).from_buffer_copy(a)  # the same descriptor without its tensor reference
    if isinstance(a, (ctypes.Array, ctypes.Structure)):  # a vector or matrix value: the recorded launch may keep the
        return type(a).from_buffer_copy(a)  # object itself as its parameter slot, which later calls overwrite
    return a


_SORT_KERNELS = {torch.float32: "float", torch.int32: "int"}
_sort_fns: dict = {}


def _runtime_sort(kind: str, side: str):
    key = (kind, side)
    if key not in _sort_fns:
        try:
            from warp._src.context import runtime
        except ImportError:  # Warp before 1.10
            from warp.context import runtime
        _sort_fns[key] = getattr(runtime.core, f"wp_radix_sort_pairs_{kind}_{side}", None)
    return _sort_fns[key]


def sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, begin_bit: int = 0, end_bit: int = 32) -> None:
    """``wp.utils.radix_sort_pairs`` on torch buffers (keys float32 or int32, values int32, each with room for
    2 * count) on the current Warp stream, called straight into Warp's runtime: no wp.array wrappers, no checks
    (a render sorts twice). Falls back to wp.utils where the runtime entry is missing."""
    if count == 0:
        return
    fn = _runtime_sort(_SORT_KERNELS[keys.dtype], "device" if keys.is_cuda else "host")
    if fn is None:
        wp.utils.radix_sort_pairs(wp.from_torch(keys), wp.from_torch(values), count, begin_bit, end_bit)
    else:
        fn(keys.data_ptr(), values.data_ptr(), count, begin_bit, end_bit, 4)


def canonical(t: torch.Tensor) -> torch.Tensor:
    """``t.contiguous()`` with the row-major strides spelled out. Torch calls a tensor contiguous whatever the
    stride of a size-1 dimension (a [1, 3] column slice of a [1, 26] PLY table keeps stride 26), but Warp
    compares an array's strides with its gradient's literally, so one Gaussian would fail the backward. The
    memory is the same; only the unused stride changes (a view, no copy)."""
    t = t.contiguous()
    strides, step = [], 1
    for n in reversed(t.shape):
        strides.append(step)
        step *= n
    strides = tuple(reversed(strides))
    return t if t.stride() == strides else t.as_strided(t.shape, strides)


def to_warp(t: torch.Tensor, dtype, grad: torch.Tensor | None = None):
    if t.numel() == 0:  # torch gives empty tensors arbitrary strides, which from_torch rejects
        return wp.zeros(t.shape[0], dtype=dtype, device=wp.device_from_torch(t.device), requires_grad=grad is not None)
    return wp.from_torch(canonical(t.detach()), dtype=dtype, grad=None if grad is None else canonical(grad),
                         requires_grad=grad is not None)


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


_inputs: dict = {}  # id(tensor) -> (weakref, layout key, descriptor): the inputs of recent renders


def input_ct(t: torch.Tensor, dtype):
    """``ct`` of a render input, reused across renders while the tensor keeps its storage and layout (an optimizer
    steps the same tensors in place). The entry goes when the tensor does; a tensor given new storage
    (``t.data = ...``) gets a new descriptor. The descriptor holds a detached alias of t's storage, never t."""
    if t.numel() and t.stride()[-1] != 1:  # the vector dimension must be innermost and contiguous
        return ct(t.detach().contiguous(), dtype)
    key = (t.data_ptr(), t.shape, t.stride(), t.dtype)
    hit = _inputs.get(id(t))
    if hit is not None and hit[0]() is t and hit[1] == key:
        return hit[2]
    a = ct(t.detach(), dtype)
    tid = id(t)
    _inputs[tid] = (weakref.ref(t, lambda _r: _inputs.pop(tid, None)), key, a)
    return a


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


def camera_values(cam: Camera):
    """(R rows, t, center) of the camera as Python floats, from one read of the 4x4 (no torch ops per value)."""
    m = cam.world_to_camera.tolist()
    R = [row[:3] for row in m[:3]]
    t = [row[3] for row in m[:3]]
    center = [-(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]) for j in range(3)]
    return R, t, center


def camera_args(cam: Camera, K, values=None):
    """(R, t, fx, fy, cx, cy, width, height, near, far) as kernel values (array reads would become atomics in
    the adjoint); ``values``: ``camera_values(cam)`` when the caller already has them. Kept per camera (by value):
    building Warp's matrix and vector values costs more host time than the launch that takes them."""
    R, t, _ = values or camera_values(cam)
    s = K.scalar
    key = (s, *R[0], *R[1], *R[2], *t, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.near, cam.far)
    return list(_kept(key, lambda: [K.mat33(*[s(v) for row in R for v in row]), K.vec3(*map(s, t)), s(cam.fx),
                                    s(cam.fy), s(cam.cx), s(cam.cy), cam.width, cam.height, s(cam.near), s(cam.far)]))


def no_grad_args(values) -> list:
    """Zero adjoints for kernel values that get no gradient (the camera's): what a by-hand adjoint launch passes."""
    return [0 if isinstance(a, int) else type(a)() for a in values]


_values: dict = {}  # key -> a kernel value built from it (camera arguments, camera centers, backgrounds)


def _kept(key, make):
    """``make()``, kept under ``key`` (bounded: a long orbit of cameras clears it now and then)."""
    v = _values.get(key)
    if v is None:
        if len(_values) > 2048:
            _values.clear()
        v = _values[key] = make()
    return v


def kernel_vec3(K, xyz):
    """``K.vec3(*xyz)`` in K's scalar type, kept per value (the camera center, the background)."""
    return _kept((K.scalar, *xyz), lambda: K.vec3(*map(K.scalar, xyz)))


def camera_center(K, values):
    """The camera position of ``camera_values`` as a kernel value."""
    return kernel_vec3(K, values[2])


def project(K, args, colors: torch.Tensor, cam: Camera, cam_values, n: int, dtype, device):
    """Launch the projection: returns (Projected, its output descriptors [means2d, conic, depth, opacity, color,
    radii]); the colors (``ShadeFn``'s output, ``args[4]``) pass through. The adjoint is launched by
    ``project_adjoint``."""
    means2d, conic, depth, opacity = packed_zeros([(n, 2), (n, 3), (n,), (n,)], dtype, device)
    proj = Projected(means2d, None, conic, depth, opacity, colors, torch.zeros(n, dtype=torch.int32, device=device))
    outs = [ct(means2d, K.vec2), ct(conic, K.vec3), ct(depth), ct(opacity), args[4], ct(proj.radii)]
    fast_launch(K.project, n, args[:4] + camera_args(cam, K, cam_values) + outs[:4] + outs[5:], wdevice(device))
    return proj, outs


def project_adjoint(K, args, pouts, grads, out_grads, cam: Camera, cam_values, n: int, device):
    """The projection's Warp-generated adjoint: dL/d(screen mean, conic, depth, opacity) -> ``grads`` of the four
    geometric inputs (accumulated). What wp.Tape would launch, with the gradient buffers passed as adjoint
    arguments: the forward descriptors carry no gradient pointers, so no output gradient is zeroed on the way (the
    screen-mean one stays dL/d(screen mean))."""
    cam_args = camera_args(cam, K, cam_values)
    fast_launch(K.project, n, args[:4] + cam_args + pouts[:4] + pouts[5:], wdevice(device),
                adj_args=[ct(g, a) for g, a in zip(grads, (K.vec3, K.vec4, K.vec3, None))] + no_grad_args(cam_args)
                + [ct(out_grads[0], K.vec2), ct(out_grads[1], K.vec3), ct(out_grads[2]), ct(out_grads[3]), None])


def binning_geometry(proj: Projected):
    """float32 views of what the binning kernels read (copies only on the float64 path; the projection's
    outputs are contiguous)."""
    if proj.depth.dtype == torch.float32:
        return [ct(proj.means2d, wp.vec2), ct(proj.radii), ct(proj.conic, wp.vec3), ct(proj.opacity)]
    return [ct(proj.means2d.float(), wp.vec2), ct(proj.radii), ct(proj.conic.float(), wp.vec3),
            ct(proj.opacity.float())]


_dummies: dict = {}


def _dummy(dtype, device) -> torch.Tensor:
    """A one-element buffer for kernel outputs that a render does not ask for (never read)."""
    key = (dtype, device)
    t = _dummies.get(key)
    if t is None:
        t = _dummies[key] = torch.zeros(1, dtype=dtype, device=device)
    return t


def _zeros(n: int, dtype, device) -> torch.Tensor:
    """A kept zero vector of n elements (read-only: the broadcast row of an absent upstream gradient)."""
    key = (n, dtype, device)
    t = _dummies.get(key)
    if t is None:
        t = _dummies[key] = torch.zeros(n, dtype=dtype, device=device)
    return t


def tile_grid(width: int, height: int) -> tuple[int, int]:
    return (width + TILE - 1) // TILE, (height + TILE - 1) // TILE


def warp_padded(n: int) -> int:
    """Thread count for the binning kernels: n rounded up to whole warps (their lanes cooperate)."""
    return (n + 31) // 32 * 32


def count_intersections(K, proj: Projected, width: int, height: int, all_tiles: bool = False):
    """Tiles touched per Gaussian [N] int32, their total, the binning's inputs, and the depth sort's buffers
    (float32 depths and Gaussian ids, each with the radix sort's 2x room, filled by the same kernel): the total
    is the one host sync per render (it sizes the key buffers). Only the projection runs before it."""
    n = proj.depth.shape[0]
    device = proj.depth.device
    geometry = binning_geometry(proj)
    if n == 0:
        return torch.empty(0, dtype=torch.int32, device=device), 0, geometry, None
    tiles_x, tiles_y = tile_grid(width, height)
    total = torch.zeros(1, dtype=torch.int64, device=device)
    # the binning's per-Gaussian int32 and float32 buffers as views of one allocation (host time bounds a render's
    # forward; all of them go when the forward ends): counts [N], depth sort keys and values [2N] each, counts in
    # depth order and depth ranks [N]
    counts, depth_keys, order, sorted_counts, rank = torch.empty(7 * n, dtype=torch.int32, device=device) \
        .split_with_sizes([n, 2 * n, 2 * n, n, n])
    depth_keys = depth_keys.view(torch.float32)
    ranges = torch.empty(tiles_x * tiles_y, 2, dtype=torch.int32, device=device)  # zeroed by the kernel
    fast_launch(K.count_tiles, warp_padded(max(n, tiles_x * tiles_y)),
                [*geometry, ct(proj.depth.float()), n, tiles_x, tiles_y, width, height, int(all_tiles), ct(counts),
                 ct(total), ct(depth_keys), ct(order), ct(ranges)], wdevice(device))
    total = int(total.item())
    if total >= 2**31:
        raise RuntimeError(f"{total} tile intersections exceed the int32 index range; render at a lower resolution")
    return counts, total, geometry, (depth_keys, order, ranges, sorted_counts, rank)


def bin_tiles(K, proj: Projected, counts: torch.Tensor, total: int, geometry, sort_buffers, width: int, height: int,
              all_tiles: bool = False):
    """Depth order, then stably tile-sorted keys -> per-tile [start, end) ranges [tiles, 2] and the sorted
    Gaussian ids [total]."""
    device = proj.depth.device
    wdev = wdevice(device)
    n = proj.depth.shape[0]
    tiles_x, tiles_y = tile_grid(width, height)
    if sort_buffers is None:  # no Gaussians: nothing was counted
        return torch.zeros(tiles_x * tiles_y, 2, dtype=torch.int32, device=device), \
            torch.zeros(1, dtype=torch.int32, device=device), tiles_x, tiles_y
    depth_keys, order, ranges, sorted_counts, rank = sort_buffers
    if total == 0:
        return ranges, torch.zeros(1, dtype=torch.int32, device=device), tiles_x, tiles_y
    # depth order (culled Gaussians sort anywhere: they emit no keys)
    sort_pairs(depth_keys, order, n)
    del depth_keys
    order = order[:n]
    fast_launch(K.depth_rank, n, [ct(order), ct(counts), ct(sorted_counts), ct(rank)], wdev)
    ends = torch.cumsum(sorted_counts, 0, dtype=torch.int32)  # [N] inclusive, in depth order; < 2**31 (checked)
    # two allocations, not one: the sorted ids outlive the keys until the blending backward, and on a wide image
    # (beer, 720x1280) that stage holds the backward's peak
    keys = torch.empty(2 * total, dtype=torch.int32, device=device)  # each with the radix sort's 2x room
    ids = torch.empty(2 * total, dtype=torch.int32, device=device)
    fast_launch(K.emit_keys, warp_padded(n), [*geometry, ct(rank), ct(ends), ct(counts), n, tiles_x, tiles_y, width,
                                              height, int(all_tiles), ct(keys), ct(ids)], wdev)
    tile_bits = max(1, (tiles_x * tiles_y).bit_length())  # room for the sentinel tile id
    sort_pairs(keys, ids, total, 0, tile_bits)  # stable: each tile stays in depth order
    fast_launch(K.tile_ranges, total, [ct(keys), total, ct(ranges)], wdev)
    # a view: the sort's second half lives until the blending backward has run (no copy per render; the
    # backward's peak comes later, at the SH gradients, after these are freed)
    return ranges, ids[:total], tiles_x, tiles_y


def blend(K, proj: Projected, pouts, counts, total: int, geometry, sort_buffers, cam: Camera, settings: dict):
    """Bin, then blend front to back: the images, and the per-pixel state the blending backward reads."""
    device, dtype, n = proj.depth.device, proj.depth.dtype, proj.depth.shape[0]
    H, W = cam.height, cam.width
    ranges, ids, tiles_x, tiles_y = bin_tiles(K, proj, counts, total, geometry, sort_buffers, W, H,
                                              settings["all_tiles"])
    color = torch.empty(H, W, 3, dtype=dtype, device=device)
    alpha = torch.empty(H, W, dtype=dtype, device=device)
    want_depth = settings.get("depth", True)
    depth = torch.empty((H, W) if want_depth else (1, 1), dtype=dtype, device=device)  # (1, 1): never written
    T = torch.empty(H, W, dtype=dtype, device=device)
    last = torch.empty(H, W, dtype=torch.int32, device=device)
    weights = torch.zeros(n, dtype=dtype, device=device) if settings["weights"] else _dummy(dtype, device)
    bg = kernel_vec3(K, settings["background"])
    w_means2d, w_conic, w_depth, w_opacity, w_color, _w_radii = pouts
    args = [ct(ranges), ct(ids), w_means2d, w_conic, w_opacity, w_color, w_depth, bg, W, H, tiles_x, int(want_depth)]
    fast_launch(K.blend_forward, tiles_x * tiles_y * TILE * TILE,
                args + [int(settings["weights"]), ct(color, K.vec3), ct(alpha), ct(depth), ct(T), ct(last), ct(weights)],
                wdevice(device), block_dim=TILE * TILE)
    state = {"args": args, "saved": [ct(depth), ct(T), ct(last)], "threads": tiles_x * tiles_y * TILE * TILE}
    if _capture is not None:
        _capture.update(proj=proj, counts=counts, total=total, ranges=ranges, ids=ids, last=last,
                        tiles=(tiles_x, tiles_y))
    return color, alpha, depth if want_depth else None, weights, state


class ShadeFn(torch.autograd.Function):
    """(means, sh) -> colors [N, 3] = max(SH up to ``degree`` (view direction from the camera center) + 0.5, 0),
    for every Gaussian (a culled one's color is never blended).

    Its own op, before the raster op (gsplat's stage split): autograd runs its backward after the raster op's,
    when the image gradient and the raster state are gone, so the SH coefficients' gradient (48 floats a Gaussian at
    degree 3, the largest buffer of a backward) never coexists with them. Backward by hand: the direction part of
    dL/dmeans and the coefficient gradients (Warp's generated adjoint would add atomically per coefficient read)."""

    @staticmethod
    def forward(ctx, means, sh, cam_values, degree: int):
        K = kernels_for(means.dtype)
        device, n = means.device, means.shape[0]
        colors = torch.empty(n, 3, dtype=means.dtype, device=device)
        center = camera_center(K, cam_values)
        with warp_on(device) as wdev:
            fast_launch(K.sh_color, n, [input_ct(means, K.vec3), input_ct(sh, K.vec3), center, degree,
                                        ct(colors, K.vec3)], wdev)
        ctx.save_for_backward(means, sh)
        ctx.center, ctx.degree = center, degree
        return colors

    @staticmethod
    def backward(ctx, g_colors):
        means, sh = ctx.saved_tensors
        K = kernels_for(means.dtype)
        device, n = means.device, means.shape[0]
        n_coeffs = (ctx.degree + 1) ** 2
        g_means = torch.empty_like(means)  # sh_backward stores every row (0 where dL/dcolor is 0)
        g_rgb = torch.empty(n, 3, dtype=means.dtype, device=device)  # dL/d(SH sum), the clamp applied
        g_sh = torch.empty_like(sh) if n_coeffs == sh.shape[1] else torch.zeros_like(sh)  # degree < stored: rest 0
        with warp_on(device) as wdev:
            m = input_ct(means, K.vec3)
            rgb = ct(g_rgb, K.vec3)
            fast_launch(K.sh_backward, n, [m, input_ct(sh, K.vec3), ctx.center, ctx.degree,
                                           ct(g_colors.contiguous(), K.vec3), rgb, ct(g_means, K.vec3)], wdev)
            fast_launch(K.sh_coeff_grad, n * n_coeffs, [m, ctx.center, n_coeffs, rgb, ct(g_sh, K.vec3)], wdev)
        return g_means, g_sh, None, None


class RasterizeFn(torch.autograd.Function):
    """(means, quats, log_scales, opacity_logits, colors, means2d_probe) -> color, alpha, depth, radii, weights.

    ``colors`` [N, 3] come from ``ShadeFn``; ``means2d_probe`` is a zero tensor whose gradient receives dL/d(screen
    mean) for density control.

    The backward runs the blending backward and the projection's Warp-generated adjoint, on array descriptors (no
    wp.Tape, no wp.array per render). Memory: the binning and per-pixel state (sorted ids, T, last) are dropped
    after the blending backward, before the input gradients are allocated, and the projection when the op returns;
    the backward's peak is ShadeFn's, after all of these are gone. A second backward through the same graph
    (retain_graph, gradcheck) rebuilds what the first freed (projection, binning) from the saved inputs."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, colors, means2d_probe, cam, cam_values, settings):
        K = kernels_for(means.dtype)
        device, n = means.device, means.shape[0]
        with warp_on(device):
            args = [input_ct(t, ty) for t, ty in zip((means, quats, log_scales, opacity_logits),
                                                      (K.vec3, K.vec4, K.vec3, None))] + [ct(colors, K.vec3)]
            proj, pouts = project(K, args, colors, cam, cam_values, n, means.dtype, device)
            binning = count_intersections(K, proj, cam.width, cam.height, settings["all_tiles"])
            color, alpha, depth, weights, first = blend(K, proj, pouts, *binning, cam, settings)
            del binning
        ctx.state = {"proj": proj, "pouts": pouts, "blend": first, "args": args, "cam": cam, "cam_values": cam_values,
                     "settings": settings}
        # the inputs are read by the adjoints: saving them lets autograd refuse a backward after an in-place
        # change (torch's version counter) instead of returning stale gradients
        ctx.save_for_backward(means, quats, log_scales, opacity_logits, colors)
        ctx.mark_non_differentiable(proj.radii, weights)
        return color, alpha, depth, proj.radii, weights if settings["weights"] else None  # depth None if not asked

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, _g_radii, _g_weights):
        state = ctx.state
        args, cam, cam_values, settings = (state[k] for k in ("args", "cam", "cam_values", "settings"))
        inputs = ctx.saved_tensors  # (raises if an input changed in place since the forward)
        means = inputs[0]
        K = kernels_for(means.dtype)
        device, dtype, n = means.device, means.dtype, means.shape[0]
        H, W = cam.height, cam.width
        with warp_on(device) as wdev:
            proj, pouts = state.pop("proj", None), state.pop("pouts", None)
            if proj is None:  # a second backward through the same graph: the first freed the projection
                proj, pouts = project(K, args, inputs[4], cam, cam_values, n, dtype, device)
            # gradient buffers exist only from here on (fresh per call, so a second backward through the same
            # graph, e.g. gradcheck or retain_graph, never sees the first call's sums). What outlives this op (the
            # probe's dL/d(screen mean), dL/dcolor for ShadeFn, dL/dmeans until ShadeFn adds its part) shares one
            # buffer; the geometric gradients go with this op, the other inputs' once autograd has accumulated them
            kept_flat = torch.zeros(8 * n, dtype=dtype, device=device)  # [means2d (N, 2) | color (N, 3) | means (N, 3)]
            geo_flat = torch.zeros(5 * n, dtype=dtype, device=device)  # [conic (N, 3) | opacity (N) | depth (N)]
            g_means2d, g_rgb = kept_flat[:2 * n].view(n, 2), kept_flat[2 * n:5 * n].view(n, 3)
            g_means = kept_flat[5 * n:].view(n, 3)
            g_conic, g_opacity, g_depth_n = geo_flat[:3 * n].view(n, 3), geo_flat[3 * n:4 * n], geo_flat[4 * n:]
            # an absent upstream gradient is a broadcast zero (stride 0 over rows): no [H, W] buffer, no memset
            ups = [g.contiguous() if g is not None else _zeros(shape[-1], dtype, device).expand(shape)
                   for g, shape in ((g_color, (H, W, 3)), (g_alpha, (H, W)), (g_depth, (H, W)))]
            # the sorted ids, T and last go when this block ends (stream-ordered: safe with the launch queued);
            # a second backward through the same graph rebuilds them
            st = state.pop("blend", None) or blend(
                K, proj, pouts, *count_intersections(K, proj, W, H, settings["all_tiles"]), cam, settings)[4]
            fast_launch(K.blend_backward, st["threads"],
                        st["args"] + st["saved"] + [ct(ups[0], K.vec3), ct(ups[1]), ct(ups[2])]
                        + [ct(kept_flat), ct(geo_flat)], wdev, block_dim=TILE * TILE)
            del st, ups, proj
            grads = [g_means] + packed_zeros([t.shape for t in inputs[1:4]], dtype, device)
            project_adjoint(K, args, pouts, grads, (g_means2d, g_conic, g_depth_n, g_opacity), cam, cam_values, n,
                            device)
        return (*grads, g_rgb, g_means2d, None, None, None)
