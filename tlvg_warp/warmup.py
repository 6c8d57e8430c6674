"""CUDA's primary context made in a background thread while Python imports torch and the package; and the
process's end after a GPU command without the interpreter's teardown.

Why: the first CUDA call waits for the context to be made (the driver started, the GPU's memory mapped), and
Python spends over a second importing torch before that call. The driver calls go through ctypes, which releases
the interpreter lock, so the two overlap; torch and Warp both use the device's primary context and find it made.
Only for the commands that run on a GPU, and never when the command line asks for the CPU; without an NVIDIA
driver it does nothing. (LOCAL_RANK is read here by hand: distributed.py, which reads it for the run, imports
torch.)"""
from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import threading
from typing import NoReturn

GPU_COMMANDS = ("stylize", "reconstruct")
_LIBCUDA = "nvcuda.dll" if sys.platform == "win32" else "libcuda.so.1"


def wants_gpu(argv: list[str]) -> bool:
    """Whether the command line ``argv`` (without the program) runs a GPU command that may use CUDA."""
    if not argv or argv[0] not in GPU_COMMANDS or "-h" in argv or "--help" in argv:
        return False
    for i, a in enumerate(argv):
        if a == "--device" and i + 1 < len(argv) and argv[i + 1] == "cpu":
            return False
        if a in ("--device=cpu", "--set=device=cpu") or (a == "--set" and argv[i + 1:i + 2] == ["device=cpu"]):
            return False
    return os.environ.get("CUDA_VISIBLE_DEVICES") != ""  # set and empty: torch sees no GPU


def start_cuda_warmup(argv: list[str]) -> threading.Thread | None:
    """Retain the primary context of this process's GPU (LOCAL_RANK under torchrun, else 0) in a daemon thread
    when ``argv`` asks for a GPU command; returns the thread, or None when nothing was started."""
    if not wants_gpu(argv):
        return None
    try:
        index = int(os.environ.get("LOCAL_RANK", "0"))
    except ValueError:
        index = 0
    t = threading.Thread(target=retain_primary_context, args=(index,), name="cuda-warmup", daemon=True)
    t.start()
    return t


def retain_primary_context(index: int) -> bool:
    """cuInit and cuDevicePrimaryCtxRetain for device ``index``; False where there is no driver or no such device
    (the first CUDA call then reports it as it would have)."""
    try:
        cu = ctypes.CDLL(_LIBCUDA)
    except OSError:
        return False
    dev, ctx = ctypes.c_int(), ctypes.c_void_p()
    return (cu.cuInit(0) == 0 and cu.cuDeviceGet(ctypes.byref(dev), index) == 0
            and cu.cuDevicePrimaryCtxRetain(ctypes.byref(ctx), dev) == 0)


def leave(code, argv: list[str]) -> NoReturn:
    """End the process with ``code`` (what ``main`` returned). After a GPU command (``wants_gpu``) in a single
    process, once Python's streams are flushed, ``os._exit``: the interpreter's teardown (its modules and objects
    freed one at a time, torch's and Warp's GPU memory among them) took 0.7-0.8 s after a 1-iteration stylize on a
    GPU, and the driver frees a process's memory at once when it ends (docs/performance.md, "Stylization"). Nothing
    is lost: every output file is written, closed and renamed before ``main`` returns (the output writers' threads
    are joined), and no exit handler of this package, torch or Warp writes a file. Other commands end normally, and
    so do a rank of a torchrun job (WORLD_SIZE > 1: its process group is left to torch's own teardown) and a
    process that a profiler, tracer or coverage tool watches (it writes its results at the end)."""
    code = 0 if code is None else code if isinstance(code, int) else 1
    if wants_gpu(argv) and os.environ.get("WORLD_SIZE", "1") in ("", "1") and not watched():
        with contextlib.suppress(Exception):
            sys.stdout.flush()
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        os._exit(code)
    raise SystemExit(code)


def watched() -> bool:
    """Whether a tracer, profiler or coverage tool watches this process (sys.settrace / setprofile, or a tool
    registered with sys.monitoring, as Python 3.12's cProfile and coverage are)."""
    if sys.gettrace() is not None or sys.getprofile() is not None:
        return True
    monitoring = getattr(sys, "monitoring", None)
    return monitoring is not None and any(monitoring.get_tool(i) is not None for i in range(6))
