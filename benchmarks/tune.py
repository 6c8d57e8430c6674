"""Stylize one scene with several config variants and paintings in ONE process, then score them with `evaluate`
(which adds its anchors: the un-stylized scene and the pasted painting), print one table per painting and write a picture montage.

    python benchmarks/tune.py --scene fern.spz --data fern_llff --styles a.jpg,b.jpg --out OUT \
        --variant tlvg: --variant abcgs:config=configs/abcgs.yaml --variant big:stroke_scale=2;loss.w_tv=0

A variant is ``name:key=value;key=value`` (``config=PATH`` picks the config file, default configs/tlvg.yaml;
other keys are `stylize --set` overrides). Finished runs (metrics.json present) are skipped, so a call cut
short is continued by the same command. ``--phase run`` only stylizes, ``--phase eval`` only scores.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT))  # after an installed package or the GPU scripts' source view

from tlvg_warp import cli  # noqa: E402

from tlvg_warp.eval.metrics import METRICS  # noqa: E402

KEYS = tuple(k for k in METRICS if k not in ("consistency_k5", "bytes"))  # the table's columns: evaluate's metrics


def parse_variant(text: str):
    name, _, rest = text.partition(":")
    cfg, sets = str(ROOT / "configs" / "tlvg.yaml"), []
    for kv in filter(None, (x.strip() for x in rest.split(";"))):
        k, _, v = kv.partition("=")
        if k == "config":
            cfg = str(ROOT / v) if not Path(v).is_absolute() else v
        else:
            sets.append(f"{k}={v}")
    return name, cfg, sets


def stylize(args, variants, styles):
    for style in styles:
        for name, cfg, sets in variants:
            out = Path(args.out) / Path(style).stem / name
            if (out / "metrics.json").is_file():
                continue
            data = ["--data", args.data] if args.data else []  # none: a splat file alone
            argv = ["stylize", "--scene", args.scene, *data, "--style", style, "--config", cfg, "--out", str(out),
                    "--overwrite", "--quiet", *sum((["--set", s] for s in sets), [])]
            if args.downscale:
                argv += ["--downscale", str(args.downscale)]
            if args.iterations:
                argv += ["--iterations", str(args.iterations)]
            t = time.perf_counter()
            rc = cli.main(argv)
            print(f"run {out}: rc {rc}, {time.perf_counter() - t:.1f} s", flush=True)


def evaluate(args, variants, styles):
    for style in styles:
        d = Path(args.out) / Path(style).stem
        runs = [d / n for n, _, _ in variants if (d / n / "metrics.json").is_file()]
        if not runs:
            continue
        t = time.perf_counter()
        cli.main(["evaluate", *map(str, runs), "--scene", args.scene, "--out", str(d / "evaluation"),
                  *(["--max-views", str(args.max_views)] if args.max_views else [])])
        print(f"evaluate {d.name}: {time.perf_counter() - t:.1f} s", flush=True)
        table(d / "evaluation" / "evaluation.json")


def _mean(v):
    if isinstance(v, dict):
        v = v.get("mean")
    return v


def table(path: Path):
    res = json.loads(path.read_text())
    keys = [k for k in KEYS if any(k in r["summary"] for r in res["runs"])]
    print(f"\n{path.parent.parent.name}\n| run | " + " | ".join(keys) + " |")
    for r in res["runs"]:
        cells = []
        for k in keys:
            v = _mean(r["summary"].get(k))
            cells.append("-" if v is None else f"{v:.4g}")
        print(f"| {r['name']} | " + " | ".join(cells) + " |")


def montage(args, variants, styles, view: int = 0, width: int = 504):
    import cv2

    rows = []
    for style in styles:
        d = Path(args.out) / Path(style).stem
        tiles = []
        names = [n for n, _, _ in variants if (d / n / "renders").is_dir()]
        for n in names[:1] + names:
            folder = d / n / ("renders" if tiles else "originals")
            files = sorted(folder.glob("*.png")) if folder.is_dir() else []
            if not files:
                continue
            im = cv2.imread(str(files[min(view, len(files) - 1)]))
            im = cv2.resize(im, (width, round(im.shape[0] * width / im.shape[1])), interpolation=cv2.INTER_AREA)
            cv2.putText(im, n if len(tiles) else "un-stylized", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 255), 2)
            tiles.append(im)
        p = cv2.imread(str(style))
        if p is not None and tiles:
            h = tiles[0].shape[0]
            tiles.append(cv2.resize(p, (round(p.shape[1] * h / p.shape[0]), h), interpolation=cv2.INTER_AREA))
        if tiles:
            h = tiles[0].shape[0]
            rows.append(np.concatenate([cv2.resize(t, (t.shape[1], h)) for t in tiles], 1))
    if rows:
        w = max(r.shape[1] for r in rows)
        rows = [np.pad(r, ((0, 0), (0, w - r.shape[1]), (0, 0))) for r in rows]
        cv2.imwrite(str(Path(args.montage)), np.concatenate(rows, 0), [cv2.IMWRITE_JPEG_QUALITY, 85])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--data", default="", help="the scene's photos (a dataset folder); none: a splat file alone, "
                    "stylized against its own renders from orbit cameras")
    ap.add_argument("--styles", required=True, help="comma-separated painting paths")
    ap.add_argument("--out", required=True)
    ap.add_argument("--variant", action="append", default=[], help="name:key=value;key=value")
    ap.add_argument("--downscale", type=float, default=0, help="render resolution divisor (0: the dataset's)")
    ap.add_argument("--iterations", type=int, default=0, help="override every variant's iterations (0: keep)")
    ap.add_argument("--phase", choices=["all", "run", "eval"], default="all")
    ap.add_argument("--montage", default=None, help="write a JPEG montage of view --view of every run here")
    ap.add_argument("--view", type=int, default=0)
    ap.add_argument("--max-views", type=int, default=0, help="evaluate the first N views only (0: all)")
    args = ap.parse_args()
    variants = [parse_variant(v) for v in args.variant]
    styles = [s for s in args.styles.split(",") if s]
    if args.phase in ("all", "run"):
        stylize(args, variants, styles)
    if args.phase in ("all", "eval"):
        evaluate(args, variants, styles)
    if args.montage:
        montage(args, variants, styles, args.view)
    missing = [f"{Path(st).stem}/{n}" for st in styles for n, _, _ in variants
               if not (Path(args.out) / Path(st).stem / n / "metrics.json").is_file()]
    if missing:  # a caller that retries (benchmarks/device_paint.sh) sees it; the finished runs stay and are skipped
        print(f"runs that did not finish: {', '.join(missing)}", file=sys.stderr)
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main())
