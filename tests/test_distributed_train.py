"""One scene on two ranks: `torchrun --nproc-per-node 2 -m tlvg_warp stylize|reconstruct` with two
gloo processes on the CPU equals the one-process run with views_per_step=2 (the same views per step), and so do
runs that stop and are resumed:
- a 2-rank reconstruct resumed (in place, to more iterations) by a second 2-rank command;
- a 2-rank stylize killed right after a periodic checkpoint (`checkpoint_every`, mid Stylize phase, density
  statistics half-way to a densify step), resumed to the same iterations by 2 ranks (into another --out) and by
  ONE process with views_per_step=2 (a checkpoint of 2 ranks x 1 view: the same views per step);
- the same checkpoint resumed by one process with views_per_step=1 (1 view per step instead of 2) continues with
  one line on stderr naming the change (the behaviour chosen over refusing: README, "Many GPUs").
(Stylize is not extended with --iterations: its phases split the iterations, so a longer run has other phases.)

Tolerance: 1e-6 absolute on parameters of magnitude <= 10. A 2-rank step does the same float32 arithmetic as
the one-process step on the same two views: each view's backward fills its own gradient, and the mean of two is
a sum and an exact halving either way ((g_a + g_b) / 2 == g_a / 2 + g_b / 2 in IEEE arithmetic), so the runs
are measured bit-identical here; the margin is for a library reduction whose order follows the thread count
(torchrun sets OMP_NUM_THREADS=1). A wrong view split, a missing all-reduce or density statistics that are not
summed over the ranks move parameters by 1e-3 or more within these few steps (and change the clone counts).

Sizes are the smallest that still densify: ~940 Gaussians, 6 views of 32x24, random VGG, 12 iterations."""
from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tlvg_warp.cli import main

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--set", "checkpoint_seconds=0", "--set", "log_every=2"]
# --keep-checkpoint: the finished runs are compared through their checkpoints (and extended with --resume)
STYLIZE = ["--vgg-weights", "random", "--device", "cpu", "--iterations", "12", "--quiet", "--keep-checkpoint",
           "--set", "orbit_frames=0",
           "--set", "comparison_views=1", "--set", "web_formats=false", "--set", "style_height=64",
           "--set", "densify_interval=2", "--set", "densify_grad_threshold=1e-7",
           "--set", "refine_radius=1", *SMALL]  # splats over 2 px are refined first, by rank 0 for every rank
# the means' learning rate decays over a fixed 1000 steps (by default over the run's own iterations, so an
# extended run would follow another schedule than a straight one)
RECON = ["demo", "--downscale", "4", "--device", "cpu", "--quiet", "--keep-checkpoint", "--set", "max_init_points=400",
         "--set", "save_renders=false", "--set", "lr.means_steps=1000", *SMALL]


@contextlib.contextmanager
def one_thread():
    """As torchrun runs each rank (OMP_NUM_THREADS=1); also keeps the shared 2-core CI machine responsive."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


WORKER = """
import json, os, sys
from tlvg_warp.cli import main
from tlvg_warp.train.loop import Run, _Loop


class Killed(BaseException):
    pass


save = Run.save_checkpoint


def save_then_die(run, note=""):  # as a launch killed (SIGKILL, a preempted job) right after a periodic checkpoint
    save(run, note)
    if note == "periodic":
        raise Killed


step = _Loop.step
SIGINT_AT = [None]


def step_then_sigint(loop, phase, k, i):  # as a Ctrl-C that reached rank 1 alone, after step SIGINT_AT
    view = step(loop, phase, k, i)
    if i == SIGINT_AT[0] and os.environ.get("RANK") == "1":
        loop.intr.flag = True
    return view


_Loop.step = step_then_sigint
for argv in json.loads(sys.argv[1]):
    kill = argv[0] == "--killed-after-checkpoint"
    sigint = argv[0] == "--sigint-rank1-after"
    SIGINT_AT[0] = int(argv[1]) if sigint else None
    argv = argv[kill:] if not sigint else argv[2:]
    Run.save_checkpoint = save_then_die if kill else save
    print("== " + argv[0], flush=True)
    try:
        rc = main(argv)
    except Killed:
        continue
    sys.stdout.flush()
    if sigint and rc == 130:  # interrupted, as it should be: the CLI's exit code for Ctrl-C
        print(f"== rank {os.environ.get('RANK')} interrupted", flush=True)
        continue
    if rc or kill or sigint:
        sys.exit(rc or 3)  # 3: a run to be killed wrote no periodic checkpoint, or one to interrupt finished
