"""`python -m tlvg_warp study`: a tiny CPU study (the demo scene, 2 configs x 2 seeds, 4 iterations, random VGG so
the style metrics are 'not measured'): tables with the anchors, CSV, report; a second invocation skips every
finished run; each config keeps its own schedule unless the study forces one; --only-configs."""
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
seeds: 2
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
    assert [r["config"] for r in rows] == ["tlvg", "abcgs", "no stylization", "sticker"]
    assert [bool(r.get("anchor")) for r in rows] == [False, False, True, True]
    for r in rows:
        assert r["style_gram"] is None and r["flow_alignment"] is None  # random VGG: not measured
        c = r["consistency_k1"]
        assert c["lo"] <= c["mean"] <= c["hi"] and c["n"] == 2 * 5  # 2 seeds x (6 views -> 5 pairs)
    # the evaluation is the one `evaluate` writes for the same runs (one ruler), pooled over the seeds in order
    ev = json.loads((out / "eval" / "demo__starry" / "evaluation.json").read_text())
    by = dict(zip(ev["names"], ev["runs"]))
    anchors = {a["name"]: a for a in ev["anchors"]}
    for r in rows:
        if r.get("anchor"):
            pv = anchors[r["config"]]["per_view"]["consistency_k1"] * 2  # paired with each seed's views
        else:
            pv = by[f"{r['config']}/seed_0"]["per_view"]["consistency_k1"] + \
                by[f"{r['config']}/seed_1"]["per_view"]["consistency_k1"]
        # two seeds: the two-stage interval, seeds drawn first (each seed's items labelled with it)
        n0 = len(by["tlvg/seed_0"]["per_view"]["consistency_k1"])
        assert interval(pv, groups=[0] * n0 + [1] * (len(pv) - n0)) == r["consistency_k1"]
        assert interval(pv) != r["consistency_k1"]  # not the one-stage interval over items drawn alike
    import yaml

    seeds = [yaml.safe_load((out / "runs" / "demo" / "starry" / "tlvg" / f"seed_{k}" / "config.yaml").read_text())
             ["seed"] for k in (0, 1)]
    assert seeds == [0, 1]
    assert all(r["wall_time_s"] > 0 for r in rows if not r.get("anchor"))
    assert [r["config"] for r in res["ablation"]] == ["abcgs"]
    with open(out / "study.csv") as f:
        table = list(csv.DictReader(f))
    assert {r["metric"] for r in table if r["mean"] == "not measured"} == {"flow_alignment", "flow_energy",
                                                                             "style_gram", "style_gram_inside",
                                                                             "style_nnfm", "style_nnfm_inside",
                                                                             "content"}
    html = (out / "study.html").read_text()
    for text in ("Scene demo", "Ablations", "Speed and quality", "Multi-view error", "not measured", "base64",
                 "no stylization", "sticker", "(reference)", "2 seed(s)"):
        assert text in html, text


def test_study_resume_skips_finished_runs(study, capsys):
    out, y = study
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*/*/*/stylized.ply")}
    assert len(stamps) == 4
    assert main(["study", str(y)]) == 0
    res = json.loads((out / "study.json").read_text())
    assert set(res["status"].values()) == {"skipped"}
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert capsys.readouterr().out.count("skip demo/starry/") == 4


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
    assert two["status"] == {f"demo/starry/{c}/seed_{k}": "ran" for c in ("tlvg", "abcgs") for k in (0, 1)}
    assert two["ranks"]["world"] == 2
    assert set(two["ranks"]["stylized_by"].values()) == {0, 1}  # both ranks took jobs; each run once
    assert len(two["ranks"]["stylized_by"]) == 4
    for key in ("tables", "ablation", "overall"):
        _same(one[key], two[key], key)
    assert not list((out2 / ".claims").iterdir())  # the launch's claims are removed at the end
    assert main(["study", str(y), "--out", str(out2)]) == 0
    again = json.loads((out2 / "study.json").read_text())
    assert set(again["status"].values()) == {"skipped"}
    _same(one["tables"], again["tables"], "tables")


