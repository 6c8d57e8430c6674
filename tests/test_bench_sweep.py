"""bench sweep on a tiny demo: every point is timed and scored, the CSV's Pareto flags agree with a
brute-force dominance check, the budget is respected; the raster chart's float32 error is round-off."""
import csv
import types

import numpy as np
import pytest
import torch

from tlvg_warp.eval import bench_sweep as B
from tlvg_warp.eval import stability as S
from tlvg_warp.eval.pareto import write_sweep
from tlvg_warp.losses.vgg import load_vgg

# float32 blending of ~tens of Gaussians per pixel vs float64: relative round-off ~1e-7 per term, colors O(1)
RASTER_F32_TOL = 1e-4


def dominated(t, q, i, higher):
    s = 1 if higher else -1
    return any(t[j] <= t[i] and s * q[j] >= s * q[i] and (t[j] < t[i] or q[j] != q[i]) for j in range(len(t)) if j != i)


def test_sweep_points_scored_and_front_correct(tmp_path):
    base = S.demo_base(True, "cpu", n_views=3, size=(24, 18), stride=16, iterations=3)
    base.overrides["vgg_weights"] = "random"
    vgg = load_vgg("random")
    pts = [{"label": "base"}, {"label": "budget 0.5", "budget": 0.5}, {"label": "res x0.5", "render_scale": 0.5}]
    rows = B.run_sweep(base, pts, vgg, log=None)
    assert [r["label"] for r in rows] == ["base", "budget 0.5", "res x0.5"]
    for r in rows:
        assert r["time_s"] > 0 and r["nan"] == 0, r
        for m in B.QUALITY:
            assert np.isfinite(r[m]), (r["label"], m)
    assert rows[1]["gaussians_in"] == round(base.gaussians.num * 0.5)
    assert rows[1]["gaussians_out"] <= rows[1]["gaussians_in"]
    res = write_sweep(rows, tmp_path, x="time_s", metrics=list(B.QUALITY), higher_is_better=B.HIGHER_IS_BETTER,
                      label="label")
    with open(res["csv"]) as f:
        back = list(csv.DictReader(f))
    t = [float(r["time_s"]) for r in back]
    for m in B.QUALITY:
        q = [float(r[m]) for r in back]
        flags = [r[f"pareto_{m}"] == "True" for r in back]
        assert flags == [not dominated(t, q, i, B.HIGHER_IS_BETTER[m]) for i in range(len(t))], m
    assert res["png"].stat().st_size > 1000


def test_raster_rows_error_is_float32_roundoff():
    rows = B.raster_rows([(300, 32, 24), (800, 48, 32)], torch.device("cpu"), repeats=1, log=None)
    for r in rows:
        assert r["time_s"] > 0
        assert 0 < r["max_abs_err"] < RASTER_F32_TOL and r["mean_abs_err"] <= r["max_abs_err"]


def test_sweep_points_vary_one_setting_each():
    pts = B.sweep_points(True, 6, 1000)
    keys = [set(p) - {"label"} for p in pts]
    assert keys[0] == set() and all(len(k) == 1 for k in keys[1:])
    assert {next(iter(k)) for k in keys[1:]} == {"iterations", "render_scale", "vgg_scale", "budget", "style_loss"}


def test_scene_without_data_is_an_input_error():
    from tlvg_warp.errors import InputError

    args = types.SimpleNamespace(scene="x.ply", data=None, style=None)
    with pytest.raises(InputError, match="--scene needs --data"):
        B.load_scene(args, True, "cpu")
    args = types.SimpleNamespace(scene=None, data="somewhere", style=None)
    with pytest.raises(InputError, match="--data needs --scene"):
        B.load_scene(args, True, "cpu")
