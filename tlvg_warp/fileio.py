"""Writes that never leave a half-written file: write to a temporary name beside the target, then rename."""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

from .errors import WriteError


TEMP_MARK = ".tlvg.tmp"  # in every temporary name (``.<stem>.<random>.tlvg.tmp<suffix>``): a run removes leftovers


def is_temp(path) -> bool:
    """A temporary file of :func:`atomic_path` (left behind only when its process was killed)."""
    name = Path(path).name
    return name.startswith(".") and TEMP_MARK in name


def current_umask() -> int:
    """The process umask, read from /proc where possible (os.umask can only read it by setting it)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path in the target's folder; on success rename it over ``path``. On any failure the
    temporary file goes and ``path`` keeps its previous content; an OSError (disk full, read-only folder)
    becomes a one-line WriteError naming ``path``. The temporary name keeps the target's suffix (encoders
    choose their format by it). The file ends with the mode ``open(path, "w")`` gives: 0o666 & ~umask."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f"{TEMP_MARK}{path.suffix}", dir=path.parent)
        os.close(fd)
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp's 0o600 would hide outputs from others; after the
        os.replace(tmp, path)  # writer, as some encoders replace the file rather than reuse it
    except BaseException as e:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        if isinstance(e, OSError):
            raise WriteError(f"could not write: {_reason(e, path)}", path) from None
        raise


def _reason(e: OSError, path: Path) -> str:
    if e.errno == errno.ENOSPC or (e.errno is None and _free_bytes(path.parent) < 1 << 16):
        return "no space left on device (the previous version of the file, if any, is kept)"
    return e.strerror or str(e)


def _free_bytes(folder: Path) -> int:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return 1 << 62


def write_bytes(path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


class _RecordingFile:
    """A file object that remembers the OSError its writes raised: torch's zip writer turns that error into a
    RuntimeError ("unexpected pos") which no longer says the disk was full."""

    def __init__(self, f):
        self.f, self.error = f, None

    def write(self, b):
        try:
            return self.f.write(b)
        except OSError as e:
            self.error = e
            raise

    def flush(self):
        try:
            self.f.flush()
        except OSError as e:
            self.error = e
            raise


def save_torch(path, obj) -> None:
    """torch.save to ``path`` through :func:`atomic_path`: a full disk is a one-line WriteError (whether the OS
    reports it during a write or when the file is closed), the previous file is kept, no temporary file stays."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        rec = _RecordingFile(f)
        try:
            torch.save(obj, rec)
        except RuntimeError:
            if rec.error is not None:
                raise rec.error from None
            raise
        rec.flush()
        os.fsync(f.fileno())


def write_text(path, text: str) -> None:
    write_bytes(path, text.encode())


def write_json(path, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    return str(o)


def write_image(path, rgb) -> None:
    """Save an [H,W,3] float image in [0,1] (numpy or torch), or one already in uint8, as 8-bit PNG/JPEG."""
    import cv2  # lazy: the command line imports this module at startup, and cv2 takes a tenth of a second

    a = rgb.detach().cpu().numpy() if hasattr(rgb, "detach") else np.asarray(rgb)
    if a.dtype != np.uint8:
        a = np.clip(np.nan_to_num(a, nan=0.0) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(Path(path).suffix or ".png", a)
    if not ok:
        raise OSError(f"{path}: could not encode image")
    write_bytes(path, buf.tobytes())