def _study(tmp_path, body: str):
    from tlvg_warp.eval.study import load_study

    y = tmp_path / "s.yaml"
    y.write_text(f"""out: out
configs: {{tlvg: {REPO}/configs/tlvg.yaml, abcgs: {REPO}/configs/abcgs.yaml}}
ours: tlvg
baseline: abcgs
ablations: [abcgs]
scenes: {{demo: {{demo: true}}}}
paintings: {{starry: builtin}}
{body}""")
    return load_study(y)


def test_each_config_keeps_its_own_schedule_unless_the_study_forces_one(tmp_path):
    """Oracle: the schedule each config file states (read with yaml.safe_load) is what stylize runs when the study
    sets no iterations; a study that sets them passes them to every run."""
    import yaml

    from tlvg_warp.eval.study import stylize_kwargs
    from tlvg_warp.stylize.config import load_config

    st = _study(tmp_path, "")
    assert st.iterations is None and st.seeds == 3
    for c, want in (("abcgs", 1400), ("tlvg", 3000)):
        kw = stylize_kwargs(st, "demo", None, "starry", c, seed=2, device="cpu")
        assert kw["iterations"] is None and kw["overrides"][0] == "seed=2"
        assert yaml.safe_load(Path(kw["config"]).read_text())["iterations"] == want
        assert load_config(kw["config"]).iterations == want
    assert load_config(f"{REPO}/configs/abcgs.yaml").phase_steps() == (400, 600, 400)
    forced = _study(tmp_path, "iterations: 4\nseeds: 1")
    assert stylize_kwargs(forced, "demo", None, "starry", "abcgs", seed=0, device="cpu")["iterations"] == 4


def test_only_configs_keeps_a_subset_and_drops_orphan_roles(tmp_path):
    from tlvg_warp.errors import InputError
    from tlvg_warp.eval.study import only_configs

    st = only_configs(_study(tmp_path, ""), ["tlvg"])
    assert list(st.configs) == ["tlvg"] and st.ours == "tlvg" and st.baseline is None and st.ablations == []
    with pytest.raises(InputError, match="nope"):
        only_configs(_study(tmp_path, ""), ["nope"])


def test_paper_study_and_ablations_are_the_papers(tmp_path):
    """configs/study_paper.yaml: fern, beer, lego x the four paintings, 3 seeds, each config's own schedule; the
    RGB-loss ablation replaces the colour preservation (luminance-only style AND the Lab loss), nothing else."""
    import dataclasses

    import yaml

    from tlvg_warp.eval.study import load_study
    from tlvg_warp.stylize.config import load_config

    data = REPO.parent / "shared" / "data"  # the path configs/study_paper.yaml names, relative to the repository
    if not data.is_dir():
        pytest.skip(f"data absent: {data} (configs/study_paper.yaml names its scenes and paintings there)")
    st = load_study(REPO / "configs" / "study_paper.yaml")
    assert set(st.scenes) == {"fern", "beer", "lego"} and st.seeds == 3 and st.iterations is None
    assert set(st.paintings) == {"starry_night", "shipwreck", "starry_night_over_the_rhone", "monet_san_giorgio"}
    assert set(st.ablations) == {"no_advection", "rgb_loss", "no_density", "canvas_field"}
    ours, rgb = load_config(REPO / "configs" / "tlvg.yaml"), load_config(REPO / "configs" / "ablation_rgb_loss.yaml")
    assert ours.loss.luminance_only and ours.loss.w_lab_start > 0
    assert not rgb.loss.luminance_only and rgb.loss.w_lab_start == 0 and rgb.loss.w_lab_end == 0
    # nothing else differs from ours (ours has no colour style term either: the ablation's style term sees RGB)
    a, b = dataclasses.asdict(ours), dataclasses.asdict(rgb)
    diff = {f"{k}.{j}" for k in a if isinstance(a[k], dict) for j in a[k] if a[k][j] != b[k][j]}
    diff |= {k for k in a if not isinstance(a[k], dict) and a[k] != b[k]}
    assert diff == {"loss.luminance_only", "loss.w_lab_start", "loss.w_lab_end"}, diff
    assert ours.loss.content_on == rgb.loss.content_on == "luminance"  # the content term alike in both
    assert rgb.loss.w_style_color == 0
    assert yaml.safe_load((REPO / "configs" / "ablation_rgb_loss.yaml").read_text())["base"] == "tlvg.yaml"