"""


def torchrun(tmp: Path, *argvs) -> str:
    """One `torchrun --standalone --nproc-per-node 2` launch (two gloo ranks) that runs the given commands in
    turn, as `python -m tlvg_warp ARGV` would: one launch instead of one per command saves the two processes'
    start-up (torch, Warp modules) each time, the larger part of these tests' time. An ARGV that starts with
    --killed-after-checkpoint stops (on both ranks) right after its first periodic checkpoint. Returns stdout
    and stderr."""
    script = tmp / "worker.py"
    script.write_text(WORKER)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                        str(script), json.dumps([list(map(str, a)) for a in argvs])],
                       env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p.stdout + p.stderr


def params(run: Path) -> dict:
    ck = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)
    return {k: v for k, v in ck["params"]["tensors"].items() if v.numel()}


def assert_same_run(a: Path, b: Path):
    pa, pb = params(a), params(b)
    assert set(pa) == set(pb)
    for k in pa:
        assert pa[k].shape == pb[k].shape, k
        torch.testing.assert_close(pb[k], pa[k], rtol=0, atol=1e-6, msg=k)
    la = [json.loads(line) for line in (a / "log.jsonl").read_text().splitlines()]
    lb = [json.loads(line) for line in (b / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in la] == [r["step"] for r in lb]
    for ra, rb in zip(la, lb):
        assert rb["loss"] == pytest.approx(ra["loss"], rel=1e-5), ra["step"]  # the log: mean over all views


def resume_here(*argv) -> tuple[int, str]:
    """A command in this process (one rank): its exit code and stderr."""
    err = io.StringIO()
    with one_thread(), contextlib.redirect_stderr(err):
        rc = main([*map(str, argv)])
    return rc, err.getvalue()


SIGINT_AT = 3  # a Ctrl-C on rank 1 alone after this step; both ranks stop at the next log point, step 4
STOP = 5  # the killed stylization's checkpoint: Stylize phase (steps 3-10 of 12), between its densify steps 4 and 6


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The one-process runs (in this process) and the 2-rank runs (one torchrun launch): stylize; stylize killed
    after its checkpoint at STOP, resumed by 2 ranks into s2r; reconstruct 8 iterations, then --resume to 12 (a
    new run built from checkpoint.pt alone, in the same processes). Then the killed stylization resumed here, by
    one process, with views_per_step 2 (s1r) and 1 (s1m)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from _eval_helpers import cameras_json

    from tlvg_warp import save_ply
    from tlvg_warp.io.demo import demo_dataset

    root = tmp_path_factory.mktemp("dist_train")
    ds = demo_dataset(n_views=6, width=32, height=24)
    save_ply(ds.gaussians.subset(torch.arange(0, ds.gaussians.num, 20)), root / "scene.ply")
    (root / "cameras.json").write_text(json.dumps(cameras_json(list(ds.cameras))))
    sty = ["stylize", "--scene", root / "scene.ply", "--cameras", root / "cameras.json", *STYLIZE]
    with one_thread():
        # FAST reuse off in the reference: the 2-rank runs turn it off themselves (each rank would keep its own
        # cache), which the note in their log says
        assert main([*map(str, sty), "--out", str(root / "s1"), "--set", "views_per_step=2",
                     "--set", "loss.fast_refresh=1"]) == 0
        assert main(["reconstruct", *RECON, "--iterations", "12", "--out", str(root / "r1"),
                     "--set", "views_per_step=2"]) == 0
    log = torchrun(root,
                   [*sty, "--out", root / "s2", "--set", "views_per_step=1"],
                   ["--killed-after-checkpoint", *sty, "--out", root / "s2k", "--set", "views_per_step=1",
                    "--set", f"checkpoint_every={STOP}"],
                   # into another folder: s2k keeps the checkpoint at STOP for the one-process resumes below
                   ["stylize", "--quiet", "--keep-checkpoint", "--resume", root / "s2k", "--out", root / "s2r"],
                   ["reconstruct", *RECON, "--iterations", 8, "--out", root / "r2", "--set", "views_per_step=1"],
                   ["reconstruct", "demo", "--device", "cpu", "--quiet", "--keep-checkpoint", "--resume", root / "r2",
                    "--iterations", 12],
                   # Ctrl-C on rank 1 alone after step 3 (log points are the even steps)
                   ["--sigint-rank1-after", SIGINT_AT, *sty, "--out", root / "s2i", "--set", "views_per_step=1"])
    ck = torch.load(root / "s2k" / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert (ck["iteration"], ck["note"], ck["step_views"]) == (STOP, "periodic", {"ranks": 2, "per_rank": 1})
    resumed = {out: resume_here("stylize", "--quiet", "--keep-checkpoint", "--resume", root / "s2k",
                                    "--out", root / out, *extra)
               for out, extra in (("s1r", ["--set", "views_per_step=2"]), ("s1m", []))}
    return root, log, resumed


def test_stylize_two_ranks_equal_one_rank_with_two_views_per_step(runs):
    root, log, _ = runs
    assert log.count("alignment to its training field") == 2  # s2 and s2r (the killed run: none), by the main rank alone
    assert log.count("note: loss.fast_refresh 4 -> 1 on 2 ranks") == 3  # s2, s2k and s2i (s2r resumes with 1)
    assert_same_run(root / "s1", root / "s2")
    m1, m2 = (json.loads((root / r / "metrics.json").read_text()) for r in ("s1", "s2"))
    assert m2["densify_events"] == m1["densify_events"]
    assert m2["gaussians_final"] == m1["gaussians_final"] > m1["gaussians_input"]  # density control ran, alike
    assert m2["refine"] == m1["refine"] and m1["refine"]["refined"] > 0  # the stroke-size refinement ran, alike
    assert (root / "s2" / "stylized.ply").is_file() and (root / "s2" / "comparison.png").is_file()


def test_reconstruct_two_ranks_resumed_equals_one_rank(runs):
    """Two ranks fit 8 iterations; resumed by two ranks to 12; the one-process run with two views per step does
    12 straight."""
    root, log, _ = runs
    assert log.count("held-out PSNR") == 2  # two reconstructions, each reported by the main rank alone
    m = json.loads((root / "r2" / "metrics.json").read_text())
    assert (m["iterations"], m["resumed_from"]) == (12, 8)
    assert_same_run(root / "r1", root / "r2")


def test_stylize_killed_two_ranks_resumed_by_two_ranks_equals_one_rank(runs):
    """Killed after its checkpoint at STOP (mid Stylize phase), resumed by two ranks into another folder: the
    straight one-process run. Catches a checkpoint that keeps one rank's density statistics instead of their sum
    (or a resume that gives every rank the sum: counted twice), a view order or split RNG not restored, and the
    Stylize phase's targets or anchors not coming back (the densify step at STOP + 1 and the parameters move).
    Checked by breaking DensityControl: a checkpoint with rank 0's statistics only fails this test and the next;
    every rank keeping the checkpoint's sum fails this one."""
    root, log, _ = runs
    m = json.loads((root / "s2r" / "metrics.json").read_text())
    assert (m["iterations"], m["resumed_from"]) == (12, STOP)
    assert_same_run(root / "s1", root / "s2r")
    m1 = json.loads((root / "s1" / "metrics.json").read_text())
    assert m["densify_events"] == m1["densify_events"]
    assert "views per step changed" not in log  # the same two views per step: no note


