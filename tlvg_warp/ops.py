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
import functools
import math
import os
import sys
import tempfile
import weakref
from dataclasses import dataclass

import torch
import warp as wp

from .kernels import raster_kernels
from .types import Camera

TILE = 16

_initialized = False


NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"  # what Warp's C library prints without a GPU driver


def init_warp() -> None:
    global _initialized
    if not _initialized:
        if os.environ.get("TLVG_WARP_VERBOSE", "") == "":  # no banner, no per-module load lines
            wp.config.quiet = True  # Warp before 1.19
            if hasattr(wp, "LOG_WARNING"):
                wp.config.log_level = wp.LOG_WARNING  # Warp 1.19 replaced `quiet` by a log level
            if not cuda_driver_present():
                # a machine without a GPU: Warp's native library says so on stderr whatever ``quiet`` is; that
                # line is dropped (anything else it writes is passed on)
                without_lines(wp.init, NO_DRIVER)
                _initialized = True
                return
        wp.init()
        _initialized = True


def cuda_driver_present() -> bool:
    """Whether the CUDA driver library loads (what Warp's ``init_cuda_driver`` tries: libcuda.so, libcuda.so.1,
    nvcuda.dll on Windows)."""
    names = ("nvcuda.dll",) if os.name == "nt" else ("libcuda.so", "libcuda.so.1")
    for name in names:
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


