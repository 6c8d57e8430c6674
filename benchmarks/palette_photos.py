"""A dataset's photos under the palette maps, as PNGs for benchmarks/grid.py (development aid, CPU, seconds).

    python benchmarks/palette_photos.py DATA PAINTING OUTDIR [--images images_8] [--downscale D] [--views 0,5]
        [--map arf] [--map sliced] [--map s05:sliced:0.05] ...

Each map (`name:mode[:smooth]`) is fitted on every photo of DATA, as `stylize` fits it (statistics over all pixels
of a capture; over the non-white pixels of a dataset with a white background, as the covered pixels stand in for
the un-stylized render's alpha here), with the painting at the photos' height, and the chosen views are written as
OUTDIR/NAME_vIDX.png beside the photos (photo_vIDX.png) and the painting (painting.png)."""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from tlvg_warp.io.datasets import dataset_background, load_dataset
from tlvg_warp.losses import resize_style
from tlvg_warp.losses.palette import palette_transfer

FLOOR = 0.004  # configs/tlvg.yaml's palette_floor (ARF's map only)


def save(path: Path, rgb) -> None:
    cv2.imwrite(str(path), (np.clip(np.asarray(rgb), 0, 1)[..., ::-1] * 255 + 0.5).astype(np.uint8))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data"), ap.add_argument("painting"), ap.add_argument("out")
    ap.add_argument("--images"), ap.add_argument("--downscale", type=float)
    ap.add_argument("--views", default="0", help="comma-separated view indices to write")
    ap.add_argument("--map", action="append", dest="maps", help="name:mode[:smooth] (default: arf and sliced)")
    a = ap.parse_args()
    ds = load_dataset(a.data, images=a.images, downscale=a.downscale)
    photos = [torch.as_tensor(np.asarray(ds.image(i))[..., :3]).float() for i in range(len(ds.names))]
    paint = cv2.imread(a.painting)
    if paint is None:
        raise SystemExit(f"error: {a.painting}: not an image OpenCV can read")
    work = torch.from_numpy(resize_style(paint[..., ::-1].astype(np.float32) / 255, photos[0].shape[0])).contiguous()
    white_bg = dataset_background(ds) == (1.0, 1.0, 1.0)  # a Blender scene's empty backdrop (the project's rule)
    cov = [(p < 0.99).any(-1, keepdim=True).float() for p in photos] if white_bg else None
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    views = [int(v) for v in a.views.split(",")]
    for v in views:
        save(out / f"photo_v{v}.png", photos[v])
    save(out / "painting.png", work)
    for spec in a.maps or ["arf:arf", "sliced:sliced"]:
        name, mode, *rest = spec.split(":")
        rec, _ = palette_transfer(photos, work, mode, coverage=cov, floor=FLOOR if mode == "arf" else 0.0,
                                  where="covered", smooth=float(rest[0]) if rest else 0.0,
                                  focus=float(rest[1]) if len(rest) > 1 else 0.0)
        for v in views:
            save(out / f"{name}_v{v}.png", rec[v])
        print(f"{name}: {len(photos)} photos, views {views} written")


if __name__ == "__main__":
    main()
