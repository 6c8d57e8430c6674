"""The evaluation engine behind `evaluate` and `study`: SPEC §4 metrics of stylization runs of one scene and
painting, all measured with one ruler (eval/refs.py builds the references from the un-stylized scene, the views,
the photos and the painting; nothing a run stored about its own targets is read).

A run folder gives stylized.ply, cameras.json, photos/, style.png (or config.yaml's style), metrics.json
(times, counts) and orbit.mp4. The un-stylized scene: the one given, else the one the run's sources.json (or an
older run's checkpoint.pt) names, else RUN/reconstruct/point_cloud.ply, else the built-in demo (at the density the
run used) when the run was made on it. Beside the runs, the same ruler scores two anchors built here: the
un-stylized scene ("no stylization") and the painting pasted over every view ("sticker"); a run wins a metric only
where it also beats the anchor that metric exists to beat (eval/metrics.py ANCHOR_TO_BEAT).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ..config_io import read_yaml_mapping
from ..errors import InputError
from ..io.datasets import read_inria_cameras
from ..io.demo import demo_scene
from ..io.images import read_image
from ..io.ply import load_ply
from ..losses.stroke_field import field_picture, stroke_field
from ..losses.vgg import resize_style
from ..runs import run_sources
from . import metrics as M
from . import report as H
from . import CAM_TOL, DEFAULT_EVAL_HEIGHT, MAX_REPORT_VIEWS, MIN_EVAL_HEIGHT
from .refs import anchor_views, build_references, compare, score_views, stylized_views, summarize
from .report import fmt


def auto_eval_height(cameras) -> int:
    """The style/content evaluation height for views of this size: their own height within
    [MIN_EVAL_HEIGHT, DEFAULT_EVAL_HEIGHT] (enlarging a small render to 256 rows adds VGG work, not detail)."""
    return int(min(DEFAULT_EVAL_HEIGHT, max(MIN_EVAL_HEIGHT, max(c.height for c in cameras))))


def stage_logger(stream=None):
    """A log function that writes each stage as one line with the seconds since it was made."""
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[evaluate {time.perf_counter() - t0:6.1f}s] {msg}", file=stream or sys.stderr, flush=True)
    return log


# ---------------------------------------------------------------- reading a run folder
def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("missing file", path) from None
    except (OSError, ValueError) as e:
        raise InputError(f"unreadable JSON ({e})", path) from None


def _image(path: Path, shape=None) -> np.ndarray:
    a = read_image(path)[:, :, :3]
    if shape is not None and a.shape[:2] != tuple(shape):
        raise InputError(f"image is {a.shape[1]}x{a.shape[0]}, expected {shape[1]}x{shape[0]}", path)
    return np.ascontiguousarray(a, np.float32)


def _view_file(folder: Path, name: str, index: int):
    for stem in (name, Path(name).stem, f"view_{index:03d}"):
        for ext in (".png", ".jpg", ".jpeg"):
            if (folder / (stem + ext)).is_file():
                return folder / (stem + ext)
    return None


def _yaml(path: Path) -> dict:
    return read_yaml_mapping(path) if path.is_file() else {}


def load_run(run, max_views: int = 0) -> dict:
    """What evaluate reads from a run folder; InputError naming the file when something is wrong."""
    run = Path(run)
    if not run.is_dir():
        raise InputError("run folder not found", run)
    cfg = _yaml(run / "config.yaml")
    ply = run / "stylized.ply"
    if not ply.is_file():
        raise InputError("missing stylized.ply (not a stylization run folder?)", run)
    names, cams = read_inria_cameras(run / "cameras.json")
    n_total = len(cams)
    if max_views > 0:
        names, cams = names[:max_views], cams[:max_views]
    style = run / "style.png"
    if not style.is_file() and cfg.get("style"):
        style = Path(cfg["style"])
    if not style.is_file():
        raise InputError("no painting: neither style.png nor config.yaml's style exists", run)
    photos = []
    for i, (n, c) in enumerate(zip(names, cams)):
        f = _view_file(run / "photos", n, i)
        if f is None:
            raise InputError(f"missing photo of view {n}", run / "photos")
        photos.append(_image(f, (c.height, c.width)))
    metrics = _read_json(run / "metrics.json") if (run / "metrics.json").is_file() else {}
    if not isinstance(metrics, dict):
        raise InputError("expected a JSON object", run / "metrics.json")
    bg = cfg.get("background") or [1.0, 1.0, 1.0]
    return {"dir": run, "name": run.name, "gaussians": load_ply(ply), "bytes": ply.stat().st_size, "names": names,
            "cameras": cams, "painting": _image(style), "photos": photos, "metrics": metrics,
            "background": tuple(float(x) for x in bg), "video": run / "orbit.mp4", "n_total": n_total}


def resolve_scene(run: dict, scene=None):
    """The un-stylized scene of a run (see the module doc)."""
    if scene is not None:
        return load_ply(Path(scene))
    src = run_sources(run["dir"])
    for cand in (src.get("scene"), run["dir"] / "reconstruct" / "point_cloud.ply"):
        if cand and Path(cand).is_file():
            return load_ply(Path(cand))
    if not src.get("data"):
        g = demo_original(run["dir"], run["cameras"], run["n_total"])
        if g is not None:
            return g
    raise InputError("cannot find the un-stylized scene of this run; pass --scene PLY", run["dir"])


def demo_original(run_dir, cameras, n_total: int | None = None):
    """The built-in demo scene a demo run started from, or None when the cameras are not the demo's orbit. The
    demo samples its surfaces more sparsely at a larger downscale (stylize: spacing = max(1, downscale)), so the
    run's config.yaml downscale picks the same density (e.g. 4,678 Gaussians at downscale 2, not 18,733)."""
    if not cameras:
        return None
    try:
        downscale = float(_yaml(Path(run_dir) / "config.yaml").get("downscale") or 1.0)
    except (TypeError, ValueError):
        downscale = 1.0
    c = cameras[0]
    g, cams = demo_scene(n_views=n_total or len(cameras), width=c.width, height=c.height,
                         spacing=max(1.0, downscale))
    if all(torch.allclose(a.world_to_camera.double(), b.world_to_camera.double(), atol=CAM_TOL)
           for a, b in zip(cams, cameras)):
        return g
    return None


