"""What a run folder keeps: a finished stylize run removes checkpoint.pt (kept with --keep-checkpoint) and records
its inputs in sources.json, where evaluate and view find the un-stylized scene; a run that stops early keeps its
checkpoint, and --resume finishes it."""
import json
import sys
from pathlib import Path

import pytest
import torch

from tlvg_warp.cli import main

sys.path.insert(0, str(Path(__file__).parent))
from _eval_helpers import cameras_json  # noqa: E402

TINY = ["--vgg-weights", "random", "--device", "cpu", "--iterations", "6", "--quiet", "--set", "orbit_frames=2",
        "--set", "comparison_views=1", "--set", "web_formats=false", "--set", "style_height=64",
        "--set", "log_every=2", "--set", "checkpoint_seconds=0"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A small saved scene with an INRIA cameras.json (stylize --scene --cameras: no photos needed)."""
    from tlvg_warp import save_ply
    from tlvg_warp.io.demo import demo_dataset

    root = tmp_path_factory.mktemp("scene")
    ds = demo_dataset(n_views=6, width=32, height=24)
    g = ds.gaussians.subset(torch.arange(0, ds.gaussians.num, 20))
    save_ply(g, root / "scene.ply")
    (root / "cameras.json").write_text(json.dumps(cameras_json(list(ds.cameras))))
    return root, g.num


def _stylize(scene_root, out, *extra):
    return main(["stylize", "--scene", str(scene_root / "scene.ply"), "--cameras", str(scene_root / "cameras.json"),
                 "--out", str(out), *TINY, *extra])


def test_finished_run_drops_checkpoint_and_records_sources(scene, tmp_path, capsys):
    from tlvg_warp.commands.view import find_original
    from tlvg_warp.runs import run_sources

    root, n = scene
    out = tmp_path / "run"
    assert _stylize(root, out) == 0
    assert not (out / "checkpoint.pt").exists()
    assert (out / "stylized.ply").is_file() and (out / "metrics.json").is_file()
    src = json.loads((out / "sources.json").read_text())  # plain JSON, the paths given on the command line
    assert src["scene"] == str((root / "scene.ply").resolve())
    assert src["cameras"] == str((root / "cameras.json").resolve())
    assert run_sources(out)["scene"] == src["scene"]  # what evaluate reads
    g, where = find_original(out, [])  # what view shows as the un-stylized scene
    assert where == src["scene"] and g is not None and g.num == n
    capsys.readouterr()
    assert main(["stylize", "--resume", str(out), "--quiet"]) == 2  # nothing to resume: one line saying why
    err = capsys.readouterr().err
    assert "--keep-checkpoint" in err and len(err.strip().splitlines()) == 1


def test_keep_checkpoint_keeps_it(scene, tmp_path):
    from tlvg_warp.stylize import load_checkpoint

    root, _ = scene
    out = tmp_path / "run"
    assert _stylize(root, out, "--keep-checkpoint") == 0
    ck = load_checkpoint(out)
    assert ck["iteration"] == 6 and ck["note"] == "finished"
    assert ck["sources"] == json.loads((out / "sources.json").read_text())


def test_interrupted_run_keeps_checkpoint_and_resumes(scene, tmp_path, monkeypatch, capsys):
    """Ctrl-C after step 3 (the loop's flag, as the SIGINT handler sets it): exit 130, checkpoint.pt at that step,
    no outputs yet; --resume finishes the run, which then removes the checkpoint."""
    from tlvg_warp.stylize import load_checkpoint
    from tlvg_warp.train import loop

    root, _ = scene
    out = tmp_path / "run"
    step = loop._Loop.step

    def step_then_ctrl_c(self, phase, k, i):
        view = step(self, phase, k, i)
        if i == 3:
            self.intr.flag = True
        return view

    monkeypatch.setattr(loop._Loop, "step", step_then_ctrl_c)
    assert _stylize(root, out) == 130
    assert load_checkpoint(out)["iteration"] == 3 and not (out / "metrics.json").exists()
    monkeypatch.setattr(loop._Loop, "step", step)
    assert main(["stylize", "--resume", str(out), "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert (m["iterations"], m["resumed_from"]) == (6, 3)
    assert not (out / "checkpoint.pt").exists() and (out / "sources.json").is_file()


def test_sources_of_an_older_run_come_from_its_checkpoint(tmp_path):
    """A run folder from before sources.json: run_sources falls back to checkpoint.pt's sources."""
    from tlvg_warp.runs import run_sources

    torch.save({"format": "tlvg_warp.stylize.v1", "sources": {"scene": "/data/a.ply"}}, tmp_path / "checkpoint.pt")
    assert run_sources(tmp_path) == {"scene": "/data/a.ply"}
    (tmp_path / "sources.json").write_text(json.dumps({"scene": "/data/b.ply"}))
    assert run_sources(tmp_path) == {"scene": "/data/b.ply"}  # sources.json first
