"""`python -m tlvg_warp bench [sweep]`: speed against quality, charted.

Stylization sweep: one setting varied at a time around a base point (iterations, render resolution, VGG
input scale, Gaussian budget, style loss variant) on a scene + painting (the demo by default). Each point is
timed (wall time of the pipeline) and scored on the same evaluation cameras at the base resolution (flow
alignment against the painting's field mapped "canvas" onto each view, so every point is scored against
the same target; multi-view consistency k = 1; FAST/Gram style distance; content distance to the
un-stylized renders). Writes sweep.csv/.png (the Pareto front marked, pareto.write_sweep) and sweep.json.

Rasterizer chart: float32 Warp renders against the float64 torch reference at several image sizes and
Gaussian counts: time against max / mean abs color error -> raster.csv/.png.
"""
from __future__ import annotations

import statistics
import time
from pathlib import Path

import torch

from ..errors import InputError
from ..fileio import write_json
from ..io import load_ply
from ..io.datasets import load_dataset
from ..io.demo import builtin_painting
from ..io.images import read_image
from ..renderer import render
from . import quick as M  # the per-run gauges (the evaluation proper is eval/metrics.py)
from . import stability as S
from .bench_raster import bench_camera, random_scene
from .pareto import write_sweep
from .stability import _resize, _style_feats, stylize_scene

QUALITY = ("flow_alignment", "consistency_k1", "style_fast", "style_gram", "content")
HIGHER_IS_BETTER = {"flow_alignment": True, "consistency_k1": False, "style_fast": False, "style_gram": False,
                    "content": False}


# ---------------------------------------------------------------- the scene
def load_scene(args, quick: bool, device: str):
    """(Base, description). Default: the demo; --scene PLY needs --data (its cameras and photos)."""
    iters = getattr(args, "iterations", None) or (6 if quick else 3000)
    style = builtin_painting()
    if args.style:
        p = Path(args.style)
        style = torch.from_numpy(read_image(p)[:, :, :3].copy())
    if not args.scene:
        if args.data:
            raise InputError("--data needs --scene (the PLY fitted to it); without both the demo is used")
        base = S.demo_base(quick, device, n_views=6 if quick else 24, size=(40, 30) if quick else (160, 120),
                           stride=4 if quick else 1, iterations=iters)
        return S.dataclasses.replace(base, style=style), "demo"
    if not args.data:
        raise InputError("--scene needs --data: the dataset (cameras and photos) the scene was fitted to")
    g = load_ply(args.scene).to(device)  # evaluation renders happen where the sweep runs
    ds = load_dataset(args.data, downscale=4 if quick else None)
    n = min(len(ds), 6 if quick else len(ds))
    base = S.Base(g, ds.cameras[:n], ds.names[:n], [ds.image(i) for i in range(n)], style,
                  (1.0, 1.0, 1.0), {"device": device, "iterations": iters, "log_every": 1000})
    return base, f"{args.scene} on {args.data}"


def sweep_points(quick: bool, base_iters: int, n_gauss: int) -> list[dict]:
    """One setting varied at a time around the base (label, overrides, budget fraction, render scale)."""
    it = base_iters
    pts = [{"label": "base"}]
    its = [it // 2, it * 2] if quick else [it // 10, it // 3, it * 2]
    pts += [{"label": f"iters {i}", "iterations": max(3, i)} for i in its]
    pts += [{"label": f"res x{s:g}", "render_scale": s} for s in ([0.5] if quick else [0.25, 0.5])]
    pts += [{"label": f"vgg x{s:g}", "vgg_scale": s} for s in ([0.25] if quick else [0.25, 1.0])]
    pts += [{"label": f"budget {f:g}", "budget": f} for f in ([0.5] if quick else [0.1, 0.25, 0.5])]
    pts += [{"label": f"loss {v}", "style_loss": v} for v in ("gram", "nnfm")]
    return pts


def _subsample(g, frac: float):
    n = max(1, round(g.num * frac))
    idx = torch.randperm(g.num, generator=torch.Generator().manual_seed(0))[:n].sort().values
    return g.subset(idx.to(g.device))


def run_point(pt: dict, base, vgg, eval_views_cache: dict) -> dict:
    """Stylize with one point's settings, time it, score it on the base cameras."""
    ov = dict(base.overrides)
    b = base
    if "render_scale" in pt:
        c = base.cameras[0]
        b = _resize(base, max(8, round(c.width * pt["render_scale"])), max(6, round(c.height * pt["render_scale"])))
    g = b.gaussians
    if "budget" in pt:
        g = _subsample(g, pt["budget"])
        ov["density.max_gaussians"] = g.num  # density control may not grow past the budget
    for k, key in (("iterations", "iterations"), ("vgg_scale", "vgg_scale"), ("style_loss", "loss.style_loss")):
        if k in pt:
            ov[key] = pt[k]
    row = {"label": pt["label"], **{k: v for k, v in pt.items() if k != "label"}, "gaussians_in": g.num}
    t0 = time.perf_counter()
    try:
        out, _, pm = stylize_scene(g, b.cameras, b.names, b.photos, b.style, b.background, ov, vgg)
    except Exception as e:  # noqa: BLE001 - a failed point is a row with its error, not a failed sweep
        row |= {"time_s": None, "error": f"{type(e).__name__}: {e}"[:300]}
        return row
    row["time_s"] = time.perf_counter() - t0
    row["gaussians_out"] = out.num
    views = M.render_views(out, base.cameras, base.background)
    if "originals" not in eval_views_cache:
        eval_views_cache["originals"] = [v["color"] for v in M.render_views(base.gaussians, base.cameras,
                                                                            base.background)]
    q = M.scene_metrics(views, base.style, vgg, eval_views_cache["originals"], None, ks=(1,),
                        style_feats=_style_feats(vgg, base.style))["summary"]
    row |= {k: q.get(k) for k in QUALITY}
    row["nan"] = q["nan"]
    row["pipeline_train_s"] = pm.get("train_time_s")
    return row


def run_sweep(base, points, vgg, log=print) -> list[dict]:
    cache: dict = {}
    rows = []
    for pt in points:
        r = run_point(pt, base, vgg, cache)
        rows.append(r)
        if log:
            log(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()))
    return rows


