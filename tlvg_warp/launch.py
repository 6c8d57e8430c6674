"""Warp's runtime for the torch side: initialization, the per-dtype kernel sets, devices and streams, array
descriptors of torch tensors, and kernel launches (recorded ``wp.Launch``es refilled per call), the radix sort and
the scan. Every use the raster layer makes of Warp's private API (and torch's) is in this module, listed in
``PRIVATE_API`` and checked by ``private_api_problems`` (tests/test_warp_private_api.py), so a Warp upgrade that
moves or changes one fails there, by name, rather than as a crash in a kernel (distributed.py's check that Warp's
runtime is not up yet included: ``warp_runtime_up``).

Kernels get bare array descriptors of torch tensors (``ct``), launched through recorded ``wp.Launch``es
(``fast_launch``): a render's host time, not its GPU time, bounds small and sparse scenes."""
from __future__ import annotations

import contextlib
import ctypes
import functools
import inspect
import os
import sys
import tempfile
import threading
import weakref

import torch
import warp as wp

from .kernels import raster_kernels
from .kernels.camera import camera_struct
from .kernels.flow import flow_targets_kernel

_initialized = False
_init_lock = threading.Lock()


NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"  # what Warp's C library prints without a GPU driver


def init_warp() -> None:
    """Start Warp's runtime once (quiet unless TLVG_WARP_VERBOSE is set)."""
    global _initialized
    if _initialized:
        return
    with _init_lock:  # two threads' first uses start Warp once
        if _initialized:
            return
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

    Private API (``warp._src.types``; ``warp.types`` before 1.10): tests/test_warp_private_api.py checks that it
    still is the class from_torch returns, with the fields ``ct`` fills."""
    global _ARRAY_T
    if _ARRAY_T is None:
        try:  # at first use, not at the top: a Warp that lacks it fails here with the message below
            from warp._src.types import array_t
        except ImportError:
            try:
                from warp.types import array_t
            except ImportError as e:
                raise ImportError(f"this Warp ({wp.config.version}) has no array_t in warp._src.types or "
                                  f"warp.types: tlvg_warp.launch.warp_array_ctype needs updating") from e
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
_sites: dict = {}  # (kernel, device alias, block_dim, adjoint, instance) -> _Site


def fast_launch(kernel, dim: int, args, device, block_dim: int | None = None, adj_args=None, instance: int = 0) -> None:
    """``wp.launch(kernel, dim, inputs=args, device=device, block_dim=block_dim, record_tape=False)`` for the
    per-render launches, with less host time: the first call per (kernel, device, block_dim, forward/adjoint)
    records a ``wp.Launch``; later calls write its parameter slots directly (array descriptors from ``ct``,
    ``wp.array``s, scalars, vectors) and, on CUDA, enqueue it through Warp's runtime, skipping ``wp.launch``'s
    per-argument checks and packing and ``Launch``'s per-call bookkeeping (a render's host time bounds its
    forward: the GPU waits on the host for most of it). ``adj_args``: launch the kernel's adjoint with these
    adjoint arguments (None for an array: no gradient). The Launch keeps no tensor alive between renders: on CUDA
    its parameter addresses point at the caller's descriptors only until the enqueue has copied them, on the CPU
    it holds bare copies (``_set_args``); the caller's own references cover the enqueue (the allocator is
    stream-ordered). ``instance``: another recorded launch of the same kernel, for calls from two threads at once
    (each thread its own: a recorded launch's slots are written just before its call)."""
    if dim <= 0:
        return
    adjoint = adj_args is not None
    key = (kernel, device.alias, block_dim, adjoint, instance)
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


def warp_runtime_up() -> bool:
    """Whether Warp's runtime is up in this process (wp.init() has run, so Warp may have initialized CUDA); starts
    nothing."""
    return _runtime() is not None


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
        _sort_fns[key] = getattr(_runtime().core, f"wp_radix_sort_pairs_{kind}_{side}", None)
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




# Every use of Warp's (and torch's) private API above, with where it is used. ``private_api_problems`` checks each
# one against the installed versions.
PRIVATE_API = (
    ("warp._src.types.array_t: the array descriptor (fields data, grad, shape, strides, ndim; built as "
     "array_t(data, grad, ndim, shape, strides)), what wp.from_torch(return_ctype=True) returns",
     "warp_array_ctype, ct, ct_at, _null_array, _bare"),
    ("warp._src.context.runtime (set by wp.init): .core, Warp's native library, and .default_device",
     "_runtime, _WarpOn, warp_runtime_up"),
    ("Device.runtime and Device.context (the CUDA context handle)", "_WarpOn"),
    ("runtime.core.wp_cuda_context_get_current() -> void*, wp_cuda_context_push_current(ctx), "
     "wp_cuda_context_pop_current()", "_WarpOn"),
    ("runtime.core.wp_cuda_launch_kernel(context, hook, size, max_blocks, block_dim, grid_stride, cluster_dim, "
     "shared_memory_bytes, params_addr, stream, apic_info) -> nonzero on failure", "_enqueue_of"),
    ("runtime.core.wp_radix_sort_pairs_{float,int}_{host,device}(keys, values, count, begin_bit, end_bit, "
     "key_size)", "_runtime_sort, sort_pairs_at"),
    ("runtime.core.wp_array_scan_int_{host,device}(src, dst, count, value_size, ..., inclusive)",
     "inclusive_scan_at"),
    ("wp.Launch internals: params (the bounds, then one ctypes slot per argument, the adjoint's after), params_addr "
     "(their addresses, a ctypes void* array), hooks.forward / backward / forward_smem_bytes / backward_smem_bytes, "
     "bounds.size, max_blocks, block_dim, grid_stride, cluster_dim, set_dim(dim), launch()",
     "_Site, fast_launch, _enqueue_of, _set_args"),
    ("struct instances: __ctype__() is the instance's own ctypes bytes; type(s)() a zero instance; s.assign(other)",
     "_Site, _set_args, _bare"),
    ("torch._C._cuda_getCurrentRawStream(device index) -> int stream handle (CUDA builds of torch)", "_WarpOn"),
)


def private_api_problems() -> list[str]:
    """What of ``PRIVATE_API`` the installed Warp (and torch) no longer provides in the expected shape: one line
    each, naming the function of this module that uses it; empty when everything is as expected. Initializes Warp
    and launches one small kernel on the CPU (compiled on first use)."""
    problems: list[str] = []

    def check(what: str, used_by: str, test) -> None:
        try:
            ok = test()
            detail = "" if ok is True else f": {ok}" if ok else ""
        except Exception as e:  # noqa: BLE001 - any failure is the finding
            ok, detail = False, f": {type(e).__name__}: {e}"
        if ok is not True:
            problems.append(f"{what} (used by tlvg_warp.launch.{used_by}){detail}")

    init_warp()

    def array_t_fields():
        cls = warp_array_ctype()
        names = {f[0] for f in cls._fields_}
        missing = {"data", "grad", "shape", "strides", "ndim"} - names
        if missing:
            return f"fields {sorted(missing)} missing"
        if type(wp.from_torch(torch.zeros(3), return_ctype=True)) is not cls:
            return "wp.from_torch(return_ctype=True) returns another class"
        a = cls(0, 0, 1, (3,), (4,))
        return True if (a.ndim, a.shape[0], a.strides[0]) == (1, 3, 4) else "constructor argument order changed"

    check("warp._src.types.array_t", "warp_array_ctype", array_t_fields)

    def runtime_attrs():
        rt = _runtime()
        if rt is None or not warp_runtime_up():
            return "None after wp.init()"
        missing = [a for a in ("core", "default_device") if not hasattr(rt, a)]
        return f"attributes {missing} missing" if missing else True

    check("warp._src.context.runtime", "_runtime", runtime_attrs)

    def device_attrs():
        d = wp.get_device("cpu")
        missing = [a for a in ("runtime", "context") if a not in dir(d)]
        if missing:
            return f"attributes {missing} missing"
        return True if d.runtime is _runtime() else "Device.runtime is not warp._src.context.runtime"

    check("wp.Device.runtime / wp.Device.context", "_WarpOn", device_attrs)
    check("wp.Device.set_stream(stream, sync)", "_WarpOn",
          lambda: list(inspect.signature(wp.Device.set_stream).parameters)[1:3] == ["stream", "sync"])
    # the native functions: their argument counts as Warp declares them (ctypes argtypes; None is no argument)
    native = {"wp_cuda_context_get_current": 0, "wp_cuda_context_push_current": 1, "wp_cuda_context_pop_current": 0,
              "wp_cuda_launch_kernel": 11}
    native.update({f"wp_radix_sort_pairs_{k}_{s}": 6 for k in ("float", "int") for s in ("host", "device")})
    native.update({f"wp_array_scan_int_{s}": 7 for s in ("host", "device")})
    users = {"wp_cuda_launch_kernel": "_enqueue_of", "wp_radix_sort_pairs": "sort_pairs_at",
             "wp_array_scan_int": "inclusive_scan_at", "wp_cuda_context": "_WarpOn"}
    for name, n_args in native.items():
        def argcount(name=name, n_args=n_args):
            fn = getattr(_runtime().core, name)
            got = len(fn.argtypes or ())
            return True if got == n_args else f"takes {got} arguments, {n_args} expected"
        check(f"runtime.core.{name}", next(v for k, v in users.items() if name.startswith(k)), argcount)
    check("runtime.core.wp_cuda_context_get_current's return type", "_WarpOn",
          lambda: _runtime().core.wp_cuda_context_get_current.restype is ctypes.c_void_p)

    def recorded_launch():
        kernel, cam = flow_targets_kernel("float32"), camera_struct("float32")()
        if not wp.types.is_struct(cam):
            return "wp.types.is_struct(camera struct instance) is False"
        devices = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
        for device, adjoint in [(d, a) for d in devices for a in (False, True)]:
            dev = wp.get_device(device)
            args = [wp.zeros(1, dtype=wp.vec3, device=dev), wp.zeros(1, dtype=wp.vec3, device=dev),
                    wp.zeros(1, dtype=wp.float32, device=dev), wp.zeros((1, 1, 2), dtype=wp.float32, device=dev), cam,
                    0.5, wp.zeros(1, dtype=wp.vec2, device=dev), wp.zeros(1, dtype=wp.int32, device=dev),
                    wp.zeros(1, dtype=wp.float32, device=dev)]
            adj = [wp.zeros_like(a) if isinstance(a, wp.array) else None for a in args] if adjoint else []
            if adjoint:
                adj[4], adj[5] = camera_struct("float32")(), 0.0
            launch = wp.launch(kernel, dim=1, inputs=args, adj_inputs=adj, adjoint=adjoint, device=dev,
                               record_tape=False, record_cmd=True)
            missing = [a for a in ("params", "params_addr", "hooks", "bounds", "max_blocks", "block_dim",
                                   "grid_stride", "cluster_dim", "set_dim", "launch") if not hasattr(launch, a)]
            missing += [f"hooks.{a}" for a in ("forward", "backward", "forward_smem_bytes", "backward_smem_bytes")
                        if not hasattr(launch.hooks, a)]
            if missing:
                return f"attributes {missing} missing"
            params = launch.params
            if len(params) != 1 + len(args) * (2 if adjoint else 1):
                return f"{len(params)} parameter slots for {len(args)} arguments (adjoint {adjoint})"
            if not hasattr(params[0], "size") or not isinstance(params[5], ctypes.Structure):
                return "slot 0 is not the launch bounds, or a struct argument's slot is not its ctypes bytes"
            if dev.is_cuda and [p for p in launch.params_addr] != [ctypes.addressof(p) for p in params]:
                return "params_addr does not hold the addresses of params"  # (None on the CPU: not used there)
            if list(inspect.signature(launch.set_dim).parameters) != ["dim"]:
                return "Launch.set_dim's parameters changed"
            launch.set_dim(1)
            launch.launch()
        copy = type(cam)()
        copy.assign(cam)
        return True if bytes(copy.__ctype__()) == bytes(cam.__ctype__()) else "assign does not copy the bytes"

    check("wp.Launch internals and struct arguments", "fast_launch", recorded_launch)
    if torch.backends.cuda.is_built():
        check("torch._C._cuda_getCurrentRawStream", "_WarpOn",
              lambda: callable(getattr(torch._C, "_cuda_getCurrentRawStream", None)))
    return problems
