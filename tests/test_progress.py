"""The run's progress: one line with an ETA across the phases; plain periodic lines (no carriage return) when
the output is not a terminal."""
import io
import json
import re
import sys
from pathlib import Path

import torch

from tlvg_warp.progress import Progress, clock_text

sys.path.insert(0, str(Path(__file__).parent))
from _eval_helpers import cameras_json  # noqa: E402


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class Tty(io.StringIO):
    def isatty(self):
        return True


PHASES = [("pre", 10, "Fit"), ("stylize", 10, "Stylize"), ("post", 10, "Fit")]


def _simulate(p, clock, upto, sec=(1.0, 3.0, 1.0)):
    """Steps 1..upto, phase i taking sec[i] seconds a step; a log point every 2 steps and at each phase end."""
    start = 0
    for i, (_, n, _) in enumerate(PHASES):
        if start >= upto:
            break
        p.start_phase(i, 0)
        for k in range(n):
            step = start + k + 1
            if step > upto:
                return
            clock.t += sec[i]
            p.update(step)
            if step % 2 == 0 or k + 1 == n:
                p.postfix({"loss": f"{1 / step:.4f}"})
        p.end_phase()
        start += n


def test_eta_adds_each_remaining_phase_at_its_own_rate():
    """Hand-computed: pre 1 s/step, stylize 3 s/step. After step 15 (5 steps into stylize): 5 stylize steps at 3 s
    and 10 post steps at pre's rate (the same kind of phase), 25 s. During pre, stylize's rate is unknown: the
    estimate (30 - 5 steps at 1 s) is a lower bound."""
    clock = FakeClock()
    p = Progress(PHASES, stream=io.StringIO(), tty=False, clock=clock)
    assert p.eta() == (None, False)
    _simulate(p, clock, 5)
    assert p.eta() == (25.0, False)
    clock2 = FakeClock()
    p2 = Progress(PHASES, stream=io.StringIO(), tty=False, clock=clock2)
    _simulate(p2, clock2, 15)
    p2.cur = 1
    assert p2.eta() == (25.0, True)
    assert "ETA 0:25" in p2.line() and "| stylize 5/10 |" in p2.line()
    assert clock_text(3725) == "1:02:05" and clock_text(65) == "1:05"


def test_plain_lines_off_a_terminal_and_one_rewritten_line_on_one():
    plain, clock = io.StringIO(), FakeClock()
    p = Progress(PHASES, stream=plain, tty=None, clock=clock, every_s=1e9)  # StringIO: not a terminal
    _simulate(p, clock, 30)
    p.close()
    text = plain.getvalue()
    assert "\r" not in text
    steps = [int(m.group(1)) for m in re.finditer(r"^\s*\d+% (\d+)/30 ", text, re.M)]
    assert len(steps) == len(text.splitlines())  # every line is a progress line
    assert {s * 10 // 30 for s in steps} == set(range(1, 11))  # a line at each tenth of the run
    assert {10, 20, 30} <= set(steps) and steps == sorted(steps)  # and at each phase's end
    tty, clock = Tty(), FakeClock()
    p = Progress(PHASES, stream=tty, clock=clock)
    _simulate(p, clock, 30)
    p.close()
    out = tty.getvalue()
    assert out.count("\n") == 1 and out.endswith("\n") and out.count("\r") > 3
    assert "100%" in out.split("\r")[-1] and "ETA 0:00" in out.split("\r")[-1]


def test_stylize_output_to_a_file_has_periodic_lines_with_the_run_eta(tmp_path, capsys):
    """A real run through the CLI, its stderr captured (not a terminal): no carriage return, lines whose step counts
    rise through every tenth of the run, each with the run's ETA, the last at 100% with nothing left."""
    from tlvg_warp import save_ply
    from tlvg_warp.cli import main
    from tlvg_warp.io.demo import demo_dataset

    ds = demo_dataset(n_views=4, width=32, height=24)
    save_ply(ds.gaussians.subset(torch.arange(0, ds.gaussians.num, 20)), tmp_path / "scene.ply")
    (tmp_path / "cameras.json").write_text(json.dumps(cameras_json(list(ds.cameras))))
    rc = main(["stylize", "--scene", str(tmp_path / "scene.ply"), "--cameras", str(tmp_path / "cameras.json"),
               "--out", str(tmp_path / "run"), "--vgg-weights", "random", "--device", "cpu", "--iterations", "20",
               "--set", "orbit_frames=2", "--set", "comparison_views=1", "--set", "web_formats=false",
               "--set", "style_height=64", "--set", "log_every=1"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "\r" not in captured.err and "\r" not in captured.out
    lines = [ln for ln in captured.err.splitlines() if re.match(r"^\s*\d+% \d+/20 \|", ln)]
    steps = [int(re.match(r"^\s*\d+% (\d+)/", ln).group(1)) for ln in lines]
    assert steps == sorted(steps) and {s * 10 // 20 for s in steps} == set(range(1, 11))
    assert all(re.search(r"\| (pre|stylize|post) \d+/\d+ \|.*\| ETA >?\d+:\d\d", ln) for ln in lines), lines
    assert lines[-1].lstrip().startswith("100% 20/20") and "ETA 0:00" in lines[-1]
