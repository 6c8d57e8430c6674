"""torch.distributed for tlvg_warp: one small handle, `Dist`, that every command takes.

`Dist.from_env(device)` reads torchrun's environment (WORLD_SIZE, RANK, LOCAL_RANK, MASTER_ADDR/PORT). With
WORLD_SIZE > 1 it joins the process group (NCCL for a CUDA device, gloo for the CPU) and picks
cuda:LOCAL_RANK; otherwise it returns the single-process handle, on which every collective is a no-op, so
the same code runs under `python -m tlvg_warp ...` and `torchrun --nproc-per-node N -m tlvg_warp ...`.

Tensor collectives (`all_reduce_mean_`, `all_reduce_sum_`, `all_reduce_max_`, `broadcast_tensors_`) flatten
their list into one buffer per dtype and issue ONE collective for it (a step's gradients are a handful of
tensors; one call per tensor would pay the latency each time). Object collectives (`broadcast_object`,
`gather_objects`) and `barrier` run on a gloo group (the default group itself on the CPU; a separate gloo
group beside NCCL on GPUs), so they need no CUDA tensors and can wait as long as the slowest rank's work
(a study's fits and stylizations): the process group's timeout is `$TLVG_DIST_TIMEOUT_S` seconds (default
6 hours). torchrun ends every rank when one fails, so a long timeout does not leave orphans waiting.
"""
from __future__ import annotations

import contextlib
import datetime
import os
import sys
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.distributed as tdist

DEFAULT_TIMEOUT_S = 6 * 3600
_LOCAL_ONLY = [0]  # > 0 inside local_only(): from_env returns the single-process handle


@contextlib.contextmanager
def local_only():
    """Inside this block `Dist.from_env` returns the single-process handle even under torchrun.

    The study runs whole stylizations on each rank (one job per rank): the stylize command it calls in-process
    must not take the launch's ranks for data-parallel partners of its own.
    """
    _LOCAL_ONLY[0] += 1
    try:
        yield
    finally:
        _LOCAL_ONLY[0] -= 1


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name)
    if value is None or value == "":
        return default
    try:
        return int(value)
    except ValueError as exc:
        raise ValueError(f"environment variable {name}={value!r} is not an integer") from exc