def check_same_setting(runs: list) -> None:
    """Runs compared with one ruler must share cameras, photos and painting."""
    a = runs[0]
    for r in runs[1:]:
        same_cams = len(r["cameras"]) == len(a["cameras"]) and all(
            (x.width, x.height) == (y.width, y.height) and abs(x.fx - y.fx) < 1e-3 and
            torch.allclose(x.world_to_camera.double(), y.world_to_camera.double(), atol=CAM_TOL)
            for x, y in zip(r["cameras"], a["cameras"]))
        if not same_cams:
            raise InputError(f"not the same views as {a['dir']} (cameras.json differs)", r["dir"] / "cameras.json")
        if r["painting"].shape != a["painting"].shape or not np.array_equal(r["painting"], a["painting"]):
            raise InputError(f"not the same painting as {a['dir']}", r["dir"] / "style.png")
        if any(not np.array_equal(p, q) for p, q in zip(r["photos"], a["photos"])):
            raise InputError(f"not the same photos as {a['dir']}", r["dir"] / "photos")


# ---------------------------------------------------------------- evaluation
def wall_time(m: dict):
    for key in ("wall_time_s", "total_time_s"):
        if isinstance(m.get(key), (int, float)):
            return float(m[key])
    t = m.get("time_per_phase_s") or m.get("time")
    if isinstance(t, dict):
        vals = [float(v) for v in t.values() if isinstance(v, (int, float))]
        return sum(vals) if vals else None
    return None


