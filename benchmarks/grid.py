"""A labelled picture grid from image files (the README's controls grid), each tile resized to one width.

    python benchmarks/grid.py OUT.jpg --cols 5 [--width 504] "label=path.png" ... ["=" for an empty cell]

Tiles fill the rows left to right; each gets its label in a white band above it; a tile of another aspect (the
painting) keeps its aspect at the row's height, centred in its cell.
"""
from __future__ import annotations

import argparse

import cv2
import numpy as np

BAND = 34  # the label band's height in pixels


def read(path: str) -> np.ndarray:
    im = cv2.imread(path)
    if im is None:
        raise SystemExit(f"error: {path}: not an image OpenCV can read")
    return im


def tile(path: str, label: str, width: int, height: int) -> np.ndarray:
    cell = np.full((BAND + height, width, 3), 255, np.uint8)
    if path:
        im = read(path)
        s = min(width / im.shape[1], height / im.shape[0])
        im = cv2.resize(im, (round(im.shape[1] * s), round(im.shape[0] * s)), interpolation=cv2.INTER_AREA)
        y, x = BAND + (height - im.shape[0]) // 2, (width - im.shape[1]) // 2
        cell[y:y + im.shape[0], x:x + im.shape[1]] = im
    cv2.putText(cell, label, (8, BAND - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.75, (0, 0, 0), 2, cv2.LINE_AA)
    return cell


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("tiles", nargs="+", help="label=path (an empty path leaves the cell blank)")
    ap.add_argument("--cols", type=int, default=4)
    ap.add_argument("--width", type=int, default=504)
    a = ap.parse_args()
    pairs = [t.split("=", 1) for t in a.tiles]
    first = read(next(p for _, p in pairs if p))
    height = round(first.shape[0] * a.width / first.shape[1])  # the first image's aspect sets the rows' height
    cells = [tile(p, label, a.width, height) for label, p in pairs]
    cells += [tile("", "", a.width, height)] * (-len(cells) % a.cols)
    rows = [np.concatenate(cells[i:i + a.cols], 1) for i in range(0, len(cells), a.cols)]
    cv2.imwrite(a.out, np.concatenate(rows, 0), [cv2.IMWRITE_JPEG_QUALITY, 88])


if __name__ == "__main__":
    main()
