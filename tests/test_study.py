"""`python -m tlvg_warp study`: a tiny CPU study (the demo scene, 2 configs, 4 iterations, random VGG so the
style metrics are 'not measured'): tables, CSV, report; a second invocation skips every finished run."""
import csv
import json
from pathlib import Path

import pytest
import torch

from tlvg_warp.cli import main
from tlvg_warp.eval.metrics import interval

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("study")
    y = root / "study.yaml"
    y.write_text(f"""out: out
device: cpu
iterations: 4
vgg_weights: random
eval_height: 32
max_views: 6
set: [orbit_frames=0, comparison_views=1, log_every=2]
configs: {{tlvg: {REPO}/configs/tlvg.yaml, abcgs: {REPO}/configs/abcgs.yaml}}
ours: tlvg
baseline: abcgs
ablations: [abcgs]
scenes: {{demo: {{demo: true, downscale: 4}}}}
paintings: {{starry: builtin}}
""")
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # as each torchrun rank runs (OMP_NUM_THREADS=1); 2 threads crawl on a busy 2-core box
    try:
        assert main(["study", str(y)]) == 0
    finally:
        torch.set_num_threads(n)
    return root / "out", y


def test_study_writes_table_per_scene_ablation_and_report(study):
    out, _ = study
    res = json.loads((out / "study.json").read_text())
    assert set(res["status"].values()) == {"ran"}
    rows = res["tables"]["demo"]["rows"]
    assert [r["config"] for r in rows] == ["tlvg", "abcgs"]
    for r in rows:
        assert r["style_gram"] is None and r["flow_alignment"] is None  # random VGG: not measured
        c = r["consistency_k1"]
        assert c["lo"] <= c["mean"] <= c["hi"] and c["n"] == 5  # 6 views -> 5 pairs
    # the evaluation is the one `evaluate` writes for the same runs (one ruler)
    ev = json.loads((out / "eval" / "demo__starry" / "evaluation.json").read_text())
    by = {r["name"]: r for r in ev["runs"]}
    for r in rows:
        assert interval(by[r["config"]]["per_view"]["consistency_k1"]) == r["consistency_k1"]
    assert [r["config"] for r in res["ablation"]] == ["abcgs"]
    with open(out / "study.csv") as f:
        table = list(csv.DictReader(f))
    assert {r["metric"] for r in table if r["mean"] == "not measured"} == {"flow_alignment", "style_gram",
                                                                             "style_nnfm", "content"}
    html = (out / "study.html").read_text()
    for text in ("Scene demo", "Ablations", "Speed and quality", "Multi-view error", "not measured", "base64"):
        assert text in html, text


def test_study_resume_skips_finished_runs(study, capsys):
    out, y = study
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*/*/stylized.ply")}
    assert len(stamps) == 2
    assert main(["study", str(y)]) == 0
    res = json.loads((out / "study.json").read_text())
    assert set(res["status"].values()) == {"skipped"}
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert capsys.readouterr().out.count("skip demo/starry/") == 2


def _same(a, b, path=""):
    """Equal structure; floats equal to 1e-6 relative. The split study runs the same computation in other
    processes; torchrun sets OMP_NUM_THREADS=1, and a different thread count may only move the last bits of a
    float reduction (measured: bit-identical on 2 cores)."""
    if isinstance(a, dict):
        assert set(a) == set(b), (path, set(a) ^ set(b))
        for k in a:
            if k != "wall_time_s":  # the only field that may differ: time
                _same(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert b == pytest.approx(a, rel=1e-6, abs=1e-9), path
    else:
        assert a == b, path


def test_split_study_over_two_ranks_gives_the_one_process_table(study, tmp_path):
    """`torchrun --nproc-per-node 2 -m tlvg_warp study` (two gloo ranks on the CPU): each rank stylizes one of
    the two runs, the main rank gathers and writes the table, equal to the one-process study's; a later
    one-process launch on the same folder skips both runs and writes the same table again."""
    import os
    import subprocess
    import sys

    out1, y = study
    one = json.loads((out1 / "study.json").read_text())
    out2 = tmp_path / "split"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                        "-m", "tlvg_warp", "study", str(y), "--out", str(out2)],
                       env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert p.stdout.count("wrote ") == 1 and "with 2 ranks" in p.stdout  # the main rank alone reports
    two = json.loads((out2 / "study.json").read_text())
    assert two["status"] == {"demo/starry/tlvg": "ran", "demo/starry/abcgs": "ran"}
    assert two["ranks"]["world"] == 2
    assert sorted(two["ranks"]["stylized_by"].values()) == [0, 1]  # one job per rank, each run once
    for key in ("tables", "ablation", "overall"):
        _same(one[key], two[key], key)
    assert not list((out2 / ".claims").iterdir())  # the launch's claims are removed at the end
    assert main(["study", str(y), "--out", str(out2)]) == 0
    again = json.loads((out2 / "study.json").read_text())
    assert set(again["status"].values()) == {"skipped"}
    _same(one["tables"], again["tables"], "tables")
