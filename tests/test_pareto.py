"""Pareto front against a brute-force dominance check; the sweep CSV and chart round-trip."""
import csv

import cv2
import numpy as np
import pytest

from tlvg_warp.eval.pareto import pareto_front, write_sweep


def brute_front(t, q, higher):
    """O(n^2) definition: i is on the front iff no j is <= in time, >= in quality, and better in one."""
    q = q if higher else -q
    ok = np.isfinite(t) & np.isfinite(q)
    out = []
    for i in range(len(t)):
        dom = any(ok[j] and t[j] <= t[i] and q[j] >= q[i] and (t[j] < t[i] or q[j] > q[i])
                  for j in range(len(t)) if j != i)
        out.append(bool(ok[i]) and not dom)
    return np.array(out)


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("higher", [True, False])
def test_front_matches_brute_force(seed, higher):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    # Small integer grids force equal times, equal qualities and exact duplicates; some seeds add NaNs.
    t = rng.integers(0, 8, n).astype(float) if seed % 2 else rng.random(n)
    q = rng.integers(0, 8, n).astype(float) if seed % 3 else rng.normal(size=n)
    if seed % 4 == 0:
        t[rng.random(n) < 0.1] = np.nan
        q[rng.random(n) < 0.1] = np.nan
    np.testing.assert_array_equal(pareto_front(t, q, higher), brute_front(t, q, higher))


def test_front_known_case():
    # Fast-but-bad, slow-but-good, and one point beaten on both axes by the middle one.
    t, q = [1, 2, 3, 4], [0.1, 0.5, 0.4, 0.9]
    assert pareto_front(t, q).tolist() == [True, True, False, True]
    assert pareto_front(t, q, higher_is_better=False).tolist() == [True, False, False, False]


def test_write_sweep_csv_and_png(tmp_path):
    rng = np.random.default_rng(0)
    rows = [{"label": f"it{i}", "time_s": float(rng.random() * 10), "psnr": float(rng.random() * 30),
             "style_loss": float(rng.random()), "iterations": int(100 * (i + 1))} for i in range(9)]
    metrics, hib = ["psnr", "style_loss"], {"style_loss": False}
    res = write_sweep(rows, tmp_path, metrics=metrics, higher_is_better=hib, dpi=80, panel_in=(4.0, 3.0))
    with open(res["csv"], newline="") as f:
        back = list(csv.DictReader(f))
    assert len(back) == len(rows)
    for r, b in zip(rows, back):
        assert b["label"] == r["label"] and int(b["iterations"]) == r["iterations"]
        assert all(float(b[k]) == r[k] for k in ("time_s", "psnr", "style_loss"))  # exact: repr round-trips
    t = np.array([r["time_s"] for r in rows])
    for m in metrics:
        want = brute_front(t, np.array([r[m] for r in rows]), hib.get(m, True))
        assert [b[f"pareto_{m}"] == "True" for b in back] == want.tolist()
        np.testing.assert_array_equal(res["front"][m], want)
    img = cv2.imread(str(res["png"]))
    assert img is not None and img.shape == (3 * 80, 2 * 4 * 80, 3)  # height, width: 2 panels of 4x3 in
    assert img.std() > 0  # something was drawn


def test_write_sweep_default_metrics_skip_text(tmp_path):
    rows = [{"name": "a", "time_s": 1.0, "q": 2.0, "note": "x"}, {"name": "b", "time_s": 2.0, "q": 1.0}]
    res = write_sweep(rows, tmp_path, name="s")
    assert list(res["front"]) == ["q"] and res["front"]["q"].tolist() == [True, False]
    assert (tmp_path / "s.png").is_file() and (tmp_path / "s.csv").read_text().count("\n") == 3
