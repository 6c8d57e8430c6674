"""`python -m tlvg_warp evaluate RUN [--against RUN2]`: SPEC §4 metrics of a stylization run folder.

Reads RUN/stylized.ply, cameras.json (INRIA), style.png (or config.yaml's `style`), renders/ and
originals/ (the run's stylized and un-stylized views, PNG), photos/, metrics.json and, when the run stored
them, fields/<view>.npy (target doubled-angle fields). Multi-view consistency is measured on fresh renders
of stylized.ply (it needs depth); the image metrics (flow alignment, style and content distance) on the
PNGs the run wrote, falling back to the fresh renders. Writes evaluation.json and evaluation.html (images
embedded, nothing linked) to --out (default: RUN).
"""
from __future__ import annotations

import base64
import html
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..fileio import write_json, write_text

REPORT_THUMB_H = 240  # px height of each image in the HTML report (large views are shrunk to keep it small)


def add_arguments(p):
    p.add_argument("run", help="stylization run folder (stylized.ply, cameras.json, style.png, renders/, ...)")
    p.add_argument("--against", default=None, help="a second run on the same scene and painting to compare")
    p.add_argument("--vgg-weights", default=None, help="VGG-16 weights path, or 'random' (smoke runs only)")
    p.add_argument("--out", default=None, help="folder for evaluation.json/.html (default: RUN)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--max-views", type=int, default=0, help="evaluate only the first N cameras (0: all)")


# ---------------------------------------------------------------- reading a run folder
def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("missing file", path) from None
    except (OSError, ValueError) as e:
        raise InputError(f"unreadable JSON ({e})", path) from None


def cameras_from_json(path: Path):
    """INRIA cameras.json -> (names, [Camera]) (rotation = camera-to-world, principal point at the center)."""
    from ..types import Camera

    data = _read_json(path)
    if not isinstance(data, list) or not data:
        raise InputError("expected a non-empty list of cameras", path)
    from ..io.datasets import inria_camera_entries

    names, cams = [], []
    for name, w2c, fx, fy, w, h in inria_camera_entries(data, path):
        cams.append(Camera(torch.from_numpy(w2c), fx, fy, w / 2, h / 2, int(w), int(h), name=name))
        names.append(name)
    return names, cams


def _image(path: Path, shape=None):
    from ..io.images import read_image

    a = read_image(path)[:, :, :3]
    if shape is not None and a.shape[:2] != tuple(shape):
        raise InputError(f"image is {a.shape[1]}x{a.shape[0]}, expected {shape[1]}x{shape[0]}", path)
    return torch.from_numpy(np.ascontiguousarray(a))


def _view_file(folder: Path, name: str, index: int):
    for stem in (name, Path(name).stem, f"view_{index:03d}"):
        for ext in (".png", ".jpg", ".jpeg"):
            if (folder / (stem + ext)).is_file():
                return folder / (stem + ext)
    return None


def load_run(run, max_views: int = 0) -> dict:
    """Everything evaluate needs from a run folder; InputError naming the file when something is wrong."""
    import yaml

    from ..io.ply import load_ply

    run = Path(run)
    if not run.is_dir():
        raise InputError("run folder not found", run)
    cfg = {}
    if (run / "config.yaml").is_file():
        try:
            cfg = yaml.safe_load((run / "config.yaml").read_text()) or {}
        except yaml.YAMLError as e:
            raise InputError(f"unreadable YAML ({e})", run / "config.yaml") from None
        if not isinstance(cfg, dict):
            raise InputError("expected a mapping", run / "config.yaml")
    ply = run / "stylized.ply"
    if not ply.is_file():
        raise InputError("missing stylized.ply (not a stylization run folder?)", run)
    g = load_ply(ply)
    names, cams = cameras_from_json(run / "cameras.json")
    if max_views > 0:
        names, cams = names[:max_views], cams[:max_views]
    style = run / "style.png"
    if not style.is_file() and cfg.get("style"):
        style = Path(cfg["style"])
    if not style.is_file():
        raise InputError("no painting: neither style.png nor config.yaml's style exists", run)
    painting = _image(style)
    metrics = {}
    if (run / "metrics.json").is_file():
        metrics = _read_json(run / "metrics.json")
        if not isinstance(metrics, dict):
            raise InputError("expected a JSON object", run / "metrics.json")
    bg = cfg.get("background") or [1.0, 1.0, 1.0]
    per = {"renders": [], "originals": [], "photos": [], "fields": []}
    for i, (n, c) in enumerate(zip(names, cams)):
        for sub in ("renders", "originals", "photos"):
            f = _view_file(run / sub, n, i)
            per[sub].append(_image(f, (c.height, c.width)) if f is not None else None)
        f = next((p for p in (run / "fields" / f"{n}.npy", run / "fields" / f"view_{i:03d}.npy") if p.is_file()), None)
        fld = None
        if f is not None:
            fld = np.load(f)
            if fld.shape != (c.height, c.width, 2):
                raise InputError(f"target field has shape {fld.shape}, expected {(c.height, c.width, 2)}", f)
        per["fields"].append(fld)
    return {"dir": run, "config": cfg, "gaussians": g, "ply_bytes": ply.stat().st_size, "names": names,
            "cameras": cams, "painting": painting, "style_path": str(style), "metrics": metrics,
            "background": [float(x) for x in bg], **per}


