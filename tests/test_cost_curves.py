"""benchmarks/cost_curves.py's CSV across calls: a curve can take more than one call (``--resume``), and a later
call writes a column the earlier rows lack (``start_mib``, what earlier points of a process still hold). Oracle: the
csv module reading the file back, and the closed form of a view's size in megapixels."""
import csv
import math

import cv2
from _bench_helpers import load_benchmark

cost_curves = load_benchmark("cost_curves.py")


class _Args:
    base_gaussians, base_megapixels = 1_000_000, 0.76


def _row(step, n, mp, ms, peak, **extra):
    return {"step": step, "gaussians": n, "width": 100, "height": 75, "megapixels": mp, "rc": 0,
            "ms_per_step": ms, "peak_mib": peak, "megapixels_asked": mp, **extra}


def test_rows_of_an_earlier_call_keep_their_values_beside_a_later_column(tmp_path):
    earlier = [_row("fit", 1_000_000, 0.76, 7.4, 2499.0), _row("raster tlvg_warp", 1_000_000, 0.76, 2.6, 268.0)]
    later = [_row("stylize", 1_000_000, 0.76, 15.4, 3044.8, start_mib=0.0),
             _row("stylize", 1_000_000, 0.1, 6.4, 1156.3, start_mib=160.0)]
    cost_curves.write(earlier + later, tmp_path, _Args)  # a DictWriter on the first row's keys raised here
    with open(tmp_path / "cost_curves.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["step"] for r in rows] == ["fit", "raster tlvg_warp", "stylize", "stylize"]
    assert [r["start_mib"] for r in rows] == ["", "", "0.0", "160.0"]  # blank where a call did not measure it
    back = cost_curves.read(tmp_path / "cost_curves.csv")
    assert [r["ms_per_step"] for r in back] == [7.4, 2.6, 15.4, 6.4]
    assert back[0]["gaussians"] == 1_000_000 and isinstance(back[3]["peak_mib"], float)
    im = cv2.imread(str(tmp_path / "cost_curves.png"))
    assert im is not None and im.shape[0] > 100 and im.shape[1] > 100


def test_view_size_gives_the_asked_megapixels_at_the_orbit_aspect():
    for mp in (0.1, 0.5, 0.76, 2.0, 4.0):
        downscale, w, h = cost_curves.view_size(mp)
        assert abs(w * h / 1e6 - mp) / mp < 0.01
        ow, oh = cost_curves.ORBIT_SIZE
        assert math.isclose(w / h, ow / oh, rel_tol=0.01) and round(ow / downscale) == w


def test_a_points_settings_reach_the_run_and_its_row(tmp_path, monkeypatch):
    """``--set`` goes to every point's stylize command line, pair by pair, and the row names it (an A/B of a setting
    in one CSV must not read as one curve)."""
    seen = []
    monkeypatch.setattr(cost_curves.cli, "main", lambda argv: seen.append(list(argv)) or 0)
    monkeypatch.setattr(cost_curves, "random_scene", lambda *a, **k: None)
    monkeypatch.setattr(cost_curves, "save_ply", lambda g, p: p.write_bytes(b""))

    class Args:
        warm, steps, vgg_weights, device = 1, 2, None, "cpu"
        set = ["style_max_cells=0", "loss.w_style=2"]

    row = cost_curves.point(tmp_path, 1000, 0.1, "stylize", Args)
    argv = seen[0]
    pairs = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
    assert pairs[-2:] == ["style_max_cells=0", "loss.w_style=2"] and "phases=[0,1,0]" in pairs
    assert row["settings"] == "style_max_cells=0 loss.w_style=2" and row["rc"] == 0


def test_the_chart_of_one_curve_alone_and_of_one_setting(tmp_path, monkeypatch):
    """A call that measures points of the pixel curve only leaves the Gaussian curve empty: the chart draws it as an
    empty panel (log axes without data raised, after the CSV was written, and ended the call); rows of another
    setting stay out of the curves."""
    plotted = []
    from matplotlib.axes import Axes
    real_plot = Axes.plot
    monkeypatch.setattr(Axes, "plot", lambda self, x, y, *a, **k: plotted.append((list(x), list(y)))
                        or real_plot(self, x, y, *a, **k))
    rows = [_row("stylize", 1_000_000, 2.0, 31.9, 6885.0, settings=""),
            _row("stylize", 1_000_000, 2.0, 50.5, 7214.0, settings="style_max_cells=0")]
    cost_curves.write(rows, tmp_path, _Args)
    im = cv2.imread(str(tmp_path / "cost_curves.png"))
    assert im is not None and im.shape[1] > 100
    assert ([2.0], [31.9]) in plotted and all(50.5 not in y for _, y in plotted)
