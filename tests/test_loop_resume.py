"""A stylization SIGKILLed mid-phase and resumed equals the uninterrupted run.

The killed run is a child process with a tiny checkpoint interval (``checkpoint_seconds`` 0.2, the default
time-based mechanism) that is killed with SIGKILL (no handler runs) once its checkpoint is past the start of the
Stylize phase (so the phase's targets, anchors and density state must come back from the file). Then
``run_stylize(..., resume=DIR)`` in this process finishes it. Oracles: an uninterrupted run of the same config
in this process — final parameters bit-identical, every log row identical — and the killed run's own
log.jsonl, which must hold every step up to its checkpoint (written at the same point). The FAST match is reused
between a view's steps (``loss.fast_refresh`` 2), so a resume that lost that cache would diverge."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

HERE = Path(__file__).resolve().parent
CFG = {"iterations": 24, "phases": [1, 2, 1], "device": "cpu", "vgg_weights": "random", "style_height": 64,
       "log_every": 2, "checkpoint_seconds": 0.2, "density.interval": 3, "orbit_frames": 0,
       "loss.fast_refresh": 2,  # a view's FAST match reused on its next step: the cache must come back too
       "stroke_jitter": 1.0, "loss.w_orient": 1.0}  # the jitter is drawn once, at the stylize start: not again on resume
STYLIZE_START, STYLIZE_END = 6, 18  # steps of the phases at 24 iterations, [1, 2, 1]
FLUSH_SLEEP_S = 0.3  # the child sleeps at each log flush so that it is surely killed before its end

CHILD = f"""
import sys, time
sys.path.insert(0, {str(HERE)!r})
from test_loop_resume import CFG, inputs
from tlvg_warp.losses import load_vgg
from tlvg_warp.stylize import run_stylize
from tlvg_warp.stylize.config import config_from_dict
run_stylize(inputs(), config_from_dict(CFG), sys.argv[1], progress=False, quiet=True, vgg=load_vgg("random"),
            on_progress=lambda step, g: time.sleep({FLUSH_SLEEP_S}))
"""


def inputs():
    from _demo_helpers import demo_stylize_inputs

    return demo_stylize_inputs(4, 32, 24, 8)[1]


def _rows(out: Path) -> list:
    return [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


def _checkpoint_step(out: Path):
    try:
        return torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)["iteration"]
    except (FileNotFoundError, EOFError, RuntimeError):
        return None


def test_sigkill_mid_phase_then_resume_equals_uninterrupted(tmp_path):
    from tlvg_warp.losses import load_vgg
    from tlvg_warp.stylize import load_checkpoint, run_stylize
    from tlvg_warp.stylize.config import config_from_dict

    killed = tmp_path / "killed"
    env = dict(os.environ, PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(killed)], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while child.poll() is None and time.monotonic() - t0 < 300:
            step = _checkpoint_step(killed)
            if step is not None and STYLIZE_START < step:
                break
            time.sleep(0.02)
        assert child.poll() is None, child.communicate()[1][-3000:]  # still running: killed mid-run
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == -signal.SIGKILL
    ck = load_checkpoint(killed)
    k = ck["iteration"]
    assert ck["note"] == "periodic" and STYLIZE_START < k < CFG["iterations"]
    assert [r["step"] for r in _rows(killed)] == list(range(1, k + 1))  # the log as of the checkpoint
    if k < STYLIZE_END:
        assert ck["phases"]["stylize"]["fields"] is not None and ck["density"]["tracked"]

    vgg = load_vgg("random")
    resumed = run_stylize(inputs(), config_from_dict(CFG), killed, resume=killed, progress=False, quiet=True, vgg=vgg)
    ref = run_stylize(inputs(), config_from_dict(CFG), tmp_path / "straight", progress=False, quiet=True, vgg=vgg)
    assert resumed.metrics["resumed_from"] == k and resumed.metrics["iterations"] == CFG["iterations"]
    for f in ref.gaussians.FIELDS:
        assert torch.equal(getattr(resumed.gaussians, f), getattr(ref.gaussians, f)), f
    assert resumed.metrics["densify_events"] == ref.metrics["densify_events"]
    rows, ref_rows = _rows(killed), _rows(tmp_path / "straight")
    assert [r["step"] for r in rows] == list(range(1, CFG["iterations"] + 1))
    for a, b in zip(rows, ref_rows):  # (flow_score is measured at log flushes, which checkpoints add)
        a.pop("flow_score", None), b.pop("flow_score", None)
        assert a == b, (a, b)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
