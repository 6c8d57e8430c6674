"""What every run folder shares (reconstruct and stylize): device choice, the refusal to overwrite another run,
one run at a time per folder (a lock), no trace of a run that stopped on bad input, and Ctrl-C that finishes the
current iteration before saving a checkpoint."""
from __future__ import annotations

import contextlib
import fcntl
import json
import os
import pickletools
import signal
import threading
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch

from .errors import InputError, WriteError
from .fileio import atomic_path, is_temp

LOCK = ".lock"  # held (flock) by the run writing the folder; the kernel releases it when that process dies


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    d = torch.device(name)
    if d.type == "cuda" and not torch.cuda.is_available():
        raise InputError("device cuda requested but CUDA is not available (use --device cpu)")
    return d


def check_out_dir(out: Path, overwrite: bool, resume: bool, run_files=()) -> None:
    """Refuse an unwritable folder, or one that already holds something, unless overwrite/resume."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    if out.is_dir() and any(p.name != LOCK and not is_temp(p) for p in out.iterdir()) and not (overwrite or resume):
        held = [f for f in run_files if (out / f).exists()]
        what = f"a previous run ({', '.join(held)})" if held else "other files"
        raise InputError(f"output folder already holds {what}; pass --overwrite to replace it or "
                         f"--resume {out} to continue it", out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with atomic_path(out / ".write_test") as tmp:
            tmp.write_bytes(b"")
        (out / ".write_test").unlink()
    except OSError as e:
        raise InputError(f"output folder is not writable ({e.strerror or e})", out) from None


def start_run_dir(out: Path, overwrite: bool, resuming: bool, run_files=(), render_dirs=()) -> None:
    """check_out_dir, then, when a run is replaced (--overwrite, not resuming), delete its files and the PNG
    renders under ``render_dirs`` so nothing stale mixes with the new run's outputs."""
    out = Path(out)
    check_out_dir(out, overwrite, resuming, run_files)
    if overwrite and not resuming:
        for f in run_files:
            with contextlib.suppress(FileNotFoundError):
                (out / f).unlink()
        for sub in render_dirs:
            for f in (out / sub).glob("*.png") if (out / sub).is_dir() else ():
                f.unlink()


