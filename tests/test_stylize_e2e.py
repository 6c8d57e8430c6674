"""End to end on the demo scene at a tiny size (CPU, random VGG): every output file, finite metrics, a PLY
that loads back at SH degree 0, no NaN in the log, Ctrl-C + resume continuing from the checkpoint's
iteration, and the CLI's one-line errors (exit 2)."""
import json
import math

import numpy as np
import pytest
import torch

from tlvg_warp import load_ply
from tlvg_warp.cli import main
from tlvg_warp.io.demo import builtin_painting, demo_dataset
from tlvg_warp.stylize import StylizeConfig, StylizeInputs, load_checkpoint, run_stylize, write_outputs
from tlvg_warp.stylize.pipeline import LOG_TERMS

ITERS = 30  # 5 pre / 20 stylize / 5 post
W, H, VIEWS = 48, 36, 6  # tiny views
SUBSAMPLE = 4  # every 4th demo Gaussian (~4.7k): renders in a few ms on one CPU core

OUTPUTS = ["stylized.ply", "config.yaml", "log.jsonl", "cameras.json", "style.png", "comparison.png", "orbit.mp4",
           "stroke_field.png", "loss_curves.png", "metrics.json", "checkpoint.pt"]
METRIC_KEYS = ["flow_alignment", "time_per_phase_s", "gaussians_input", "gaussians_final", "bytes_in", "bytes_out",
               "vgg_random", "iterations"]


def _cfg(**kw):
    base = dict(iterations=ITERS, device="cpu", vgg_weights="random", log_every=10, orbit_frames=6,
                densify_interval=5, comparison_views=2)
    base.update(kw)
    return StylizeConfig(**base)


@pytest.fixture(scope="module")
def inputs():
    ds = demo_dataset(n_views=VIEWS, width=W, height=H)
    photos = [ds.image(i) for i in range(VIEWS)]
    g = ds.gaussians.subset(torch.arange(0, ds.gaussians.num, SUBSAMPLE))  # holes do not matter here
    return StylizeInputs(g, list(ds.cameras), list(ds.names), photos, builtin_painting(),
                         tuple(ds.background), {"demo": True})


@pytest.fixture(scope="module")
def run_dir(inputs, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    res = run_stylize(inputs, _cfg(), out, progress=False, quiet=True)
    write_outputs(out, res, input_bytes=None)
    return out, res


def test_every_output_written(run_dir):
    out, _ = run_dir
    for f in OUTPUTS:
        assert (out / f).is_file() and (out / f).stat().st_size > 0, f
    for sub in ("renders", "originals", "photos"):
        assert sorted(p.name for p in (out / sub).glob("*.png")) == [f"view_{i:03d}.png" for i in range(VIEWS)]
    cams = json.loads((out / "cameras.json").read_text())
    assert len(cams) == VIEWS and {"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"} <= set(cams[0])
    assert (cams[0]["width"], cams[0]["height"]) == (W, H)


def test_metrics_present_and_finite(run_dir):
    out, _ = run_dir
    m = json.loads((out / "metrics.json").read_text())
    for k in METRIC_KEYS:
        assert k in m, k
    assert m["vgg_random"] is True and "RANDOM" in m["vgg_note"]
    assert m["iterations"] == ITERS
    assert -1.0 <= m["flow_alignment"] <= 1.0 and len(m["flow_alignment_per_view"]) == VIEWS
    flat = [m["flow_alignment"], m["gaussians_input"], m["gaussians_final"], m["bytes_in"], m["bytes_out"],
            *m["time_per_phase_s"].values(), *m["flow_alignment_per_view"]]
    assert all(isinstance(v, (int, float)) and math.isfinite(v) for v in flat)
    assert m["gaussians_final"] <= m["gaussian_budget"]


def test_ply_is_degree_zero_and_finite(run_dir):
    out, res = run_dir
    g = load_ply(out / "stylized.ply")
    assert g.sh_degree == 0 and g.num == res.gaussians.num
    for f in g.FIELDS:
        assert torch.isfinite(getattr(g, f)).all(), f
    assert torch.allclose(g.means, res.gaussians.means.float().cpu())


def test_log_has_every_term_and_no_nan(run_dir):
    out, _ = run_dir
    rows = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(1, ITERS + 1))
    assert [r["phase"] for r in rows] == ["pre"] * 5 + ["stylize"] * 20 + ["post"] * 5
    for r in rows:
        for t in LOG_TERMS:
            assert math.isfinite(r[t]), (r["step"], t)
    sty = [r for r in rows if r["phase"] == "stylize"]
    assert all(r["style"] > 0 and r["lab"] > 0 and r["align"] > 0 for r in sty)  # the terms are really there
    assert sty[0]["w_lab"] == pytest.approx(0.2) and sty[-1]["w_lab"] == pytest.approx(0.05)
    assert any("flow_score" in r for r in sty)


def test_resume_continues_from_checkpoint(inputs, tmp_path, run_dir):
    out = tmp_path / "r"
    with pytest.raises(KeyboardInterrupt):
        run_stylize(inputs, _cfg(), out, progress=False, interrupt_at=12, quiet=True)
    ck = load_checkpoint(out)
    assert ck["iteration"] == 12 and ck["fields"] is not None  # mid-stylize: the target fields travel along
    res = run_stylize(inputs, _cfg(), out, resume=out, progress=False, quiet=True)
    assert res.metrics["resumed_from"] == 12 and res.metrics["iterations"] == ITERS
    rows = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(1, ITERS + 1))
    # the uninterrupted run and the resumed one agree: same view order and the same steps
    _, ref = run_dir
    assert [r["view"] for r in rows] == [r["view"] for r in ref.log]
    assert res.gaussians.num == ref.gaussians.num
    np.testing.assert_allclose(res.gaussians.means.numpy(), ref.gaussians.means.numpy(), atol=1e-4)


def _cli(args, capsys):
    rc = main(["stylize", *args])
    err = capsys.readouterr().err.strip().splitlines()
    return rc, [e for e in err if e.startswith("error")]


def test_cli_missing_style_is_one_line(tmp_path, capsys):
    rc, err = _cli(["--style", str(tmp_path / "nope.jpg"), "--vgg-weights", "random", "--out", str(tmp_path / "o")],
                   capsys)
    assert rc == 2 and len(err) == 1 and "nope.jpg" in err[0]
    assert not (tmp_path / "o").exists()  # nothing half-written


def test_cli_bad_set_key_is_one_line(tmp_path, capsys):
    rc, err = _cli(["--set", "w_algn=1", "--vgg-weights", "random", "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and len(err) == 1 and "w_algn" in err[0] and "w_align" in err[0]


def test_cli_tiny_style_and_missing_weights(tmp_path, capsys):
    import cv2

    cv2.imwrite(str(tmp_path / "tiny.png"), np.zeros((20, 30, 3), np.uint8))
    rc, err = _cli(["--style", str(tmp_path / "tiny.png"), "--vgg-weights", "random", "--out", str(tmp_path / "o")],
                   capsys)
    assert rc == 2 and len(err) == 1 and "64" in err[0]
    rc, err = _cli(["--vgg-weights", str(tmp_path / "none.pth"), "--out", str(tmp_path / "o2")], capsys)
    assert rc == 2 and len(err) == 1 and "--vgg-weights" in err[0]