# ---------------------------------------------------------------- evaluation
def _wall_time(m: dict):
    for key in ("wall_time_s", "total_time_s", "time_s"):
        if isinstance(m.get(key), (int, float)):
            return float(m[key])
    t = m.get("time") or m.get("time_s") or m.get("times")
    if isinstance(t, dict):
        if isinstance(t.get("total"), (int, float)):
            return float(t["total"])
        vals = [float(v) for v in t.values() if isinstance(v, (int, float))]
        return sum(vals) if vals else None
    return None


def evaluate_run(run: dict, net, device) -> dict:
    from ..eval import metrics as M

    t0 = time.perf_counter()
    g = run["gaussians"].to(device=device)
    views = M.render_views(g, run["cameras"], run["background"])
    originals = run["originals"] if all(o is not None for o in run["originals"]) else None
    # image metrics on the PNGs the run wrote (when present); consistency on the fresh renders (they carry depth)
    res = M.scene_metrics(views, run["painting"], net, originals, run["fields"], colors=run["renders"])
    res["per_view"] = [dict(name=n, **r) for n, r in zip(run["names"], res["per_view"])]
    m = run["metrics"]
    res["summary"] |= {"gaussians": run["gaussians"].num, "bytes": run["ply_bytes"], "wall_time_s": _wall_time(m)}
    for k in ("gaussians_in", "gaussians_out", "gaussians_input", "gaussians_final", "bytes_in", "bytes_out"):
        if k in m:
            res["summary"][k] = m[k]
    res["flow_target"] = "stored" if any(f is not None for f in run["fields"]) else "canvas"
    res["content_reference"] = "originals" if originals is not None else None
    res["eval_time_s"] = time.perf_counter() - t0
    res["run"] = str(run["dir"])
    res["run_metrics"] = m
    return res


LOWER_IS_BETTER = {"consistency_k1", "consistency_k5", "style_fast", "style_gram", "content", "gaussians",
                   "bytes", "wall_time_s", "nan"}


def compare(a: dict, b: dict) -> dict:
    """Per summary metric: value of each run and which is better ("run", "against" or "tie")."""
    out = {}
    for k, va in a.items():
        vb = b.get(k)
        if not isinstance(va, (int, float)) or not isinstance(vb, (int, float)):
            continue
        if math.isclose(va, vb, rel_tol=1e-9, abs_tol=1e-12):
            better = "tie"
        else:
            better = "run" if (va < vb) == (k in LOWER_IS_BETTER) else "against"
        out[k] = {"run": va, "against": vb, "better": better}
    return out


