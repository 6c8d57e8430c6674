"""How much of a run's Gram style distance comes from outside the object? For a scene on an empty background (a
Blender scene), `evaluate`'s Gram distance is taken over the whole view, so splats frayed or strayed into the white
background add texture that lowers it. Per pair, on one view (the study's montage tile, as `benchmarks/tune.py
--montage` writes it), each run's Gram distance to the painting (the metric's own code, at `evaluate`'s height 256):

- whole: the tile as rendered,
- object only: every pixel outside the un-stylized object (its non-white pixels, dilated by 2 px) set to white in
  every run alike, so only what is painted on the object counts,
- outside: the share of the view that is non-white outside the un-stylized object (frayed or strayed splats).

    python benchmarks/gram_background.py PAIRS_DIR VARIANTS RUNS PAIR [PAIR ...] [--styles DIR]

VARIANTS: the montage's variant order (comma-separated, after the un-stylized tile); RUNS: those to score; PAIR:
scene_painting (the montage PAIRS_DIR/PAIR.jpg; the painting STYLES/painting.*). One JPEG view per pair: an
indication of where the distance comes from, not a replacement for `evaluate`'s per-view means.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from gallery import WHITE, object_mask, tiles_of  # noqa: E402  (benchmarks/gallery.py: the montage's tiles)
from tlvg_warp.eval import DEFAULT_EVAL_HEIGHT as EVAL_HEIGHT  # evaluate's style height
from tlvg_warp.eval import metrics as M
from tlvg_warp.losses import load_vgg


def read_bgr(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise SystemExit(f"{path}: not an image")
    return img


def to_rgb(bgr: np.ndarray) -> np.ndarray:
    return bgr[..., ::-1].astype(np.float32) / 255.0


def gram(net, img: np.ndarray, painting_grams: dict) -> float:
    return M.style_gram(M.vgg_feats(net, M.resize_to_height(img, EVAL_HEIGHT))["grams"], painting_grams)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("pairs_dir")
    ap.add_argument("variants")
    ap.add_argument("runs")
    ap.add_argument("pairs", nargs="+")
    ap.add_argument("--styles", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "styles"))
    args = ap.parse_args()
    runs = args.runs.split(",")
    net = load_vgg("hed", device="cpu")
    print("| pair | " + " | ".join(f"{r}: whole / object only / outside" for r in runs) + " |")
    print("|" + " --- |" * (len(runs) + 1))
    for pair in args.pairs:
        tiles = {n: to_rgb(t) for n, t in tiles_of(read_bgr(Path(args.pairs_dir) / f"{pair}.jpg"),
                                                   args.variants.split(",")).items()}
        painting_name = pair.split("_", 1)[1]
        painting = to_rgb(read_bgr(next(Path(args.styles).glob(f"{painting_name}.*"))))
        pg = M.vgg_feats(net, M.resize_to_height(painting, EVAL_HEIGHT))["grams"]
        obj = object_mask(tiles["un-stylized"])
        cells = []
        for r in runs:
            t = tiles[r]
            inside = np.where(obj[..., None], t, 1.0).astype(np.float32)
            outside = float(((t.min(-1) < WHITE) & ~obj).mean())
            cells.append(f"{gram(net, t, pg):.3f} / {gram(net, inside, pg):.3f} / {100 * outside:.2f}%")
        print(f"| {pair} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
