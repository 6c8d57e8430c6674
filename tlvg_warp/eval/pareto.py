"""Speed against quality: the Pareto front of a settings sweep, written as a CSV and a PNG chart.

A point is on the front when no other point is at least as fast and at least as good, and strictly better
in one of the two. `python -m tlvg_warp bench` feeds its sweep rows (one dict per setting) to write_sweep.
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from ..fileio import write_bytes, write_text

PANEL_IN = (5.0, 4.0)  # inches per metric subplot (width, height)
DPI = 100


def pareto_front(times, qualities, higher_is_better=True) -> np.ndarray:
    """Boolean mask of the non-dominated points (minimize time; maximize or minimize quality).

    Sort-and-sweep in O(n log n): a point is dominated iff some strictly faster point is at least as good,
    or a point with the same time is strictly better. Points with a NaN/inf coordinate are never on the
    front and dominate nothing. Exact duplicates do not dominate each other, so both stay on the front.
    """
    t = np.asarray(times, dtype=np.float64).ravel()
    q = np.asarray(qualities, dtype=np.float64).ravel()
    if t.shape != q.shape:
        raise ValueError(f"times ({t.size}) and qualities ({q.size}) differ in length")
    ok = np.isfinite(t) & np.isfinite(q)
    if not ok.any():
        return np.zeros(t.size, bool)
    idx = np.flatnonzero(ok)
    tt, qq = t[idx], (q[idx] if higher_is_better else -q[idx])  # from here on, larger quality is better
    order = np.lexsort((-qq, tt))  # by time, then best quality first within a time
    ts, qs = tt[order], qq[order]
    starts = np.flatnonzero(np.r_[True, ts[1:] != ts[:-1]])  # first index of each equal-time group
    group = np.cumsum(np.r_[True, ts[1:] != ts[:-1]]) - 1
    gbest = qs[starts]  # best quality within each time group (sorted best first)
    prev_best = np.r_[-np.inf, np.maximum.accumulate(gbest)[:-1]]  # best among strictly faster groups
    dominated = (prev_best[group] >= qs) | (gbest[group] > qs)
    mask = np.zeros(t.size, bool)
    mask[idx[order]] = ~dominated
    return mask


def _fmt(v):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))  # shortest exact round-trip: float(cell) == v
    return str(v.item() if isinstance(v, np.generic) else v)


def _numeric(rows, key):
    out = []
    for r in rows:
        v = r.get(key)
        try:
            out.append(float(v) if v is not None and not isinstance(v, bool) else math.nan)
        except (TypeError, ValueError):
            out.append(math.nan)
    return np.array(out)


def write_sweep(rows, out_dir, x="time_s", metrics=None, higher_is_better=None, label=None, name="sweep",
                title=None, panel_in=PANEL_IN, dpi=DPI) -> dict:
    """Write `{name}.csv` (every row, plus a `pareto_<metric>` column per metric) and `{name}.png` (x on
    the horizontal axis, one subplot per metric, all points labeled, the front marked and connected).

    metrics: the quality columns (default: every numeric column other than x and the label).
    higher_is_better: {metric: bool}, default True for each. label: column naming each point (default
    "label" or "name" when present, else the row index). Returns {"csv", "png", "front": {metric: mask}}.
    """
    # lazy: matplotlib is heavy and only the figure needs it
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure  # no pyplot: no global state, safe from threads and without a display

    rows = [dict(r) for r in rows]
    if not rows:
        raise ValueError("write_sweep: no rows")
    cols = list(dict.fromkeys(k for r in rows for k in r))  # union of keys, first-seen order
    if x not in cols:
        raise ValueError(f"write_sweep: no {x!r} column")
    if label is None:
        label = next((c for c in ("label", "name") if c in cols), None)
    if metrics is None:
        metrics = [c for c in cols if c not in (x, label) and np.isfinite(_numeric(rows, c)).any()]
    hib = {m: True for m in metrics} | dict(higher_is_better or {})
    xs = _numeric(rows, x)
    front = {m: pareto_front(xs, _numeric(rows, m), hib[m]) for m in metrics}

    out_dir = Path(out_dir)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols + [f"pareto_{m}" for m in metrics])
    for i, r in enumerate(rows):
        w.writerow([_fmt(r.get(c)) for c in cols] + [_fmt(front[m][i]) for m in metrics])
    write_text(out_dir / f"{name}.csv", buf.getvalue())

    n = max(1, len(metrics))
    fig = Figure(figsize=(panel_in[0] * n, panel_in[1]), dpi=dpi)
    FigureCanvasAgg(fig)
    names = [str(r.get(label, i)) if label else str(i) for i, r in enumerate(rows)]
    span = xs[np.isfinite(xs) & (xs > 0)]
    for k, m in enumerate(metrics):
        ax = fig.add_subplot(1, n, k + 1)
        ys, f = _numeric(rows, m), front[m]
        ax.scatter(xs[~f], ys[~f], s=18, c="0.6", label="dominated")
        o = np.argsort(xs[f], kind="stable")
        ax.plot(xs[f][o], ys[f][o], "-o", c="tab:red", ms=5, label="Pareto front")
        for xi, yi, s in zip(xs, ys, names):
            if np.isfinite(xi) and np.isfinite(yi):
                ax.annotate(s, (xi, yi), xytext=(3, 3), textcoords="offset points", fontsize=7)
        if span.size and span.max() / span.min() > 100:  # sweeps over iterations span decades
            ax.set_xscale("log")
        ax.set_xlabel(x)
        ax.set_ylabel(f"{m} ({'higher' if hib[m] else 'lower'} is better)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title)
    fig.tight_layout()  # rearranges inside the canvas; unlike bbox_inches="tight" the pixel size stays fixed
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=dpi)
    write_bytes(out_dir / f"{name}.png", png.getvalue())
    return {"csv": out_dir / f"{name}.csv", "png": out_dir / f"{name}.png", "front": front}