@contextlib.contextmanager
def run_folder(out: Path, overwrite: bool, resume: bool, run_files=(), inputs=()):
    """Claim ``out`` for one run of a command: create it, take its lock (a second run on the same folder is refused
    with one line; the lock of a killed run is free again, as flock locks die with their process), delete the
    temporary files a killed run left, refuse a folder holding another run (check_out_dir). If the command then
    stops on bad input (InputError), or on an output it could not write (WriteError) before it had a checkpoint,
    everything it created in ``out`` is removed again (the folder too when it made it), so the corrected command
    can run at once. Files that were there before are left alone."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    check_not_an_input(out, inputs)
    made = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot create the output folder ({e.strerror or e})", out) from None
    fd = _lock(out)
    try:
        for p in sorted(out.rglob(".*"), reverse=True):
            if is_temp(p) and p.is_file():
                p.unlink()
        before = set(out.rglob("*"))
        check_out_dir(out, overwrite, resume, run_files)
        yield out
    except (InputError, WriteError) as e:
        if isinstance(e, WriteError) and (out / "checkpoint.pt").is_file():
            raise  # a full disk after a checkpoint: the run is resumable, keep what it wrote
        for p in sorted(set(out.rglob("*")) - before, key=lambda q: len(q.parts), reverse=True):  # deepest first
            with contextlib.suppress(OSError):
                p.rmdir() if p.is_dir() and not p.is_symlink() else p.unlink()
        raise
    finally:
        _unlock(out, fd, made)


def check_not_an_input(out: Path, inputs) -> None:
    """Refuse an output folder that is an input's own folder (the dataset, the scene's or the painting's folder):
    the run would write its files among its inputs and --overwrite deletes files by name (an INRIA dataset's
    cameras.json is also a run file). A folder inside the dataset is fine: nothing of the dataset is touched."""
    if not out.is_dir():
        return
    for i in inputs:
        if i is None:
            continue
        p = Path(i)
        d = p if p.is_dir() else p.parent
        with contextlib.suppress(OSError):
            if d.is_dir() and os.path.samefile(d, out):
                raise InputError(f"the output folder is the folder of the input {p} (its dataset or file): "
                                 "choose another --out, so the run's files never mix with or replace its inputs",
                                 out)


def _lock(out: Path) -> int:
    path = out / LOCK
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise InputError(f"output folder is not writable ({e.strerror or e})", out) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = os.pread(fd, 32, 0).decode(errors="replace").strip()
            os.close(fd)
            raise InputError(f"another run{f' (pid {pid})' if pid.isdigit() else ''} is writing to this folder; "
                             "wait for it to finish or choose another --out", out) from None
        try:  # the file may have been removed by the run that held it just before: lock the one in the folder
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            with contextlib.suppress(OSError):  # the pid is for the message only (a full disk must not stop a run)
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            return fd
        os.close(fd)


def _unlock(out: Path, fd: int, made: bool) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(out / LOCK)  # while still holding it, so no other run locks the file being removed
    os.close(fd)
    if made:
        with contextlib.suppress(OSError):
            out.rmdir()  # only when empty: a run that stopped before writing anything leaves no folder


class Interrupt:
    """SIGINT sets a flag that the loop checks after each iteration; a second Ctrl-C interrupts at once."""

    def __init__(self):
        self.flag, self.old = False, None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            def handler(signum, frame):
                if self.flag:
                    raise KeyboardInterrupt
                self.flag = True
            self.old = signal.signal(signal.SIGINT, handler)
        return self

    def __exit__(self, *exc):
        if self.old is not None:
            signal.signal(signal.SIGINT, self.old)


# --- checkpoints are data, never code ----------------------------------------------------------------------------
def load_data(path, mmap: bool = False):
    """A torch file (checkpoint.pt, weights) read as data only: tensors, dicts, lists, tuples, str, int, float, bool
    and None (torch's weights-only unpickler, which never imports or calls anything the file names). A file that
    names any other Python object (``os.system``, a class, a numpy array) is refused with one line that says which,
    before anything in it is constructed; any other unreadable file is one line too."""
    p = Path(path)
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols on stderr: the error is one line
            warnings.simplefilter("ignore")
            return torch.load(p, map_location="cpu", weights_only=True, mmap=mmap)
    except Exception as e:  # noqa: BLE001 - whatever the loader raises, the file is bad input
        names = pickle_globals(p)
        if names:
            raise InputError(f"refused: it names the Python object {names[0]}, and a checkpoint may hold only "
                             "tensors and plain data (loading it could run code); nothing in it was loaded",
                             p) from None
        if "Weights only load failed" in str(e):
            raise InputError("refused: not plain data (tensors, dicts, lists, numbers, strings); nothing in it "
                             "was loaded", p) from None
        raise InputError(f"unreadable checkpoint ({type(e).__name__})", p) from None


SAFE_MODULES = ("torch", "collections")  # what torch.save itself names: tensor rebuilders, storages, OrderedDict


def pickle_globals(path) -> list[str]:
    """The Python objects (module.name) a torch file's pickle imports, other than torch's own and OrderedDict,
    read by scanning the opcodes (pickletools: nothing is executed). [] when it names none or is not a pickle."""
    p = Path(path)
    try:
        if zipfile.is_zipfile(p):
            with zipfile.ZipFile(p) as z:
                data = next((z.read(n) for n in z.namelist() if n.endswith("/data.pkl") or n == "data.pkl"), b"")
        else:
            with open(p, "rb") as f:
                data = f.read(64 << 20)
    except (OSError, zipfile.BadZipFile, RuntimeError):
        return []
    out, strings = [], []
    try:
        for op, arg, _ in pickletools.genops(data):
            if op.name == "GLOBAL":
                out.append(str(arg).replace(" ", "."))
            elif op.name == "STACK_GLOBAL" and len(strings) >= 2:
                out.append(f"{strings[-2]}.{strings[-1]}")
            elif isinstance(arg, str):
                strings.append(arg)
            if op.name == "STOP":
                break
    except Exception:  # noqa: BLE001 - a damaged pickle: report what was found before the damage
        pass
    return [n for n in dict.fromkeys(out) if n.split(".")[0] not in SAFE_MODULES]


def plain_data(obj, where: str = "checkpoint"):
    """``obj`` with numpy scalars as Python numbers and numpy arrays as tensors, so that it loads with
    :func:`load_data`; anything else that is not a tensor or plain data is a bug (TypeError naming it)."""
    if obj is None or isinstance(obj, (bool, int, float, str, torch.Tensor, torch.Size)):
        return obj
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(obj))
    if isinstance(obj, dict):
        return {plain_data(k, where): plain_data(v, f"{where}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(plain_data(v, f"{where}[{i}]") for i, v in enumerate(obj))
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{where} is a {type(obj).__module__}.{type(obj).__name__}, which a checkpoint cannot hold")


def read_checkpoint(path, fmt: str, what: str) -> dict:
    """A run's checkpoint.pt (``path`` is the file or its run folder), refused unless its format is ``fmt``."""
    p = Path(path)
    if p.is_dir():
        p = p / "checkpoint.pt"
    if not p.is_file():
        raise InputError("no checkpoint.pt to resume from", p.parent if p.name == "checkpoint.pt" else p)
    ck = load_data(p)
    if not isinstance(ck, dict) or ck.get("format") != fmt:
        raise InputError(f"not a tlvg_warp {what} checkpoint", p)
    return ck


class StageTimer:
    """Per-stage time split of a training loop, sampled every ``every`` iterations: CUDA events on the GPU
    (read once, at the end: no sync in the loop), perf_counter on the CPU. ``mark(stage)`` closes ``stage``;
    stages not run in an iteration count as zero.

    The sampled steps are those with ``step % every == every // 2 + 1``: off the round multiples on which
    periodic work (densify every 100 steps) falls, which sampling on multiples of ``every`` over-counted (every
    fifth sample was a densify step: 20x its share). Rare work is timed whenever it runs instead
    (``timed(stage)`` … ``done(stage, start)``) and enters the split as its total over all steps."""

    def __init__(self, device: torch.device, stages: tuple, every: int = 20):
        self.cuda, self.every, self.samples, self.marks = device.type == "cuda", max(1, every), [], None
        self.stages = tuple(stages)
        self.offset = (self.every // 2 + 1) % self.every
        self.steps, self.rare = 0, {}  # steps begun; stage -> [(start, end)] of rare work

    def _now(self):
        if self.cuda:
            e = torch.cuda.Event(enable_timing=True)
            e.record()
            return e
        return time.perf_counter()

    def _ms(self, a, b) -> float:
        return a.elapsed_time(b) if self.cuda else (b - a) * 1e3

    def begin(self, step):
        self.steps += 1
        self.marks = {"_start": self._now()} if step % self.every == self.offset else None
        self._last = "_start"

    def mark(self, stage):
        if self.marks is not None:
            self.marks[stage] = (self._last, self._now())
            self._last = stage

    def timed(self):
        """The start of rare work (timed whenever it runs); pass the result to ``done``."""
        return self._now()

    def done(self, stage, start) -> None:
        self.rare.setdefault(stage, []).append((start, self._now()))
        if self.marks is not None:  # a sampled step: the next mark starts after the rare work
            self.marks[stage] = (self._last, self.rare[stage][-1][1])
            self._last = stage

    def end(self):
        if self.marks is not None:
            self.samples.append(self.marks)
            self.marks = None

    def summary(self) -> dict:
        if not self.samples and not self.rare:
            return {}
        if self.cuda:
            torch.cuda.synchronize()
        tot = dict.fromkeys(self.stages, 0.0)
        for m in self.samples:
            for s in self.stages:
                if s in m and s not in self.rare:
                    prev, e = m[s]
                    p = m[prev] if prev == "_start" else m[prev][1]
                    tot[s] += self._ms(p, e)
        n = max(1, len(self.samples))
        split = {s: t / n for s, t in tot.items()}
        for s, spans in self.rare.items():  # every occurrence, spread over every step
            split[s] = split.get(s, 0.0) + sum(self._ms(a, b) for a, b in spans) / max(1, self.steps)
        return {"ms_per_iteration": {s: round(t, 4) for s, t in split.items()}, "samples": len(self.samples),
                "rare_events": {s: len(v) for s, v in self.rare.items()}}


SOURCES = "sources.json"  # where a run's inputs came from, written beside its outputs (plain JSON)


def read_sources_json(run) -> dict | None:
    """A run's sources.json ({name: path}), None when it has none; one line when it is not a JSON object."""
    p = Path(run) / SOURCES
    if not p.is_file():
        return None
    try:
        d = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(f"unreadable {SOURCES} ({type(e).__name__})", p) from None
    if not isinstance(d, dict):
        raise InputError("expected a JSON object", p)
    return {str(k): str(v) for k, v in d.items() if isinstance(v, str)}


def run_sources(run) -> dict:
    """Where a run's inputs came from: its sources.json, else (a run written before there was one) checkpoint.pt's
    ``sources``; {} when there is neither."""
    js = read_sources_json(run)
    if js is not None:
        return js
    ck = Path(run) / "checkpoint.pt"
    if not ck.is_file():
        return {}
    d = load_data(ck, mmap=True)
    src = d.get("sources") if isinstance(d, dict) else None
    return {str(k): str(v) for k, v in src.items() if isinstance(v, (str, Path))} if isinstance(src, dict) else {}


def drop_checkpoints(out: Path, *subdirs: str) -> None:
    """A finished run: its outputs are written, so checkpoint.pt (most of the folder's size) goes, also in
    ``subdirs`` (e.g. the reconstruct/ of a scene fitted first)."""
    for d in (Path(out), *(Path(out) / s for s in subdirs)):
        (d / "checkpoint.pt").unlink(missing_ok=True)