def pair_comparisons(names, per_views, anchors: dict, groups=None) -> dict:
    """{"a vs b": compare(a, b)} for every pair of runs, then every run against every anchor (per-view metrics).
    ``groups``: {metric: one label per view item} (the seed, where runs of several seeds are pooled; refs.compare)."""
    pairs = {f"{names[i]} vs {names[j]}": compare(per_views[i], per_views[j], groups)
             for i in range(len(names)) for j in range(i + 1, len(names))}
    return pairs | {f"{n} vs {a}": compare(p, anchors[a], groups) for n, p in zip(names, per_views) for a in anchors}


def winners(names, per_views, anchors: dict | None = None, groups=None) -> dict:
    """Per metric: the run whose paired difference to every other run favours it (95%) and that also beats the
    anchor the metric exists to beat (metrics.ANCHOR_TO_BEAT; ``anchors``: {anchor name: per-view dict}),
    else absent."""
    out = {}
    anchors = anchors or {}
    for k in M.METRICS:
        if not M.METRICS[k].per_view:
            continue
        for i, n in enumerate(names):
            if per_views[i].get(k) is None:
                continue
            rivals = [per_views[j] for j in range(len(names)) if j != i]
            target = M.ANCHOR_TO_BEAT.get(k)
            if target in anchors and anchors[target].get(k) is not None:
                rivals.append(anchors[target])
            if rivals and all(compare({k: per_views[i][k]}, {k: r[k]}, groups).get(k, {}).get("better") == "a"
                              for r in rivals):
                out[k] = n
    return out


def not_discriminating(per_views, anchors: dict, groups=None) -> dict:
    """{metric: the anchor it exists to beat (metrics.ANCHOR_TO_BEAT)} where that anchor beats every run (95%):
    on this scene the metric does not tell the runs from doing nothing (flow, style, strokes, detail) or from
    pasting the painting (content, multi-view, chroma noise). The other anchor winning is expected (the painting
    has the painting's style; the un-stylized scene is the scene) and is not a verdict."""
    out = {}
    for k, target in M.ANCHOR_TO_BEAT.items():
        pa = anchors.get(target) if target else None
        if not per_views or pa is None or pa.get(k) is None:
            continue
        if all(pv.get(k) is not None and compare({k: pa[k]}, {k: pv[k]}, groups).get(k, {}).get("better") == "a"
               for pv in per_views):
            out[k] = target
    return out


def evaluate_runs(run_dirs, net, device, *, scene=None, max_views: int = 0, eval_height: int | None = None,
                  cache_dir=None, log=print) -> tuple[dict, list, "object"]:
    """Score every run, and the two anchors, with one set of references. Returns (result dict, loaded runs,
    refs)."""
    log(f"reading {len(run_dirs)} run folder(s)")
    runs = [load_run(d, max_views) for d in run_dirs]
    check_same_setting(runs)
    if eval_height is None:
        eval_height = auto_eval_height(runs[0]["cameras"])
    log("finding the un-stylized scene")
    g0 = resolve_scene(runs[0], scene)
    t0 = time.perf_counter()
    refs = build_references(g0, runs[0]["cameras"], runs[0]["background"], runs[0]["painting"], runs[0]["photos"],
                            net, eval_height=eval_height, cache_dir=cache_dir, device=device, log=log)
    log(f"references: {refs.key} ({time.perf_counter() - t0:.1f}s)")
    per, results = [], []
    for r in runs:
        t1 = time.perf_counter()
        views, a2 = stylized_views(r["gaussians"], refs, device)
        r["colors"] = [v["color"] for v in views]  # for the report (not written to JSON)
        pv = score_views(views, a2, refs, net)
        m = r["metrics"]
        scalars = {"gaussians": r["gaussians"].num, "bytes": r["bytes"], "wall_time_s": wall_time(m)}
        per.append(pv)
        results.append({"run": str(r["dir"]), "name": r["name"], "summary": summarize(pv) | scalars,
                        "per_view": pv, "phase_times_s": m.get("time_per_phase_s"),
                        "eval_time_s": round(time.perf_counter() - t1, 3)})
        log(f"scored {r['dir']} ({time.perf_counter() - t1:.1f}s)")
    anchors, anchor_per = [], {}
    for a, (views, a2) in anchor_views(refs).items():
        t1 = time.perf_counter()
        pv = score_views(views, a2, refs, net)
        anchor_per[a] = pv
        anchors.append({"name": a, "summary": summarize(pv), "per_view": pv})
        log(f"scored the anchor '{a}' ({time.perf_counter() - t1:.1f}s)")
    names = unique_names(runs)
    pairs = pair_comparisons(names, per, anchor_per)
    res = {"vgg": net.source, "vgg_random": bool(net.is_random), "references": refs.key,
           "eval_height": eval_height, "views": runs[0]["names"], "names": names, "runs": results,
           "anchors": anchors, "anchor_to_beat": dict(M.ANCHOR_TO_BEAT),
           "comparisons": pairs, "winners": winners(names, per, anchor_per),
           "not_discriminating": not_discriminating(per, anchor_per),
           "not_measured": [k for k, v in per[0].items() if v is None]}
    return res, runs, refs


