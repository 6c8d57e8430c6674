"""Faults around a run folder, with real processes where the fault needs one: SIGINT and SIGKILL at a
random point and then --resume; two runs on one --out (the lock, and a killed run's lock recovered); temporary
files of a killed run removed; a full disk while saving (a small tmpfs, root only).

The runs are the smallest there are: a ~470-Gaussian slice of the demo scene, 4 views of 32x24 written as a COLMAP
dataset, random VGG weights, 24 iterations."""
from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from test_malformed_inputs import S, valid  # noqa: F401 (the fixture of small valid inputs)
from tlvg_warp.cli import main
from tlvg_warp.io import load_ply

ITERS = 160  # a loop of seconds: a signal sent within 1.5 s of its first checkpoint lands inside it
REPO = Path(__file__).resolve().parents[1]


def _argv(valid, out, *extra):
    return ["stylize", "--scene", str(valid / S), "--data", str(valid / "colmap_bin"), "--out", str(out),
            "--vgg-weights", "random", "--device", "cpu", "--quiet", "--iterations", str(ITERS),
            "--set", "orbit_frames=2", "--set", "comparison_views=1", "--set", "checkpoint_every=2", *extra]


def _spawn(args):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-m", "tlvg_warp", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)


def _wait_for(path: Path, proc, timeout=120):
    t0 = time.time()
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.time() - t0 < timeout
        time.sleep(0.05)


def _temps(folder: Path):
    return [p for p in folder.rglob(".*") if ".tlvg.tmp" in p.name]


@pytest.fixture(scope="module")
def reference(valid, tmp_path_factory):
    """The uninterrupted run, in this process (its checkpoint kept: the full-disk test extends it)."""
    out = tmp_path_factory.mktemp("ref") / "run"
    assert main(_argv(valid, out, "--keep-checkpoint")) == 0
    return out


def _interrupted(valid, tmp_path, sig):
    out = tmp_path / "run"
    p = _spawn(_argv(valid, out))
    _wait_for(out / "checkpoint.pt", p)  # the loop is running (a checkpoint every 2 iterations)
    time.sleep(random.Random(sig).uniform(0.0, 1.5))
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    return out, p.returncode, err


def test_sigint_then_resume_matches_uninterrupted(valid, reference, tmp_path):
    out, rc, err = _interrupted(valid, tmp_path, signal.SIGINT)
    if rc == 0:  # the signal came after the last iteration: nothing to resume, but the run must be complete
        pytest.skip("run finished before the signal")
    assert rc == 130, err
    assert not (out / ".lock").exists() and not _temps(out)
    assert main(["stylize", "--resume", str(out), "--quiet"]) == 0
    a, b = load_ply(out / "stylized.ply"), load_ply(reference / "stylized.ply")
    assert a.num == b.num
    np.testing.assert_allclose(a.means.numpy(), b.means.numpy(), atol=1e-4)
    np.testing.assert_allclose(a.sh.numpy(), b.sh.numpy(), atol=1e-3)


def test_sigkill_then_resume_finishes_and_cleans(valid, tmp_path):
    out, rc, _ = _interrupted(valid, tmp_path, signal.SIGKILL)
    assert rc == -signal.SIGKILL
    assert (out / ".lock").exists()  # the killed run's lock stays behind (its flock died with it)
    # a temporary file as a kill during an output write leaves it: full size, recognizable name
    leftover = out / "renders" / ".view_000.k1ll3d00.tlvg.tmp.png"
    leftover.parent.mkdir(exist_ok=True)
    leftover.write_bytes(b"\0" * 4096)
    p = _spawn(["stylize", "--resume", str(out), "--quiet"])
    stdout, err = p.communicate(timeout=300)
    assert p.returncode == 0, err
    assert "comparison.png" in stdout.strip().splitlines()[-1]  # the end says which file to open
    assert not _temps(out) and not (out / ".lock").exists()
    assert load_ply(out / "stylized.ply").num > 0


def test_second_run_on_same_folder_is_refused(valid, tmp_path):
    out = tmp_path / "run"
    # long enough that it still runs when the second process, seconds of imports later, reaches the lock
    first = _spawn(_argv(valid, out, "--iterations", str(2 * ITERS)))
    _wait_for(out / ".lock", first)
    second = _spawn(_argv(valid, out))
    _, err = second.communicate(timeout=120)
    assert second.returncode == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "another run" in lines[0] and str(out) in lines[0] and str(first.pid) in lines[0], err
    _, err1 = first.communicate(timeout=300)
    assert first.returncode == 0, err1  # the first run was not disturbed
    assert (out / "stylized.ply").is_file() and not (out / ".lock").exists()


def test_bad_input_leaves_no_config_behind(valid, tmp_path, capsys):
    out = tmp_path / "run"
    bad = tmp_path / "painting.png"
    bad.write_bytes((valid / "paint" / "painting.png").read_bytes()[:-40])
    assert main(_argv(valid, out, "--style", str(bad))) == 2
    assert not out.exists()  # so the corrected command runs at once
    assert main(_argv(valid, out, "--iterations", "2")) == 0
    assert (out / "config.yaml").is_file()


@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which("mount"), reason="needs root to mount a tmpfs")
def test_full_disk_while_saving_keeps_previous_checkpoint(valid, reference, tmp_path, capsys):
    disk = tmp_path / "disk"
    disk.mkdir()
    size = sum(p.stat().st_size for p in reference.rglob("*") if p.is_file())
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size + (2 << 20)}", "tmpfs", str(disk)]).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        out = disk / "run"
        shutil.copytree(reference, out)
        before = (out / "checkpoint.pt").read_bytes()
        filler = disk / "filler"
        with open(filler, "wb", buffering=0) as f:  # fill the disk; unbuffered, so that closing the file has no
            try:  # partly written block left to flush (it would raise at the close, however the free space falls)
                while True:
                    f.write(b"\0" * (1 << 16))
            except OSError:
                pass
        capsys.readouterr()
        rc = main(["stylize", "--resume", str(out), "--iterations", str(ITERS + 4), "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1, err
        assert "no space left on device" in err[0] and str(out) in err[0] and "Traceback" not in err[0]
        assert (out / "checkpoint.pt").read_bytes() == before  # the previous checkpoint is intact
        assert not _temps(out) and not (out / ".lock").exists()
    finally:
        subprocess.run(["umount", "-l", str(disk)])
