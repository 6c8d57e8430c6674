"""A full disk at any write is one line on stderr naming the file in its folder, exit 2, no temporary file left,
and the last good checkpoint intact (it still loads and resumes once there is space again).

On a real small filesystem (a tmpfs; needs root to mount, skipped otherwise): the first checkpoint of a fresh run
(nothing of the run is left: it had nothing to resume from), the outputs after the last checkpoint (the disk is
filled just before they are written), the evaluation reference cache. Everywhere: torch.save and the plain writers
against a file whose writes fail with ENOSPC part-way (the behaviour a disk gives, simulated), so the atomic writes
are checked without root too. Oracles: the bytes of the previous file, a directory listing, torch's data-only load."""
from __future__ import annotations

import contextlib
import errno
import os
import shutil
import subprocess

import pytest
import torch

from test_malformed_inputs import S, valid  # noqa: F401 (the fixture of small valid inputs)
from tlvg_warp import fileio
from tlvg_warp.cli import main
from _io_helpers import run_cli
from tlvg_warp.errors import WriteError

ITERS = 4


def _temps(folder):
    return [p for p in folder.rglob(".*") if fileio.TEMP_MARK in p.name]


def _argv(valid, out, *extra):
    return ["stylize", "--scene", str(valid / S), "--data", str(valid / "colmap_bin"), "--out", str(out),
            "--vgg-weights", "random", "--device", "cpu", "--quiet", "--iterations", str(ITERS),
            "--set", "orbit_frames=2", "--set", "comparison_views=1", "--set", "checkpoint_every=2", *extra]


@contextlib.contextmanager
def _tmpfs(path, size: int):
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("needs root to mount a small tmpfs (the simulated ENOSPC tests below still run)")
    path.mkdir(parents=True, exist_ok=True)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                      capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)])


def _fill(disk):
    """Fill the filesystem of ``disk`` to the last byte; returns the filler file (delete it to free the space)."""
    filler = disk / "filler"
    with open(filler, "wb", buffering=0) as f:
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * (1 << 16))
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0")
    return filler


def _one_line(rc, err, folder):
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("[evaluate")]  # evaluate's progress lines
    assert rc == 2, (rc, err)
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert "no space left on device" in lines[0] and str(folder) in lines[0], lines[0]




# --- a real small filesystem ------------------------------------------------------------------------------------
def test_full_disk_at_the_first_checkpoint(valid, tmp_path, capsys):
    """A 2 MB disk holds the config but not the first checkpoint (several MB): one line, exit 2, and nothing of the
    run is left (it had no checkpoint), so the same command runs once there is space."""
    with _tmpfs(tmp_path / "disk", 2 << 20) as disk:
        out = disk / "run"
        # FAST's reused projections (768 x 768 per view) make the first checkpoint several MB
        rc, err = run_cli(_argv(valid, out, "--set", "loss.style_loss=fast"), capsys)
        _one_line(rc, err, out)
        assert "checkpoint.pt" in err
        assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))


def test_full_disk_while_writing_outputs_keeps_the_checkpoint(valid, tmp_path, capsys, monkeypatch):
    """The disk fills after the last checkpoint, as the outputs are written: one line naming the output folder,
    no temporary file, the checkpoint of the last iteration loads; with space again, --resume finishes."""
    import tlvg_warp.stylize.job as outputs  # the job calls write_outputs by the name it imported

    real = outputs.write_outputs
    fillers = []

    def fill_then_write(out, *a, **k):
        fillers.append(_fill(out.parent))
        return real(out, *a, **k)

    monkeypatch.setattr(outputs, "write_outputs", fill_then_write)
    with _tmpfs(tmp_path / "disk", 48 << 20) as disk:
        out = disk / "run"
        rc, err = run_cli(_argv(valid, out), capsys)
        assert fillers, "the disk was never filled"
        _one_line(rc, err, out)
        assert not _temps(out) and not (out / ".lock").exists()
        ck = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=True)
        assert ck["iteration"] == ITERS
        monkeypatch.setattr(outputs, "write_outputs", real)
        fillers[0].unlink()
        rc, err = run_cli(["stylize", "--resume", str(out), "--quiet"], capsys)
        assert rc == 0, err
        assert (out / "stylized.ply").is_file() and not _temps(out)


def test_full_disk_while_writing_the_reference_cache(valid, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(_argv(valid, run, "--iterations", "2")) == 0
    with _tmpfs(tmp_path / "disk", 1 << 20) as disk:
        cache = disk / "cache"
        cache.mkdir()
        _fill(disk)
        rc, err = run_cli(["evaluate", str(run), "--cache", str(cache), "--device", "cpu", "--out",
                        str(tmp_path / "ev")], capsys)
        _one_line(rc, err, cache)
        assert not any(cache.iterdir())  # no partial or temporary cache entry


# --- simulated: writes that fail part-way with ENOSPC -------------------------------------------------------
class _FullFile:
    """A real file that accepts ``room`` bytes, then fails every write with ENOSPC (what a full disk does)."""

    def __init__(self, f, room: int):
        self.f, self.room = f, room

    def write(self, b):
        if len(b) > self.room:
            self.f.write(bytes(b)[: self.room])
            self.room = 0
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(b)
        return self.f.write(b)

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


@pytest.mark.parametrize("room", [0, 100, 5000])
def test_simulated_enospc_in_torch_save_keeps_the_previous_checkpoint(tmp_path, monkeypatch, room):
    ck = tmp_path / "run" / "checkpoint.pt"
    fileio.save_torch(ck, {"iteration": 1, "w": torch.arange(10.0)})
    before = ck.read_bytes()
    real_open = open
    monkeypatch.setattr(fileio, "open", lambda p, mode="r", *a, **k:
                        _FullFile(real_open(p, mode, *a, **k), room) if "w" in mode else real_open(p, mode, *a, **k),
                        raising=False)
    with pytest.raises(WriteError) as e:
        fileio.save_torch(ck, {"iteration": 2, "w": torch.arange(100000.0)})
    msg = str(e.value)
    assert "\n" not in msg and "no space left on device" in msg and str(ck.parent) in msg
    assert ck.read_bytes() == before
    assert sorted(p.name for p in ck.parent.iterdir()) == ["checkpoint.pt"]  # no temporary file
    assert torch.load(ck, map_location="cpu", weights_only=True)["iteration"] == 1


def test_simulated_enospc_in_plain_writes(tmp_path, monkeypatch):
    f = tmp_path / "out" / "metrics.json"
    fileio.write_json(f, {"a": 1})
    before = f.read_bytes()
    real = os.replace

    def full(src, dst):  # the data went to the temporary file; the disk is full when it is renamed into place
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(WriteError) as e:
        fileio.write_json(f, {"a": 2})
    monkeypatch.setattr(os, "replace", real)
    assert "no space left on device" in str(e.value) and str(f) in str(e.value)
    assert f.read_bytes() == before and sorted(p.name for p in f.parent.iterdir()) == ["metrics.json"]
