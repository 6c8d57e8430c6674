"""How much of the painting's tonal range ARF's clamp takes from a run's photos (development aid, CPU).

python benchmarks/palette_clamp.py RUN PAINTING [FLOOR]
Every view of RUN/photos/, pooled, through ARF's map (`palette_floor` FLOOR, default 0.004; all pixels, as a capture
covers them) at the painting's working size (the views' height): the share of pixels the map puts under 0, the
luminance spread before and after the clamp to [0,1], and after `palette_map: arf_rank`; the painting's."""
import glob
import sys

import cv2
import numpy as np
import torch

from tlvg_warp.losses import resize_style
from tlvg_warp.losses.color import apply_color_transform, color_transfer
from tlvg_warp.losses.palette import palette_transfer

LUMA = np.array([0.299, 0.587, 0.114])


def main(run: str, painting: str, floor: float = 0.004) -> None:
    photos = [torch.from_numpy(cv2.imread(f)[..., ::-1].astype(np.float32) / 255.0).contiguous()
              for f in sorted(glob.glob(f"{run}/photos/view_*.png"))]
    if not photos:
        sys.exit(f"{run}/photos: no views")
    style = cv2.imread(painting)[..., ::-1].astype(np.float32) / 255.0
    work = torch.from_numpy(resize_style(style, photos[0].shape[0])).contiguous()
    _, m, t = color_transfer(photos, work, floor)
    raw = np.concatenate([apply_color_transform(p, m, t, clamp=False).numpy().reshape(-1, 3) for p in photos])
    rank = np.concatenate([r.numpy().reshape(-1, 3) for r in palette_transfer(photos, work, "arf_rank", floor=floor)[0]])
    print(f"{len(photos)} views; ARF puts {np.mean((raw < 0).any(1)):.1%} of the pixels under 0 on some channel")
    print(f"luminance spread: painting {(work.numpy().reshape(-1, 3) @ LUMA).std():.3f}; ARF before its clamp "
          f"{(raw @ LUMA).std():.3f}, after {(np.clip(raw, 0, 1) @ LUMA).std():.3f}; arf_rank {(rank @ LUMA).std():.3f}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], *(float(a) for a in sys.argv[3:4]))