def unique_names(runs) -> list[str]:
    names = [r["name"] for r in runs]
    if len(set(names)) < len(names):
        names = [f"{r['dir'].parent.name}/{r['name']}" for r in runs]
    if len(set(names)) < len(names):
        names = [f"{n} ({i + 1})" for i, n in enumerate(names)]
    return names


def report_html(res: dict, runs: list, refs) -> str:
    names = res["names"]
    sums = [r["summary"] for r in res["runs"]]
    anchors = res.get("anchors") or []
    warn = ("<p class=warn>VGG-16 weights are random: style, content and flow-alignment metrics are not "
            "measured.</p>" if res["vgg_random"] else "")
    body = [f"<p>{len(names)} run(s): " + ", ".join(H.esc(r['run']) for r in res["runs"]) + "</p>", warn,
            f"<p class=small>VGG: {H.esc(res['vgg'])}; references {res['references']}; "
            f"{len(res['views'])} views; style/content measured at height {res['eval_height']} px.</p>",
            H.METHOD_NOTE, H.ANCHOR_NOTE, "<h2>Results</h2>",
            H.results_table(names, sums, res["winners"], anchors=anchors,
                            not_discriminating=res.get("not_discriminating"))]
    if res["comparisons"]:
        body.append("<h2>Paired comparisons</h2>" + comparisons_table(res["comparisons"]))
    an = [a["name"] for a in anchors]
    body += ["<h2>Means with 95% intervals</h2>", H.bars_chart(names + an, sums + [a["summary"] for a in anchors]),
             "<h2>Per view</h2>", H.per_view_chart(names + an, [r["per_view"] for r in res["runs"]]
                                                   + [a["per_view"] for a in anchors]),
             "<h2>Speed and quality</h2>",
             H.speed_chart(names, [s.get("wall_time_s") for s in sums], sums)]
    work = resize_style(refs.painting)
    th, c, _ = stroke_field(work)
    body.append("<h2>Painting</h2><div class=row>" + H.figure(refs.painting, "painting")
                + H.figure(field_picture(work, th, c), "its stroke field") + "</div>")
    n = len(refs.cameras)
    pick = sorted(set(np.linspace(0, n - 1, min(MAX_REPORT_VIEWS, n)).round().astype(int)))
    stylized = {name: [r["colors"][i] for i in pick] for r, name in zip(runs, names)}
    body.append("<h2>Views</h2>")
    for k, i in enumerate(pick):
        cells = [H.figure(refs.photos[i], "photo"), H.figure(refs.base[i]["color"], "no stylization (anchor)"),
                 H.figure(M.sticker(refs.painting, *refs.base[i]["color"].shape[:2]), "sticker (anchor)")]
        cells += [H.figure(stylized[nm][k], nm) for nm in names]
        if refs.fields is not None:
            th, c = 0.5 * np.arctan2(refs.fields[i][..., 1], refs.fields[i][..., 0]), np.linalg.norm(refs.fields[i], axis=-1)
            cells.append(H.figure(field_picture(refs.base[i]["color"], th, c), "common stroke field"))
        body.append(f"<h3>{H.esc(res['views'][i])}</h3><div class=row>{''.join(cells)}</div>")
    vids = [(nm, H.video(r["video"])) for nm, r in zip(names, runs)]
    if any(v for _, v in vids):
        body.append("<h2>Orbit videos</h2><div class=row>" + "".join(
            f"<figure>{v}<figcaption>{H.esc(nm)}</figcaption></figure>" for nm, v in vids if v) + "</div>")
    return H.page("tlvg_warp evaluation", "".join(body))


