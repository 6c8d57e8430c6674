"""docs/gallery.jpg from the per-pair montages that `benchmarks/tune.py --montage` writes (one row per pair: the
un-stylized render, one tile per variant in the order they were given, the painting; tiles 504 px wide).

    python benchmarks/gallery.py [--show abcgs,tlvg,...] OUT.jpg PAIRS_DIR scene_painting:variant,variant,...:label [...]

Each argument picks a montage (PAIRS_DIR/scene_painting.jpg), the variants it was made with (in order), and the
row's label; the row shows un-stylized | sticker | the shown variants (default: abcgs, tlvg_before, tlvg, those
present) | painting.
"""
from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from tlvg_warp.eval.metrics import sticker

TILE_W = 504
ROW_H = 300
LABEL_H = 32  # tune.py writes each variant's name into its tile's top rows (y <= 24 at 0.7 scale): cut, the
#               gallery labels every column itself (a study's variant names are not the names readers know)
SHOWN = ("abcgs", "tlvg_before", "tlvg")
WHITE = 0.93  # a pixel darker than this in any channel is painted (a Blender scene's empty background renders white)


def object_mask(unstylized: np.ndarray) -> np.ndarray:
    """[H,W] bool: where the un-stylized tile (uint8 or float in [0,1], any channel order) shows the scene, grown by
    2 px so that the silhouette's anti-aliased edge counts as the object."""
    x = unstylized.astype(np.float32) / 255.0 if unstylized.dtype == np.uint8 else unstylized
    painted = (x.min(-1) < WHITE).astype(np.uint8)
    return cv2.dilate(painted, np.ones((5, 5), np.uint8)) > 0


def tiles_of(montage: np.ndarray, variants: list[str]) -> dict:
    h, w = montage.shape[:2]
    names = ["un-stylized", *variants]
    out = {n: montage[LABEL_H:, i * TILE_W:(i + 1) * TILE_W] for i, n in enumerate(names)}
    rest = montage[:, len(names) * TILE_W:]
    out["painting"] = rest[:, :np.flatnonzero(rest.reshape(h, -1, 3).max(axis=(0, 2)) > 0).max() + 1]
    view_h, view_w = out["un-stylized"].shape[:2]
    out["sticker"] = sticker(out["painting"], view_h, view_w).astype(np.uint8)
    return out


def row(montage: np.ndarray, variants: list[str], label: str, shown=SHOWN) -> np.ndarray:
    t = tiles_of(montage, variants)
    order = ["un-stylized", "sticker", *[v for v in shown if v in t], "painting"]
    scaled = [cv2.resize(t[n], (round(t[n].shape[1] * ROW_H / t[n].shape[0]), ROW_H), interpolation=cv2.INTER_AREA)
              for n in order]
    img = np.concatenate(scaled, 1)
    bar = np.zeros((26, img.shape[1], 3), np.uint8)
    x = 0
    for n, s in zip(order, scaled):
        text = label if n == "painting" else ("tlvg, previous config" if n == "tlvg_before" else n)
        cv2.putText(bar, text, (x + 6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
        x += s.shape[1]
    return np.concatenate([bar, img], 0)


def main(argv: list[str]) -> None:
    shown = SHOWN
    if argv and argv[0] == "--show":
        shown, argv = tuple(argv[1].split(",")), argv[2:]
    out, folder, specs = argv[0], Path(argv[1]), argv[2:]
    rows = []
    for spec in specs:
        name, variants, label = spec.split(":", 2)
        m = cv2.imread(str(folder / f"{name}.jpg"))
        if m is None:
            raise SystemExit(f"{folder / (name + '.jpg')}: not a readable montage")
        rows.append(row(m, variants.split(","), label, shown))
    w = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, w - r.shape[1]), (0, 0))) for r in rows]
    cv2.imwrite(out, np.concatenate(rows, 0), [cv2.IMWRITE_JPEG_QUALITY, 82])


if __name__ == "__main__":
    main(sys.argv[1:])