def test_stylize_two_rank_checkpoint_resumed_by_one_process(runs):
    """The 2-rank (1 view each) checkpoint resumed by ONE process with views_per_step=2: the same two views per
    step, so the straight one-process run, and no note. Catches statistics that a one-process resume would not
    take from the checkpoint (or would take halved), and a note keyed on the number of ranks or on
    views_per_step alone instead of their product."""
    root, _, resumed = runs
    rc, err = resumed["s1r"]
    assert rc == 0, err
    assert "views per step" not in err, err
    m, m1 = (json.loads((root / r / "metrics.json").read_text()) for r in ("s1r", "s1"))
    assert (m["iterations"], m["resumed_from"]) == (12, STOP)
    assert_same_run(root / "s1", root / "s1r")
    assert m["densify_events"] == m1["densify_events"]


def test_resume_with_other_views_per_step_continues_with_a_note(runs):
    """The 2-rank checkpoint (2 views per step) resumed by one process as it is (views_per_step 1): the run goes on
    to its iterations with 1 view per step, after one line on stderr. Fails if such a resume is refused (exit 2),
    or continues silently (no note), or counts iterations in views instead of steps."""
    root, _, resumed = runs
    rc, err = resumed["s1m"]
    assert rc == 0, err
    notes = [line for line in err.splitlines() if "views per step" in line]
    assert notes == ["note: views per step changed from 2 (2 ranks x views_per_step 1, the checkpoint's) to 1 "
                     "(1 rank x views_per_step 1); iterations keep counting steps"], err
    m = json.loads((root / "s1m" / "metrics.json").read_text())
    assert (m["iterations"], m["resumed_from"]) == (12, STOP)
    rows = [json.loads(line) for line in (root / "s1m" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(1, 13))


def test_ctrl_c_on_one_rank_stops_both_at_the_next_log_point(runs):
    """A Ctrl-C that reaches rank 1 alone after step 3 stops both ranks together at step 4, the next log point,
    with one checkpoint of that step and the log up to it; both exit 130. Catches a rank that acts on its own
    flag at once: it flushes alone (a collective the other rank never joins), and the launch fails or hangs."""
    root, log, _ = runs
    assert log.count("== rank 0 interrupted") == 1 and log.count("== rank 1 interrupted") == 1
    ck = torch.load(root / "s2i" / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert (ck["iteration"], ck["note"]) == (SIGINT_AT + 1, "interrupted")
    rows = [json.loads(line) for line in (root / "s2i" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(1, SIGINT_AT + 2))
