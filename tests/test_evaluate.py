"""`python -m tlvg_warp evaluate RUN [RUN ...]` on hand-made run folders (tests/_eval_helpers.py): one ruler
(a run's values do not depend on the other runs), the report, the view-dependence oracle, bad input."""
import json

import numpy as np
import pytest

from _eval_helpers import make_run
from tlvg_warp.cli import main

EVAL_H = 32  # tiny evaluation size: the VGG passes are the cost here
N_VIEWS = 7


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    a = make_run(tmp_path_factory.mktemp("run_a"), n_views=N_VIEWS)[0]
    b = make_run(tmp_path_factory.mktemp("run_b"), n_views=N_VIEWS, view_dependent=2.0)[0]
    return a, b


def _evaluate(tmp_path, name, *runs, weights="hed", extra=()):
    out = tmp_path / name
    rc = main(["evaluate", *map(str, runs), "--vgg-weights", weights, "--out", str(out), "--device", "cpu",
               "--eval-height", str(EVAL_H), "--cache", str(tmp_path / "cache"), *extra])
    return rc, out


@pytest.fixture(scope="module")
def both(runs, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ev")
    rc1, alone = _evaluate(tmp, "alone", runs[0])
    stamps = {p: p.stat().st_mtime_ns for p in (tmp / "cache").glob("*.npz")}
    rc2, pair = _evaluate(tmp, "pair", runs[1], runs[0])  # A second: order must not matter either
    assert rc1 == 0 and rc2 == 0
    return (json.loads((alone / "evaluation.json").read_text()), json.loads((pair / "evaluation.json").read_text()),
            pair, tmp, stamps)


def test_a_run_scores_the_same_alone_and_beside_another(both):
    alone, pair, _, _, _ = both
    a_alone = alone["runs"][0]
    a_pair = next(r for r in pair["runs"] if r["run"] == a_alone["run"])
    assert a_alone["per_view"] == a_pair["per_view"]
    assert a_alone["summary"] == a_pair["summary"]
    assert alone["references"] == pair["references"]
    assert a_alone["per_view"]["flow_alignment"] is not None  # measured (pretrained HED backbone)


def test_view_dependent_colors_lose_multiview_consistency(both, runs):
    """Oracle: run B is run A's scene plus strong random view-dependent color (degree-1 SH): its reprojected
    colors disagree; everything else about the geometry is equal."""
    _, pair, _, _, _ = both
    by = {r["run"]: r for r in pair["runs"]}
    a, b = by[str(runs[0])], by[str(runs[1])]
    for k in ("consistency_k1", "consistency_k5"):
        assert b["summary"][k]["mean"] > 1.5 * a["summary"][k]["mean"]
        assert pair["winners"][k] == runs[0].name
    assert a["summary"]["holes_1x"]["mean"] == 0.0  # same geometry: nothing uncovered
    assert a["summary"]["wall_time_s"] == pytest.approx(3.5)  # the fixture's phase times


def test_report_reads_as_words_with_units_and_images(both):
    _, _, out, _, _ = both
    html = (out / "evaluation.html").read_text()
    for text in ("Flow alignment with the painting", "lower is better", "higher is better", "RMSE of RGB",
                 "no clear winner", "data:image/png;base64", "width=320"):
        assert text in html, text
    assert "consistency_k1</td>" not in html  # raw keys are not the row labels


def test_reference_cache_is_written_once_and_reused(both):
    alone, _, _, tmp, stamps = both
    cached = list((tmp / "cache").glob("*.npz"))
    assert [p.stem for p in cached] == [alone["references"]]
    # the second evaluation (the pair, same scene and painting) read them instead of writing them again
    assert {p: p.stat().st_mtime_ns for p in cached} == stamps


def test_random_weights_report_not_measured(runs, tmp_path):
    rc, out = _evaluate(tmp_path, "rnd", runs[0], weights="random", extra=("--max-views", "6"))
    res = json.loads((out / "evaluation.json").read_text())
    assert rc == 0 and set(res["not_measured"]) == {"flow_alignment", "flow_energy", "style_gram", "style_gram_inside",
                                                      "style_nnfm", "style_nnfm_inside", "content"}
    s = res["runs"][0]["summary"]
    assert all(s[k] is None for k in res["not_measured"])
    assert np.isfinite(s["consistency_k1"]["mean"])
    assert "not measured" in (out / "evaluation.html").read_text()


def _error_lines(err: str) -> str:
    """stderr without evaluate's progress lines ("[evaluate  1.2s] stage"), which come first."""
    lines = err.strip().splitlines()
    assert all(x.startswith("[evaluate") for x in lines[:-1]) or len(lines) < 2, lines
    return "\n".join(x for x in lines if not x.startswith("[evaluate"))


def test_progress_goes_to_stderr_a_line_per_stage(runs, tmp_path, capsys):
    rc, _ = _evaluate(tmp_path, "p", runs[0], weights="random", extra=("--max-views", "6"))
    cap = capsys.readouterr()
    stages = [x for x in cap.err.splitlines() if x.startswith("[evaluate")]
    assert rc == 0 and "[evaluate" not in cap.out
    assert stages[0].split("]")[1].strip().startswith("loading VGG")
    assert any("scored the anchor 'sticker'" in x for x in stages) and stages[-1].endswith("done")


def test_bad_input_is_one_line_naming_the_file(runs, tmp_path, capsys):
    rc = main(["evaluate", str(tmp_path / "nope"), "--vgg-weights", "random"])
    err = _error_lines(capsys.readouterr().err)
    assert rc == 2 and "nope" in err and "\n" not in err
    other = make_run(tmp_path / "other", n_views=N_VIEWS)[0]
    (other / "style.png").write_bytes((runs[0] / "photos" / "view_000.png").read_bytes()
                                      if (runs[0] / "photos" / "view_000.png").exists()
                                      else next((runs[0] / "photos").iterdir()).read_bytes())
    rc = main(["evaluate", str(runs[0]), str(other), "--vgg-weights", "random", "--out", str(tmp_path / "o")])
    err = _error_lines(capsys.readouterr().err)
    assert rc == 2 and "style.png" in err and "not the same painting" in err


def test_anchors_are_reference_rows_in_json_table_and_report(both, capsys):
    _, pair, out, _, _ = both
    assert [a["name"] for a in pair["anchors"]] == ["no stylization", "sticker"]
    un = pair["anchors"][0]["summary"]
    assert un["holes_1x"]["mean"] == 0.0 and un["consistency_k1"]["n"] == N_VIEWS - 1
    # the sticker is the same image on every view: its multi-view error is the painting against itself moved
    assert pair["anchors"][1]["summary"]["consistency_k1"]["mean"] > un["consistency_k1"]["mean"]
    html = (out / "evaluation.html").read_text()
    for text in ("no stylization", "sticker", "reference", "must beat"):
        assert text in html, text


def _pv(vals):
    return {"style_gram": list(vals)}


def test_a_run_wins_only_where_it_also_beats_its_anchor():
    """Oracle: hand-made per-view values. Run a beats run b on every view; a win also needs beating the anchor
    the metric exists to beat (style: no stylization). An anchor better than every run marks the metric."""
    from tlvg_warp.eval.engine import not_discriminating, winners

    rng = np.random.default_rng(0)
    base = rng.normal(1.0, 0.1, 12)
    a, b = _pv(base), _pv(base + 0.5)  # lower is better: a beats b
    good_anchor = {"no stylization": _pv(base - 0.5), "sticker": _pv(base + 9)}
    weak_anchor = {"no stylization": _pv(base + 0.3), "sticker": _pv(base - 9)}
    assert winners(["a", "b"], [a, b], weak_anchor).get("style_gram") == "a"
    assert winners(["a", "b"], [a, b], good_anchor).get("style_gram") is None
    assert not_discriminating([a, b], good_anchor) == {"style_gram": "no stylization"}
    # the sticker beating every run on style is expected (it is the painting): not a verdict
    assert not_discriminating([a, b], weak_anchor) == {}


def test_demo_runs_are_compared_with_the_scene_they_started_from(tmp_path):
    """A demo run at downscale 2 starts from the demo sampled at spacing 2 (stylize's assemble_inputs): `evaluate` and
    `view` rebuild that scene from the run's config.yaml, not the default density."""
    import yaml

    from _eval_helpers import cameras_json
    from tlvg_warp.eval.engine import demo_original
    from tlvg_warp.commands.view import find_original
    from tlvg_warp.io.datasets import read_inria_cameras
    from tlvg_warp.io.demo import demo_dataset, demo_scene

    started = demo_dataset(n_views=4, width=80, height=60, spacing=2.0).gaussians  # what stylize trained from
    default = demo_scene(n_views=4, width=80, height=60)[0]
    assert started.num < default.num / 3
    (tmp_path / "cameras.json").write_text(json.dumps(cameras_json(demo_scene(n_views=4, width=80, height=60)[1])))
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({"downscale": 2.0}))
    cams = read_inria_cameras(tmp_path / "cameras.json")[1]
    g = demo_original(tmp_path, cams)
    assert g.num == started.num and np.array_equal(g.means.numpy(), started.means.numpy())
    g2, where = find_original(tmp_path, cams)
    assert g2.num == started.num and f"{started.num:,} Gaussians" in where
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({"downscale": 1.0}))
    assert demo_original(tmp_path, cams).num == default.num


def test_docs_table_gives_every_metric_its_direction_and_anchor():
    """docs/evaluation.md's metric table against eval/metrics.py: every metric listed, with its direction and the
    anchor it must beat."""
    import re
    from pathlib import Path

    from tlvg_warp.eval import metrics as M

    text = (Path(__file__).resolve().parents[1] / "docs" / "evaluation.md").read_text()
    table = text.split("## Metrics", 1)[1].split("\n\n")[2]
    seen = {}
    for row in table.splitlines()[2:]:
        cells = [c.strip() for c in row.strip("|").split("|")]
        for key in re.findall(r"`(\w+)`", cells[0]):
            seen[key] = (cells[-2], cells[-1])
    assert set(seen) == set(M.METRICS)
    for k, (better, anchor) in seen.items():
        assert better == ("higher" if M.METRICS[k].higher_better else "lower"), k
        assert anchor == (M.ANCHOR_TO_BEAT.get(k) or "–"), k