# ---------------------------------------------------------------- the rasterizer alone
def raster_rows(cases, device, repeats: int = 3, log=print) -> list[dict]:
    """cases: (n Gaussians, width, height). float32 Warp render vs the float64 reference of the same scene."""
    # lazy: imports Warp
    from ..reference import render_reference
    rows = []
    for n, w, h in cases:
        g = random_scene(n, -3.0, 1, device)
        cam = bench_camera(w, h)
        with torch.no_grad():
            ref = render_reference(g.to(device="cpu", dtype=torch.float64), cam).color
            render(g, cam)  # warm-up (kernel load)
            times = []
            for _ in range(repeats):
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                t0 = time.perf_counter()
                out = render(g, cam).color
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                times.append(time.perf_counter() - t0)
        err = (out.detach().cpu().double() - ref).abs()
        r = {"label": f"{n} G {w}x{h}", "gaussians": n, "width": w, "height": h, "time_s": statistics.median(times),
             "max_abs_err": float(err.max()), "mean_abs_err": float(err.mean())}
        rows.append(r)
        if log:
            log(f"raster {r['label']}: {r['time_s'] * 1e3:.2f} ms, max err {r['max_abs_err']:.2e}, "
                f"mean err {r['mean_abs_err']:.2e}")
    return rows


def run(args) -> int:
    # lazy: imports Warp
    from ..losses.vgg import load_vgg
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    out = Path(args.out)
    vgg = load_vgg(args.vgg_weights or ("random" if args.quick else None), device=device)
    base, what = load_scene(args, args.quick, device)
    base.overrides["vgg_weights"] = args.vgg_weights or ("random" if args.quick else None)
    points = sweep_points(args.quick, base.overrides["iterations"], base.gaussians.num)
    rows = run_sweep(base, points, vgg)
    ok = [r for r in rows if r.get("time_s") is not None]
    if not ok:
        raise InputError("every sweep point failed: " + "; ".join(r.get("error", "") for r in rows))
    res = write_sweep(ok, out, x="time_s", metrics=list(QUALITY), higher_is_better=HIGHER_IS_BETTER,
                      label="label", name="sweep",
                      title=f"stylization sweep: {what} ({device}{', random VGG' if vgg.is_random else ''})")
    cases = ([(500, 32, 24), (2000, 64, 48), (5000, 128, 96)] if args.quick else
             [(n, w, h) for n in (1000, 10000, 50000) for w, h in ((128, 96), (256, 192), (512, 384))])
    rrows = raster_rows(cases, torch.device(device), repeats=3 if args.quick else 10)
    rres = write_sweep(rrows, out, x="time_s", metrics=["max_abs_err", "mean_abs_err"],
                       higher_is_better={"max_abs_err": False, "mean_abs_err": False}, label="label",
                       name="raster", title=f"rasterizer: float32 Warp vs float64 reference ({device})")
    front = {m: [ok[i]["label"] for i in range(len(ok)) if res["front"][m][i]] for m in QUALITY}
    write_json(out / "sweep.json", {"scene": what, "device": device, "vgg": vgg.source, "vgg_random": vgg.is_random,
                                    "rows": rows, "pareto": front, "raster": rrows})
    print(f"\nsweep ({what}, {device}): {res['csv']} {res['png']}")
    for m in QUALITY:
        print(f"  Pareto front for {m}: {', '.join(front[m])}")
    print(f"rasterizer chart: {rres['csv']} {rres['png']}")
    if vgg.is_random:
        print("note: VGG is randomly initialized: style/content distances are not meaningful")
    return 0
