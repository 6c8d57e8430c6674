"""The colour spread of view 0 against the painting's: Lab standard deviations over a montage tile's pixels (lego's
white background left out), from the per-pair montages `benchmarks/tune.py --montage` writes. A look at one view, not
a metric of `evaluate`.

    python benchmarks/colour_spread.py PAIRS_DIR tlvg_before,tlvg,sw,abcgs [--show tlvg,abcgs]

The variant names are the montage's tiles in the order the study ran them; the table shows the un-stylized tile, the
--show tiles and the painting.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from gallery import object_mask, tiles_of

BACKGROUND_SHARE = 0.2  # a view this much empty is an object on a background: its spread is the object's


def lab_std(im: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    lab = cv2.cvtColor(im.astype(np.float32) / 255.0, cv2.COLOR_BGR2LAB).reshape(-1, 3)  # [P,3]
    return (lab if mask is None else lab[mask.reshape(-1)]).std(axis=0)  # [3] L, a, b


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pairs")
    ap.add_argument("variants", help="the montage's tiles in order, comma-separated")
    ap.add_argument("--show", default="tlvg,abcgs")
    a = ap.parse_args()
    shown = ["un-stylized", *a.show.split(","), "painting"]
    print("| pair | L std: " + " / ".join(shown) + " | a std | b std |\n| --- | --- | --- | --- |")
    for path in sorted(Path(a.pairs).glob("*.jpg")):
        tiles = tiles_of(cv2.imread(str(path)), a.variants.split(","))
        painted = object_mask(tiles["un-stylized"])
        mask = painted if (~painted).mean() > BACKGROUND_SHARE else None  # a capture keeps its bright pixels
        s = {k: lab_std(tiles[k], None if k == "painting" else mask) for k in shown}
        scene, painting = path.stem.split("_", 1)
        cells = [" / ".join(f"{s[k][i]:.1f}" for k in shown) for i in range(3)]
        print(f"| {scene} x {painting} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
