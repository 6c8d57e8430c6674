"""The HTML that people read (evaluate and study): metric names in words with units and directions, intervals,
winners, charts inline (matplotlib PNG, base64), thumbnails 320 px wide, the orbit video embedded."""
from __future__ import annotations

import base64
import html
import io
import math

import cv2
import numpy as np

from . import metrics as M
from .pareto import pareto_front

THUMB_W = 320  # px: strokes stay visible (small renders are enlarged with nearest neighbour)
MAX_VIDEO_BYTES = 40 << 20  # larger orbit videos are linked instead of embedded
CSS = """body{font-family:system-ui,sans-serif;margin:1.5em;max-width:1400px;color:#222}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}.win{background:#d8f5d0;font-weight:bold}
.row{display:flex;gap:8px;flex-wrap:wrap}figure{margin:0}figcaption,.small{font-size:13px;color:#555}
.warn{color:#b00;font-weight:bold}.nm{color:#999;font-style:italic}td.ref,th.ref{background:#f6f6fa;color:#555}
.nd{color:#b60}"""


def esc(x) -> str:
    return html.escape(str(x))


def png_uri(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def image_uri(img, width: int = THUMB_W) -> str:
    a = np.clip(np.nan_to_num(np.asarray(img, np.float32)), 0, 1)
    h, w = a.shape[:2]
    interp = cv2.INTER_NEAREST if w < width else cv2.INTER_AREA
    a = cv2.resize(a, (width, max(1, round(h * width / w))), interpolation=interp)
    ok, buf = cv2.imencode(".png", cv2.cvtColor((a * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


def figure(img, caption: str) -> str:
    return f"<figure><img src='{image_uri(img)}' width={THUMB_W}><figcaption>{esc(caption)}</figcaption></figure>"


def video(path) -> str:
    if path is None or not path.is_file():
        return ""
    if path.stat().st_size > MAX_VIDEO_BYTES:
        return f"<p><a href='{esc(path.resolve().as_uri())}'>orbit video ({esc(path.name)})</a></p>"
    uri = "data:video/mp4;base64," + base64.b64encode(path.read_bytes()).decode()
    return f"<video controls loop muted width={2 * THUMB_W} src='{uri}'></video>"


def fmt(v, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return f"{v:,}" if isinstance(v, int) else esc(v)


def cell(s) -> str:
    """'mean [lo, hi]' of an interval dict, a plain number, or 'not measured'."""
    if s is None:
        return "<span class=nm>not measured</span>"
    if isinstance(s, dict):
        if s.get("mean") is None:
            return "–"
        return f"{fmt(s['mean'])} <span class=small>[{fmt(s['lo'], 3)}, {fmt(s['hi'], 3)}]</span>"
    return fmt(s)


def metric_head(k: str) -> str:
    m = M.METRICS[k]
    return f"<td class=l><b>{esc(m.words)}</b><br><span class=small>{esc(m.unit)}; {m.direction}</span></td>"


def results_table(names, summaries, winners, keys=None, anchors=None, not_discriminating=None) -> str:
    """One row per metric, one column per run, then one grey reference column per anchor ({"name", "summary"});
    the winner's cell green (a win needs every paired interval against the others, and against the anchor the
    metric exists to beat, to exclude 0; otherwise 'no clear winner'); a metric that an anchor wins against
    every run says 'not discriminating'."""
    anchors = anchors or []
    nd = not_discriminating or {}
    sums = list(summaries) + [a["summary"] for a in anchors]
    keys = keys or [k for k in M.METRICS if any(k in s for s in sums)]
    head = ("<tr><th class=l>metric</th>" + "".join(f"<th>{esc(n)}</th>" for n in names)
            + "".join(f"<th class=ref>{esc(a['name'])}<br><span class=small>reference</span></th>" for a in anchors)
            + "<th>must beat</th><th>verdict</th></tr>")
    rows = []
    for k in keys:
        w = winners.get(k)
        cells = "".join(f"<td{' class=win' if w == n else ''}>{cell(s.get(k))}</td>" for n, s in zip(names, summaries))
        cells += "".join(f"<td class=ref>{cell(a['summary'].get(k)) if k in a['summary'] else ''}</td>"
                         for a in anchors)
        verdict = f"{esc(w)} wins" if w else ("no clear winner" if M.METRICS[k].per_view and (
            len(names) > 1 or anchors) else "")
        if nd.get(k):
            verdict += f"<br><span class=nd>not discriminating: {esc(nd[k])} beats every run</span>"
        target = M.ANCHOR_TO_BEAT.get(k) if anchors else None
        rows.append(f"<tr>{metric_head(k)}{cells}<td class=small>{esc(target or '')}</td><td>{verdict}</td></tr>")
    return f"<table>{head}{''.join(rows)}</table>"


def _measured(summaries):
    return [k for k, m in M.METRICS.items() if m.per_view and any(isinstance(s.get(k), dict)
                                                                    and s[k].get("mean") is not None for s in summaries)]


PANEL_COLS = 4


def _margins(fig) -> None:
    """Fixed margins for a grid of panels (tight_layout measures every label: seconds per chart on a CPU)."""
    fig.subplots_adjust(left=0.05, right=0.98, bottom=0.12, top=0.88, wspace=0.3, hspace=0.75)


def _panels(keys, panel_height: float):
    """A figure with one panel per metric key, PANEL_COLS to a row: (fig, [(i, key, axes)])."""
    # lazy: matplotlib is heavy and only the figure needs it
    from matplotlib.figure import Figure

    rows = math.ceil(len(keys) / PANEL_COLS)
    fig = Figure(figsize=(4 * PANEL_COLS, panel_height * rows))
    return fig, [(i, k, fig.add_subplot(rows, PANEL_COLS, i + 1)) for i, k in enumerate(keys)]


def bars_chart(names, summaries) -> str:
    """Bars with 95% intervals, one panel per measured per-view metric."""
    keys = _measured(summaries)
    if not keys:
        return ""
    fig, panels = _panels(keys, 3.0)
    for _, k, ax in panels:
        s = [x.get(k) or {} for x in summaries]
        mean = np.array([np.nan if v.get("mean") is None else v["mean"] for v in s])
        err = np.array([[m - (v.get("lo") if v.get("lo") is not None else m) for m, v in zip(mean, s)],
                        [(v.get("hi") if v.get("hi") is not None else m) - m for m, v in zip(mean, s)]])
        err = np.clip(err, 0.0, None)  # a two-stage interval of a constant metric may miss its mean by rounding
        ax.bar(range(len(names)), mean, yerr=err, capsize=4, color=[f"C{j}" for j in range(len(names))])
        ax.set_xticks(range(len(names)), names, rotation=20, fontsize=8)
        m = M.METRICS[k]
        ax.set_title(f"{m.words}\n({'↑' if m.higher_better else '↓'} {m.direction})", fontsize=8)
        ax.tick_params(labelsize=7)
    _margins(fig)
    return f"<img src='{png_uri(fig)}' style='max-width:100%'>"


def per_view_chart(names, per_views) -> str:
    """Per-view values (x: view index) of every measured metric, one series per run."""
    keys = [k for k in _measured([{k: {"mean": 1} for k, v in p.items() if v} for p in per_views])]
    if not keys:
        return ""
    fig, panels = _panels(keys, 2.8)
    for i, k, ax in panels:
        for j, (n, p) in enumerate(zip(names, per_views)):
            if p.get(k):
                ax.scatter(range(len(p[k])), p[k], s=12, color=f"C{j}", label=n)
        ax.set_title(M.METRICS[k].words, fontsize=8)
        ax.set_xlabel("view", fontsize=7)
        ax.tick_params(labelsize=7)
        if i == 0:
            ax.legend(fontsize=7)
    _margins(fig)
    return f"<img src='{png_uri(fig)}' style='max-width:100%'>"


def speed_chart(names, times, summaries) -> str:
    """Time on x, each measured metric on y (its interval as error bar), the Pareto front in red."""
    t = np.array([np.nan if x is None else x for x in times], np.float64)
    keys = _measured(summaries)
    if not keys or not np.isfinite(t).any():
        return "<p class=small>speed-quality chart: no run recorded its wall time</p>"
    fig, panels = _panels(keys, 3.0)
    for i, k, ax in panels:
        m = M.METRICS[k]
        y = np.array([np.nan if not s.get(k) or s[k].get("mean") is None else s[k]["mean"] for s in summaries])
        lo = np.array([np.nan if not s.get(k) or s[k].get("lo") is None else s[k]["lo"] for s in summaries])
        hi = np.array([np.nan if not s.get(k) or s[k].get("hi") is None else s[k]["hi"] for s in summaries])
        front = pareto_front(t, y, m.higher_better)
        ax.errorbar(t, y, yerr=[y - lo, hi - y], fmt="o", color="0.5", ms=4, capsize=3)
        o = np.argsort(t[front])
        ax.plot(t[front][o], y[front][o], "-o", color="tab:red", ms=5, label="Pareto front")
        for xi, yi, n in zip(t, y, names):
            if np.isfinite(xi) and np.isfinite(yi):
                ax.annotate(n, (xi, yi), xytext=(3, 3), textcoords="offset points", fontsize=7)
        ax.set_xlabel("wall time (s)", fontsize=7)
        ax.set_title(f"{m.words}\n({m.direction})", fontsize=8)
        ax.tick_params(labelsize=7)
    _margins(fig)
    return f"<img src='{png_uri(fig)}' style='max-width:100%'>"


def page(title: str, body: str) -> str:
    return (f"<!doctype html><html><head><meta charset=utf-8><title>{esc(title)}</title><style>{CSS}</style>"
            f"</head><body><h1>{esc(title)}</h1>{body}</body></html>\n")


ANCHOR_NOTE = ("<p class=small>Grey columns are anchors, scored with the same ruler and built by the evaluation "
               "itself: <b>no stylization</b> (the un-stylized scene's renders) and <b>sticker</b> (the painting "
               "center-cropped and resized over every view). A run wins a metric only where it also beats the "
               "anchor in the 'must beat' column: doing nothing must lose on flow, style, strokes and detail; the "
               "pasted painting must lose on content, multi-view consistency and chroma noise. A metric whose "
               "'must beat' anchor wins against every run is marked 'not discriminating' for this scene.</p>")

METHOD_NOTE = ("<p class=small>Every run is measured with the same ruler: references (the un-stylized scene's "
               "renders, depth and coverage; a common stroke field per view from a nearest-neighbour match of "
               "pretrained VGG features of the un-stylized render to the painting; the photos) are built by the "
               "evaluation itself, never taken from a run. Values are means over views with a 95% bootstrap "
               "interval; a run wins a metric only when the 95% interval of its paired per-view difference "
               "to every other run excludes 0.</p>")
