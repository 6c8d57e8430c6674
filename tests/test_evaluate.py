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
    assert rc == 0 and set(res["not_measured"]) == {"flow_alignment", "style_gram", "style_nnfm", "content"}
    s = res["runs"][0]["summary"]
    assert all(s[k] is None for k in res["not_measured"])
    assert np.isfinite(s["consistency_k1"]["mean"])
    assert "not measured" in (out / "evaluation.html").read_text()


def test_bad_input_is_one_line_naming_the_file(runs, tmp_path, capsys):
    rc = main(["evaluate", str(tmp_path / "nope"), "--vgg-weights", "random"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "nope" in err and "\n" not in err
    other = make_run(tmp_path / "other", n_views=N_VIEWS)[0]
    (other / "style.png").write_bytes((runs[0] / "photos" / "view_000.png").read_bytes()
                                      if (runs[0] / "photos" / "view_000.png").exists()
                                      else next((runs[0] / "photos").iterdir()).read_bytes())
    rc = main(["evaluate", str(runs[0]), str(other), "--vgg-weights", "random", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "style.png" in err and "not the same painting" in err