def comparisons_table(comparisons: dict) -> str:
    keys = [k for k in H.M.METRICS if any(k in c for c in comparisons.values())]
    head = "<tr><th class=l>metric</th>" + "".join(f"<th>{H.esc(p)}: a − b [95%]</th>" for p in comparisons) + "</tr>"
    rows = []
    for k in keys:
        tds = []
        for p, c in comparisons.items():
            d = c.get(k)
            if not d or d.get("mean") is None:
                tds.append("<td>–</td>")
                continue
            a, b = p.split(" vs ", 1)
            who = {"a": a, "b": b}.get(d["better"], d["better"])
            tds.append(f"<td>{H.fmt(d['mean'], 3)} <span class=small>[{H.fmt(d['lo'], 3)}, {H.fmt(d['hi'], 3)}]"
                       f"</span><br>{'<b>' + H.esc(who) + '</b>' if who != 'no difference' else 'no difference'}</td>")
        rows.append(f"<tr>{H.metric_head(k)}{''.join(tds)}</tr>")
    return f"<table>{head}{''.join(rows)}</table>"


def print_table(res: dict) -> None:
    names = res["names"]
    anchors = res.get("anchors") or []
    cols = names + [f"[{a['name']}]" for a in anchors]
    print(f"{'metric':<16}" + "".join(f" {n[:24]:>25}" for n in cols))
    for k in M.METRICS:
        vals = []
        for s in [r["summary"] for r in res["runs"]] + [a["summary"] for a in anchors]:
            v = s.get(k, "")
            if v is None:
                vals.append("not measured")
            elif isinstance(v, dict):
                vals.append("–" if v["mean"] is None
                            else f"{fmt(v['mean'], 3)} [{fmt(v['lo'], 2)},{fmt(v['hi'], 2)}]")
            else:
                vals.append(fmt(v) if v != "" else "")
        w = res["winners"].get(k)
        nd = (res.get("not_discriminating") or {}).get(k)
        note = (f"   winner: {w}" if w else "") + (f"   not discriminating: {nd} beats every run" if nd else "")
        print(f"{k:<16}" + "".join(f" {v:>25}" for v in vals) + note)
    print("[anchors] are references scored with the same ruler; a winner also beats the anchor its metric exists "
          "to beat: " + ", ".join(f"{k} vs {a}" for k, a in M.ANCHOR_TO_BEAT.items() if a))


def pick_weights(args_weights, run_dirs):
    """--vgg-weights, else random when every run was itself a random-weights smoke run (no download just to
    score it: its style metrics are then not measured), else the default resolution order."""
    if args_weights is not None:
        return args_weights
    flags = []
    for d in run_dirs:
        f = Path(d) / "metrics.json"
        try:
            flags.append(bool(json.loads(f.read_text()).get("vgg_random")) if f.is_file() else False)
        except (OSError, ValueError):
            flags.append(False)
    return "random" if flags and all(flags) else None