@dataclass
class Dist:
    """This process's place in a launch: rank of world, and its rank on its own machine (its GPU)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    # added to the brief's API: the device this rank computes on ("cuda:LOCAL_RANK" under torchrun on GPUs)
    device: str = "cpu"
    backend: str | None = None
    _cpu_group: Any = field(default=None, repr=False, compare=False)

    # ------------------------------------------------------------------ set-up
    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    @classmethod
    def from_env(cls, device: str | torch.device | None = None) -> "Dist":
        """The handle for this process. `device`: what the user asked for ("cpu", "cuda", "cuda:1", None).

        Under torchrun (WORLD_SIZE > 1) a CUDA request becomes cuda:LOCAL_RANK (one GPU per rank) and the
        group uses NCCL; a CPU request (or None without CUDA) uses gloo. A process group that the caller
        has already initialised (tests, embedding programs) is adopted as it is.
        """
        requested = "cpu" if device is None else str(device)
        world = _env_int("WORLD_SIZE", 1)
        if tdist.is_available() and tdist.is_initialized():
            world = tdist.get_world_size()
        if world <= 1 or _LOCAL_ONLY[0]:
            return cls(rank=0, world=1, local_rank=0, device=requested, backend=None)

        rank = _env_int("RANK", 0)
        local_rank = _env_int("LOCAL_RANK", rank)
        use_cuda = requested.startswith("cuda")
        if use_cuda:
            if not torch.cuda.is_available():
                raise RuntimeError(f"device {requested!r} asked for, but CUDA is not available on rank {rank}")
            if local_rank >= torch.cuda.device_count():
                raise RuntimeError(
                    f"rank {rank}: LOCAL_RANK {local_rank} but only {torch.cuda.device_count()} CUDA devices "
                    "on this machine (launch at most one process per GPU: --nproc-per-node <= GPUs)")
            dev = f"cuda:{local_rank}"
            torch.cuda.set_device(local_rank)
        else:
            dev = "cpu"
        backend = "nccl" if use_cuda else "gloo"
        if tdist.is_initialized():
            rank = tdist.get_rank()
            backend = tdist.get_backend()
        else:
            timeout = datetime.timedelta(seconds=_env_int("TLVG_DIST_TIMEOUT_S", DEFAULT_TIMEOUT_S))
            tdist.init_process_group(backend=backend, timeout=timeout)
            rank = tdist.get_rank()
        cpu_group = None
        if backend != "gloo":
            # collective call: every rank creates it at the same point (here)
            cpu_group = tdist.new_group(backend="gloo", timeout=datetime.timedelta(
                seconds=_env_int("TLVG_DIST_TIMEOUT_S", DEFAULT_TIMEOUT_S)))
        return cls(rank=rank, world=tdist.get_world_size(), local_rank=local_rank, device=dev,
                   backend=backend, _cpu_group=cpu_group)

    def shutdown(self) -> None:
        """Leave the process group (end of a command). No-op for a single process."""
        if self.world > 1 and tdist.is_initialized():
            tdist.destroy_process_group()

    # ------------------------------------------------------------------ tensors
    def _flat_collective_(self, tensors: list, op) -> None:
        present = [t for t in tensors if t is not None]
        if self.world <= 1 or not present:
            return
        groups: dict[tuple, list[torch.Tensor]] = {}
        for t in present:
            groups.setdefault((t.dtype, t.device), []).append(t)
        for group in groups.values():
            flat = torch.cat([t.detach().reshape(-1) for t in group])
            op(flat)
            offset = 0
            for t in group:
                n = t.numel()
                with torch.no_grad():
                    t.copy_(flat[offset:offset + n].view_as(t))
                offset += n

    def all_reduce_sum_(self, tensors: list) -> None:
        """Sum every tensor over the ranks, in place; None entries are skipped. One collective per dtype.

        Every rank must pass the same list: the same shapes and dtypes, and None at the same places (a
        parameter without a gradient on one rank must be None, or zeros, on all of them)."""
        self._flat_collective_(tensors, lambda flat: tdist.all_reduce(flat, op=tdist.ReduceOp.SUM))

    def all_reduce_mean_(self, tensors: list) -> None:
        """Average every tensor over the ranks, in place (gradients); None entries are skipped."""
        world = self.world

        def op(flat):
            tdist.all_reduce(flat, op=tdist.ReduceOp.SUM)
            flat.div_(world)
        self._flat_collective_(tensors, op)

    def all_reduce_max_(self, tensors: list) -> None:
        """Element-wise maximum over the ranks, in place (e.g. screen radii for density control)."""
        self._flat_collective_(tensors, lambda flat: tdist.all_reduce(flat, op=tdist.ReduceOp.MAX))

    def broadcast_tensors_(self, tensors: list, src: int = 0) -> None:
        """Overwrite every tensor with rank `src`'s values, in place (one collective per dtype)."""
        self._flat_collective_(tensors, lambda flat: tdist.broadcast(flat, src=src))

    # ------------------------------------------------------------------ objects
    def broadcast_object(self, obj: Any, src: int = 0) -> Any:
        """Rank `src`'s `obj` on every rank (picklable objects; returns it, also on `src`)."""
        if self.world <= 1:
            return obj
        box = [obj if self.rank == src else None]
        tdist.broadcast_object_list(box, src=src, group=self._cpu_group)
        return box[0]

    def gather_objects(self, obj: Any) -> list | None:
        """Every rank's `obj`, in rank order, on the main rank; None on the others."""
        if self.world <= 1:
            return [obj]
        out: list | None = [None] * self.world if self.is_main else None
        tdist.gather_object(obj, out, dst=0, group=self._cpu_group)
        return out

    def all_gather_objects(self, obj: Any) -> list:
        """Every rank's `obj`, in rank order, on every rank."""
        if self.world <= 1:
            return [obj]
        out: list = [None] * self.world
        tdist.all_gather_object(out, obj, group=self._cpu_group)
        return out

    def barrier(self) -> None:
        """Wait until every rank arrives here (host side; on the gloo group)."""
        if self.world <= 1:
            return
        tdist.barrier(group=self._cpu_group)

    # ------------------------------------------------------------------ work split
    def rank_slice(self, items: list) -> list:
        """This rank's share of `items`: items[rank::world] (deterministic round-robin)."""
        return list(items)[self.rank::self.world]


def isolate_local_gpu() -> bool:
    """Under torchrun, make this process see only its own GPU: CUDA_VISIBLE_DEVICES becomes the LOCAL_RANK-th
    of the GPUs visible to the launch, so code written for one GPU ("cuda", "cuda:0", Warp's current device)
    runs on it. For launches whose ranks run independent jobs (the study); the data-parallel commands use
    `Dist.from_env`'s cuda:LOCAL_RANK instead. It must run before CUDA is initialised (torch or Warp): then
    it returns True; otherwise (too late, or not under torchrun) it changes nothing and returns False.
    """
    if _env_int("WORLD_SIZE", 1) <= 1 or "LOCAL_RANK" not in os.environ:
        return False

    if torch.cuda.is_initialized():
        return False
    # Warp not loaded: its runtime cannot be up. Loaded: launch reads it (launch owns Warp's private API), imported
    # here and only then, so that importing this module (or a rank that never uses Warp) imports neither Warp nor
    # the kernels
    if "warp" in sys.modules:
        from .launch import warp_runtime_up
        if warp_runtime_up():
            return False
    local_rank = _env_int("LOCAL_RANK", 0)
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    ids = [v.strip() for v in visible.split(",") if v.strip()] if visible else None
    if ids is None:
        os.environ["CUDA_VISIBLE_DEVICES"] = str(local_rank)
    elif local_rank < len(ids):
        os.environ["CUDA_VISIBLE_DEVICES"] = ids[local_rank]
    else:
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # more ranks than GPUs: this one has none (an error if cuda asked)
    return True