# ---------------------------------------------------------------- report
def _png_b64(img) -> str:
    import cv2

    a = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    a = np.clip(np.nan_to_num(a, nan=0.0), 0, 1)
    if a.shape[0] > REPORT_THUMB_H:
        a = cv2.resize(a, (max(1, round(a.shape[1] * REPORT_THUMB_H / a.shape[0])), REPORT_THUMB_H),
                       interpolation=cv2.INTER_AREA)
    u8 = (a * 255 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


def _fmt(v):
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def stroke_picture(painting):
    from ..losses.stroke_field import field_picture, stroke_field
    from ..losses.vgg import resize_style

    p = resize_style(painting.numpy() if isinstance(painting, torch.Tensor) else painting)
    th, c, _ = stroke_field(p)
    return field_picture(p, th, c)


def report_html(result: dict, run: dict, other: dict | None = None, other_run: dict | None = None) -> str:
    s = result["summary"]
    keys = list(s)
    head = "<tr><th>metric</th><th>run</th>" + ("<th>against</th><th>better</th>" if other else "") + "</tr>"
    rows = []
    cmp_ = result.get("comparison", {})
    for k in keys:
        extra = ""
        if other:
            extra = f"<td>{_fmt(other['summary'].get(k))}</td><td>{_fmt(cmp_.get(k, {}).get('better'))}</td>"
        rows.append(f"<tr><td>{html.escape(k)}</td><td>{_fmt(s[k])}</td>{extra}</tr>")
    def img(a, cap):
        if a is None:
            return ""
        return f"<figure><img src='{_png_b64(a)}'><figcaption>{html.escape(cap)}</figcaption></figure>"
    views = []
    for i, name in enumerate(run["names"]):
        pv = result["per_view"][i]
        cells = [img(run["photos"][i], "photo"), img(run["originals"][i], "original render"),
                 img(run["renders"][i] if run["renders"][i] is not None else None, "stylized (run)")]
        if other_run is not None and i < len(other_run["names"]):
            cells.append(img(other_run["renders"][i], "stylized (against)"))
        info = ", ".join(f"{k} {_fmt(v)}" for k, v in pv.items() if k != "name")
        views.append(f"<h3>{html.escape(name)}</h3><div class=row>{''.join(cells)}</div><p class=small>{info}</p>")
    vgg_note = ("<p class=warn>VGG is randomly initialized: style and content distances are NOT meaningful.</p>"
                if result.get("vgg_random") else "")
    return f"""<!doctype html><html><head><meta charset=utf-8><title>tlvg_warp evaluation</title><style>
body{{font-family:sans-serif;margin:1.5em}} table{{border-collapse:collapse}} td,th{{border:1px solid #ccc;
padding:3px 8px;text-align:right}} .row{{display:flex;gap:8px;flex-wrap:wrap}} figure{{margin:0}}
figcaption,.small{{font-size:12px;color:#555}} .warn{{color:#b00;font-weight:bold}}</style></head><body>
<h1>Evaluation of {html.escape(str(run['dir']))}</h1>
{f"<p>against {html.escape(str(other_run['dir']))}</p>" if other_run else ""}{vgg_note}
<p class=small>VGG: {html.escape(str(result.get('vgg')))}; flow target: {result.get('flow_target')};
consistency: masked RMSE of reprojected stylized colors (k = 1 short, k = 5 long range; lower is better).</p>
<table>{head}{''.join(rows)}</table>
<h2>Painting and its stroke field</h2><div class=row>{img(run['painting'], 'painting')}
{img(stroke_picture(run['painting']), 'stroke field (LIC)')}</div>
<h2>Views</h2>{''.join(views)}</body></html>
"""


VGG_METRICS = ("style_fast", "style_gram", "content")  # need pretrained features (SPEC §4)


def _not_measured(res: dict, net) -> dict:
    """With random VGG weights the style and content distances are reported as not measured (None)."""
    if net.is_random:
        for k in VGG_METRICS:
            if k in res["summary"]:
                res["summary"][k] = None
        res["not_measured"] = [k for k in VGG_METRICS if k in res["summary"]]
    return res


def run(args) -> int:
    from ..losses.vgg import load_vgg

    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    r = load_run(args.run, args.max_views)
    o = load_run(args.against, args.max_views) if args.against else None
    out = Path(args.out) if args.out else r["dir"]
    weights = args.vgg_weights
    if weights is None and any((x or {}).get("metrics", {}).get("vgg_random") for x in (r, o)):
        weights = "random"  # a smoke run made with random weights: no download just to score it
    net = load_vgg(weights, device=device)
    res = _not_measured(evaluate_run(r, net, device), net)
    res["vgg"], res["vgg_random"] = net.source, bool(net.is_random)
    if o is not None:
        ores = _not_measured(evaluate_run(o, net, device), net)
        ores["vgg"], ores["vgg_random"] = net.source, bool(net.is_random)
        res["against"] = ores
        res["comparison"] = compare(res["summary"], ores["summary"])
    write_json(out / "evaluation.json", res)
    write_text(out / "evaluation.html", report_html(res, r, res.get("against"), o))
    s = res["summary"]
    print(f"{'metric':<18}{'run':>14}" + (f"{'against':>14}" if o else ""))
    for k, v in s.items():
        line = f"{k:<18}{_fmt(v):>14}"
        if o:
            line += f"{_fmt(res['against']['summary'].get(k)):>14}"
        print(line)
    if net.is_random:
        print("note: VGG is randomly initialized (--vgg-weights random): style/content distances are not meaningful")
    print(f"wrote {out / 'evaluation.json'} and {out / 'evaluation.html'}")
    return 0