def without_lines(fn, drop: str):
    """``fn()`` with what it writes to file descriptor 2 (C code included) captured, and passed on to stderr
    without the lines that contain ``drop``."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no file descriptor 2 to redirect: run as it is
        return fn()
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            return fn()
        finally:
            with contextlib.suppress(OSError, ValueError):
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            kept = [ln for ln in tmp.read().decode(errors="replace").splitlines(keepends=True) if drop not in ln]
            if kept:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()


def kernels_for(dtype: torch.dtype):
    K = _kernel_sets.get(dtype)  # a dict read: this runs several times a render
    if K is None:
        init_warp()
        K = _kernel_sets[dtype] = raster_kernels({torch.float32: "float32", torch.float64: "float64"}[dtype])
    return K


_kernel_sets: dict = {}  # torch dtype -> its kernels


_wdevs: dict = {}  # torch device -> its Warp device


def wdevice(device: torch.device):
    """``wp.device_from_torch(device)``, cached (a few microseconds a call, several calls a render)."""
    d = _wdevs.get(device)
    if d is None:
        d = _wdevs[device] = wp.device_from_torch(device)
    return d


_streams: dict = {}  # torch stream handle -> its wp.Stream (wrapping one registers it with Warp: not per call)


class _WarpOn:
    """``warp_on(device)``'s context manager, one per torch device, reentrant (a stack of what each entry changed).
    A class, not a generator: it is entered a few times per render and per training step, and the host time of a
    render bounds its forward."""

    __slots__ = ("device", "wdev", "stack")

    def __init__(self, device: torch.device):
        self.device, self.wdev, self.stack = device, wdevice(device), []

    def __enter__(self):
        if self.device.type != "cuda":
            self.stack.append(None)
            return self.wdev
        index = self.device.index if self.device.index is not None else torch.cuda.current_device()
        handle = torch._C._cuda_getCurrentRawStream(index)  # an int: no torch Stream object per call
        stream = _streams.get(handle)
        if stream is None:
            ts = torch.cuda.current_stream(self.device)
            stream = _streams[handle] = wp.stream_from_torch(ts)  # keeps ts alive: its handle stays unique
        wdev = stream.device
        if wdev.stream is not stream:
            wdev.set_stream(stream, sync=True)
        # what wp.ScopedDevice does, without the CUDA context push and pop when the context is already current
        # (torch's own device: the usual case)
        runtime = wdev.runtime
        core = runtime.core
        saved = runtime.default_device
        runtime.default_device = wdev
        push = core.wp_cuda_context_get_current() != wdev.context
        if push:
            core.wp_cuda_context_push_current(wdev.context)
        self.stack.append((runtime, saved, push))
        return wdev

    def __exit__(self, *exc):
        entry = self.stack.pop()
        if entry is not None:
            runtime, saved, push = entry
            if push:
                runtime.core.wp_cuda_context_pop_current()
            runtime.default_device = saved
        return False


_warp_ons: dict = {}  # torch device -> its _WarpOn


def warp_on(device: torch.device) -> _WarpOn:
    """``with warp_on(device) as wdev``: run Warp launches on torch's current stream so no extra synchronization is
    needed, with ``wdev`` Warp's default device. The stream stays the Warp device's current stream after the block
    (set once, with one wait on Warp's previous stream; a block on another torch stream switches it again):
    entering and leaving a ScopedStream per render cost two cross-stream synchronizations of host time each."""
    w = _warp_ons.get(device)
    if w is None:
        w = _warp_ons[device] = _WarpOn(device)
    return w


def warp_array_ctype():
    """Warp's C array descriptor class (``array_t``): what ``wp.from_torch(..., return_ctype=True)`` builds.

    The one place this module touches Warp's private API (``warp._src.types``; ``warp.types`` before 1.10).
    tests/test_raster.py checks that it still is the class from_torch returns, with the fields ``ct`` fills,
    so a Warp upgrade that moves or changes it fails there by name rather than as a crash in a kernel."""
    global _ARRAY_T
    if _ARRAY_T is None:
        try:  # at first use, not at the top: a Warp that lacks it fails here with the message below
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


def ct_at(base: torch.Tensor, offset: int, shape: tuple, elem: int, vec: int = 1):
    """The descriptor of a contiguous array of ``shape`` (each element ``vec`` scalars of ``elem`` bytes) that
    starts ``offset`` bytes into ``base``'s storage: what ``ct`` of a view of ``base`` gives, without making the
    torch view (a host op of its own, several per render). Keeps ``base`` alive."""
    key = ("at", shape, elem, vec)
    template = _templates.get(key)
    if template is None:
        strides, step = [], elem * vec
        for n in reversed(shape):
            strides.append(step)
            step *= n
        template = _templates[key] = warp_array_ctype()(0, 0, len(shape), tuple(shape), tuple(reversed(strides)))
    a = _ARRAY_T.from_buffer_copy(template)
    a.data = base.data_ptr() + offset
    a._ref = base
    return a


class _Site:
    """One recorded ``wp.Launch`` per (kernel, device, block_dim, forward/adjoint) and how to refill it: per
    parameter slot a setter kind (descriptor, ctypes scalar, vector/matrix copied by bytes), found once; the
    launch's dimensions, reset only when they change (``Launch.set_dim`` validates in Python each time). On CUDA
    the launch's parameter addresses are repointed per call (``_set_args``) and dangle between calls: only
    ``fast_launch`` may enqueue a site's launch."""

    __slots__ = ("launch", "dim", "kinds", "addrs", "sizes", "hook", "smem", "enqueue")

    def __init__(self, launch, dim: int, adjoint: bool, values: list):
        self.launch, self.dim = launch, dim
        self.enqueue = None  # CUDA: Warp's runtime launch with this site's fixed arguments bound (_enqueue_of)
        params = launch.params  # [0] is the launch bounds; the slots are never replaced (written in place)
        self.kinds = [_slot_kind(p) for p in params]
        for i, a in enumerate(values, 1):  # a struct value (the camera) is passed as its ctypes bytes
            if wp.types.is_struct(a):
                self.kinds[i] = _STRUCT
        self.addrs = [ctypes.addressof(p) for p in params]
        self.sizes = [ctypes.sizeof(p) for p in params]
        hooks = launch.hooks
        self.hook, self.smem = ((hooks.backward, hooks.backward_smem_bytes) if adjoint
                                else (hooks.forward, hooks.forward_smem_bytes))


def _slot_kind(p) -> int:
    if isinstance(p, (ctypes.Structure, ctypes.Array)):
        return _BYTES  # an array descriptor, a vector or a matrix: its bytes copied into the slot
    return _SCALAR  # a ctypes scalar: its .value set


_BYTES, _SCALAR, _STRUCT = 1, 2, 3
_sites: dict = {}  # (kernel, device alias, block_dim, adjoint) -> _Site


def fast_launch(kernel, dim: int, args, device, block_dim: int | None = None, adj_args=None) -> None:
    """``wp.launch(kernel, dim, inputs=args, device=device, block_dim=block_dim, record_tape=False)`` for the
    per-render launches, with less host time: the first call per (kernel, device, block_dim, forward/adjoint)
    records a ``wp.Launch``; later calls write its parameter slots directly (array descriptors from ``ct``,
    ``wp.array``s, scalars, vectors) and, on CUDA, enqueue it through Warp's runtime, skipping ``wp.launch``'s
    per-argument checks and packing and ``Launch``'s per-call bookkeeping (a render's host time bounds its
    forward: the GPU waits on the host for most of it). ``adj_args``: launch the kernel's adjoint with these
    adjoint arguments (None for an array: no gradient). The Launch keeps no tensor alive between renders: on CUDA
    its parameter addresses point at the caller's descriptors only until the enqueue has copied them, on the CPU
    it holds bare copies (``_set_args``); the caller's own references cover the enqueue (the allocator is
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
        site = _sites[key] = _Site(launch, dim, adjoint, bare + bare_adj)
        launch.launch()
        return
    launch = site.launch
    if adjoint:
        args = list(args) + [a if a is not None else _null_array() for a in adj_args]
    if dim != site.dim:
        launch.set_dim(dim)
        site.dim, site.enqueue = dim, None
    if device.is_cuda:
        keep = _set_args(site, args, True)  # the slots point at the caller's descriptors until the launch reads them
        enqueue = site.enqueue or _enqueue_of(site, device)
        if enqueue(device.stream.cuda_stream, None):
            launch.launch()  # the failure again, through Warp's own error report
        del keep
    else:
        _set_args(site, args, False)
        launch.launch()
    del args, adj_args


def _enqueue_of(site: _Site, device):
    """``wp_cuda_launch_kernel`` with every argument but the stream bound (they change only with the dimensions,
    which reset it): nine attribute reads fewer per launch."""
    launch = site.launch
    site.enqueue = functools.partial(_runtime().core.wp_cuda_launch_kernel, device.context, site.hook,
                                     launch.bounds.size, launch.max_blocks, launch.block_dim, int(launch.grid_stride),
                                     launch.cluster_dim, site.smem, launch.params_addr)
    return site.enqueue


def _set_args(site: _Site, values, cuda: bool) -> list:
    """Scalars into the launch's own slots; descriptors, vectors and matrices: on CUDA the launch's parameter
    addresses point at them (what ``Launch.set_param_at_index_from_ctype`` does; cuLaunchKernel copies them at
    the launch: a pointer store instead of a copy of the bytes), on the CPU their bytes are copied into the slots,
    which the call reads (so the launch keeps no reference: no tensor outlives its render through a descriptor's
    ``_ref``). Returns what must stay alive until the launch (``wp.array`` descriptors made here)."""
    params, kinds, keep = site.launch.params, site.kinds, []
    ptrs, addrs, sizes = site.launch.params_addr, site.addrs, site.sizes
    for i, a in enumerate(values, 1):
        kind = kinds[i]
        if kind == _SCALAR:
            params[i].value = a
        else:
            if kind == _STRUCT:
                a = a.__ctype__()  # the instance's own bytes (kept alive by the caller's reference to it)
            elif isinstance(a, wp.array):
                a = a.__ctype__()
                keep.append(a)
            if cuda:
                ptrs[i] = ctypes.addressof(a)
            else:
                ctypes.memmove(addrs[i], ctypes.addressof(a), sizes[i])
    return keep


_RUNTIME = None


def _runtime():
    global _RUNTIME
    if _RUNTIME is None:
        try:  # at call time: wp.init() sets Warp's runtime (it is None when this module is imported)
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
    if wp.types.is_struct(a):  # a struct value (the camera): the same, its bytes are the launch's slot
        copy = type(a)()
        copy.assign(a)
        return copy
    return a


_SORT_KERNELS = {torch.float32: "float", torch.int32: "int"}
_sort_fns: dict = {}


def _runtime_sort(kind: str, side: str):
    key = (kind, side)
    if key not in _sort_fns:
        try:  # at call time: wp.init() sets Warp's runtime
            from warp._src.context import runtime
        except ImportError:  # Warp before 1.10
            from warp.context import runtime
        _sort_fns[key] = getattr(runtime.core, f"wp_radix_sort_pairs_{kind}_{side}", None)
    return _sort_fns[key]


def sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, begin_bit: int = 0, end_bit: int = 32) -> None:
    """``wp.utils.radix_sort_pairs`` on torch buffers (keys float32 or int32, values int32, each with room for
    2 * count) on the current Warp stream, called straight into Warp's runtime: no wp.array wrappers, no checks
    (a render sorts twice). Falls back to wp.utils where the runtime entry is missing."""
    sort_pairs_at(keys.dtype, keys.device, keys.data_ptr(), values.data_ptr(), count, begin_bit, end_bit)


def sort_pairs_at(key_dtype: torch.dtype, device: torch.device, keys: int, values: int, count: int,
                  begin_bit: int = 0, end_bit: int = 32) -> None:
    """``sort_pairs`` on raw addresses (buffers inside a larger allocation: no torch view per call)."""
    if count == 0:
        return
    fn = _runtime_sort(_SORT_KERNELS[key_dtype], "device" if device.type == "cuda" else "host")
    if fn is None:
        dev, typ = wdevice(device), {torch.float32: wp.float32, torch.int32: wp.int32}[key_dtype]
        k = wp.array(ptr=keys, dtype=typ, shape=(2 * count,), device=dev)
        v = wp.array(ptr=values, dtype=wp.int32, shape=(2 * count,), device=dev)
        wp.utils.radix_sort_pairs(k, v, count, begin_bit, end_bit)
    else:
        fn(keys, values, count, begin_bit, end_bit, 4)


SCAN_INT32_LIMIT = 2**31  # below this bound on the total the ends are scanned in int32 (the tests lower it)
_scan_fns: dict = {}


def inclusive_scan_at(src: int, dst: int, n: int, device: torch.device) -> None:
    """Inclusive prefix sum of n int32 at address ``src`` into ``dst`` on the current Warp stream: Warp's runtime
    scan (CUB on a GPU), called directly (torch.cumsum costs a dispatch and a view of host time per render)."""
    side = "device" if device.type == "cuda" else "host"
    fn = _scan_fns.get(side)
    if fn is None:
        fn = _scan_fns[side] = getattr(_runtime().core, f"wp_array_scan_int_{side}")
    fn(src, dst, n, 4, 4, 1, True)


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


_inputs: dict = {}  # (id(tensor), vector dtype?) -> (weakref, layout key, descriptor): the inputs of recent renders


def input_ct(t: torch.Tensor, dtype):
    """``ct`` of a render input, reused across renders while the tensor keeps its storage and layout (an optimizer
    steps the same tensors in place). The entry goes when the tensor does; a tensor given new storage
    (``t.data = ...``) gets a new descriptor. The descriptor holds a detached alias of t's storage, never t."""
    if t.numel() and t.stride()[-1] != 1:  # the vector dimension must be innermost and contiguous
        return ct(t.detach().contiguous(), dtype)
    key = (t.data_ptr(), t.shape, t.stride(), t.dtype)
    slot = (id(t), hasattr(dtype, "_shape_"))  # a tensor read as vectors and as scalars has a descriptor for each
    hit = _inputs.get(slot)
    if hit is not None and hit[0]() is t and hit[1] == key:
        return hit[2]
    a = ct(t.detach(), dtype)
    _inputs[slot] = (weakref.ref(t, lambda _r: _inputs.pop(slot, None)), key, a)
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


def _dummy(dtype, device) -> torch.Tensor:
    """A one-element buffer for kernel outputs that a render does not ask for (never read)."""
    key = (dtype, device)
    t = _dummies.get(key)
    if t is None:
        t = _dummies[key] = torch.zeros(1, dtype=dtype, device=device)
    return t


def _zero_upstream(shape: tuple, dtype, device) -> torch.Tensor:
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
    total: int
    tiles: tuple  # (tiles_x, tiles_y)


def count_intersections(K, pr: Projection, width: int, height: int, all_tiles: bool = False) -> DepthOrder:
    """Tiles touched per Gaussian, the Gaussians in depth order (one radix sort of their depths), each one's
    depth rank and the end of its keys in depth order. Their total (the last end) is the one host sync per render:
    it sizes the key buffers."""
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
        ids = _dummy(torch.int32, device)
        return ct(order.ranges), ct(ids), ids
    tiles_x, tiles_y = order.tiles
    # two allocations, not one: the sorted ids outlive the keys until the blending backward, and on a wide image
    # (beer, 720x1280) that stage holds the backward's peak
    keys = torch.empty(2 * total, dtype=torch.int32, device=device)  # each with the radix sort's 2x room
    ids = torch.empty(2 * total, dtype=torch.int32, device=device)
    fast_launch(K.emit_keys, warp_padded(n), [*order.geometry, order.rank, order.ends, order.counts, n, tiles_x,
                                              tiles_y, width, height, int(all_tiles), ct(keys), ct(ids)], wdev)
    tile_bits = max(1, (tiles_x * tiles_y).bit_length())  # room for the sentinel tile id
    # stable: each tile's list stays in depth order
    sort_pairs_at(torch.int32, device, keys.data_ptr(), ids.data_ptr(), total, 0, tile_bits)
    ranges = ct(order.ranges)
    fast_launch(K.tile_ranges, total, [ct(keys), total, ranges], wdev)
    # the sort's second half lives until the blending backward has run (no copy per render; the backward's peak
    # comes later, at the SH gradients, after these are freed)
    return ranges, ct_at(ids, 0, (total,), 4), ids


def blend(K, pr: Projection, order: DepthOrder, cam: Camera, settings: dict):
    """Bin, then blend front to back: the images, and the per-pixel state the blending backward reads."""
    device, dtype, n = pr.buf.device, pr.buf.dtype, pr.n
    H, W = cam.height, cam.width
    ranges, ids, ids_buf = bin_tiles(K, pr, order, W, H, settings["all_tiles"])
    tiles_x, tiles_y = order.tiles
    color = torch.empty(H, W, 3, dtype=dtype, device=device)
    alpha = torch.empty(H, W, dtype=dtype, device=device)
    want_depth = settings.get("depth", True)
    depth = torch.empty(H, W, dtype=dtype, device=device) if want_depth else _dummy(dtype, device)  # never written
    # transmittance T [H, W] and one past each pixel's last contributor [H, W] int32: one allocation, one lifetime
    e = color.element_size()
    state_px = torch.empty(H * W * (e + 4), dtype=torch.uint8, device=device)
    T, last = ct_at(state_px, 0, (H, W), e), ct_at(state_px, H * W * e, (H, W), 4)
    weights = torch.zeros(n, dtype=dtype, device=device) if settings["weights"] else _dummy(dtype, device)
    bg = kernel_vec3(K, settings["background"])
    w_means2d, w_conic, w_depth, w_opacity, w_color, _w_radii = pr.outs
    args = [ranges, ids, w_means2d, w_conic, w_opacity, w_color, w_depth, bg, W, H, tiles_x, int(want_depth)]
    out_depth = ct(depth) if want_depth else ct_at(depth, 0, (1, 1), e)
    fast_launch(K.blend_forward, tiles_x * tiles_y * TILE * TILE,
                args + [int(settings["weights"]), ct(color, K.vec3), ct(alpha), out_depth, T, last, ct(weights)],
                wdevice(device), block_dim=TILE * TILE)
    state = {"args": args, "saved": [out_depth, T, last], "threads": tiles_x * tiles_y * TILE * TILE}
    if _capture is not None:
        _capture.update(proj=pr.tensors(), counts=order.work[:n] if order.work is not None else
                        torch.empty(0, dtype=torch.int32, device=device), total=order.total, ranges=order.ranges,
                        ids=ids_buf[:order.total], last=state_px[H * W * e:].view(torch.int32).view(H, W),
                        tiles=order.tiles)
    return color, alpha, depth if want_depth else None, weights, state


class ShadeFn(torch.autograd.Function):
    """(means, sh) -> colors [N, 3] = max(SH up to ``degree`` (view direction from the camera center) + 0.5, 0),
    for every Gaussian (a culled one's color is never blended).

    Its own op, before the raster op (gsplat's stage split): autograd runs its backward after the raster op's,
    when the image gradient and the raster state are gone, so the SH coefficients' gradient (48 floats a Gaussian at
    degree 3, the largest buffer of a backward) never coexists with them. Backward by hand: the direction part of
    dL/dmeans and the coefficient gradients (Warp's generated adjoint would add atomically per coefficient read)."""

    @staticmethod
    def forward(ctx, means, sh, cam_arg, degree: int):
        K = kernels_for(means.dtype)
        device, n = means.device, means.shape[0]
        colors = torch.empty(n, 3, dtype=means.dtype, device=device)
        with warp_on(device) as wdev:
            fast_launch(K.sh_color, 3 * n, [input_ct(means, K.vec3), input_ct(sh, None), cam_arg, (degree + 1) ** 2,
                                            ct(colors.view(-1))], wdev)
        ctx.save_for_backward(means, sh)
        ctx.cam_arg, ctx.degree = cam_arg, degree
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
            fast_launch(K.sh_backward, n, [m, input_ct(sh, K.vec3), ctx.cam_arg, ctx.degree,
                                           ct(g_colors.contiguous(), K.vec3), rgb, ct(g_means, K.vec3)], wdev)
            fast_launch(K.sh_coeff_grad, n * n_coeffs, [m, ctx.cam_arg, n_coeffs, rgb, ct(g_sh, K.vec3)], wdev)
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
    def forward(ctx, means, quats, log_scales, opacity_logits, colors, means2d_probe, cam, cam_arg, settings):
        K = kernels_for(means.dtype)
        device, n = means.device, means.shape[0]
        with warp_on(device):
            args = [input_ct(t, ty) for t, ty in zip((means, quats, log_scales, opacity_logits),
                                                      (K.vec3, K.vec4, K.vec3, None))] + [ct(colors, K.vec3)]
            pr = project(K, args, colors, cam_arg, n, means.dtype, device)
            color, alpha, depth, weights, first = blend(
                K, pr, count_intersections(K, pr, cam.width, cam.height, settings["all_tiles"]), cam, settings)
        ctx.state = {"proj": pr, "blend": first, "n": n, "dtype": means.dtype, "device": device, "args": args,
                     "cam": cam, "cam_arg": cam_arg, "settings": settings}
        # the inputs are read by the adjoints: saving them lets autograd refuse a backward after an in-place
        # change (torch's version counter) instead of returning stale gradients
        ctx.save_for_backward(means, quats, log_scales, opacity_logits, colors)
        ctx.mark_non_differentiable(pr.radii, weights)
        # an output without a gradient (the alpha of a colour loss, the radii) reaches the backward as None, which it
        # reads as kept broadcast zeros: autograd would allocate and memset an [H, W] and an [N] zero per backward
        ctx.set_materialize_grads(False)
        return color, alpha, depth, pr.radii, weights if settings["weights"] else None  # depth None if not asked

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, _g_radii, _g_weights):
        state = ctx.state
        args, cam, cam_arg, settings = (state[k] for k in ("args", "cam", "cam_arg", "settings"))
        n, dtype, device = state["n"], state["dtype"], state["device"]
        K = kernels_for(dtype)
        H, W = cam.height, cam.width
        with warp_on(device) as wdev:
            pr, st = state.pop("proj", None), state.pop("blend", None)
            if pr is None:  # a second backward through the same graph: the first freed the projection and binning
                pr = project(K, args, ctx.saved_tensors[4], cam_arg, n, dtype, device)
                st = blend(K, pr, count_intersections(K, pr, W, H, settings["all_tiles"]), cam, settings)[4]
            # gradient buffers exist only from here on (fresh per call, so a second backward through the same
            # graph, e.g. gradcheck or retain_graph, never sees the first call's sums). What outlives this op (the
            # probe's dL/d(screen mean), dL/dcolor for ShadeFn, dL/dmeans until ShadeFn adds its part) shares one
            # buffer; the geometric gradients go with this op, the other inputs' once autograd has accumulated them
            kept_flat = torch.zeros(8 * n, dtype=dtype, device=device)  # [means2d (N, 2) | color (N, 3) | means (N, 3)]
            geo_flat = torch.zeros(5 * n, dtype=dtype, device=device)  # [conic (N, 3) | opacity (N) | depth (N)]
            ups = [g.contiguous() if g is not None else _zero_upstream(shape, dtype, device)
                   for g, shape in ((g_color, (H, W, 3)), (g_alpha, (H, W)), (g_depth, (H, W)))]
            # the blending backward first: the GPU waits on its enqueue, so everything else of the host's part comes
            # after it (the sorted ids, T and last go when this block ends: stream-ordered, safe with it queued)
            fast_launch(K.blend_backward, st["threads"],
                        st["args"] + st["saved"] + [ct(ups[0], K.vec3), ct(ups[1]), ct(ups[2])]
                        + [ct(kept_flat), ct(geo_flat)], wdev, block_dim=TILE * TILE)
            inputs = ctx.saved_tensors  # (raises if an input changed in place since the forward)
            pouts = pr.outs
            del st, ups, pr
            e = kept_flat.element_size()
            g_means2d, g_rgb = kept_flat[:2 * n].view(n, 2), kept_flat[2 * n:5 * n].view(n, 3)
            grads = [kept_flat[5 * n:].view(n, 3)] + packed_zeros([t.shape for t in inputs[1:4]], dtype, device)
            project_adjoint(K, args, pouts, grads, (ct_at(kept_flat, 0, (n,), e, 2), ct_at(geo_flat, 0, (n,), e, 3),
                                                     ct_at(geo_flat, 4 * n * e, (n,), e),
                                                     ct_at(geo_flat, 3 * n * e, (n,), e)), cam_arg, n, device)
        return (*grads, g_rgb, g_means2d, None, None, None)
