"""Is the stroke field the flow terms train toward the one the ruler scores against? Per scene x painting, on photos
in place of un-stylized renders (the photo sets of field_agreement.py), the agreement (coherence-weighted mean
cos 2Δθ, 1 = the same field) with `evaluate`'s common field (RGB features, nearest cell, the painting at 256 rows) of:

- training's field: luminance features of the view at x0.5 matched top-k to the painting at its working height
  (view height x vgg_scale 0.5 x stroke_scale 2), the painting's field taken at that height;
- the same match with the painting's field taken at 256 rows.

On the CPU:

    python benchmarks/field_vs_ruler.py starry_night.jpg shipwreck.jpg
"""
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.append(str(Path(__file__).resolve().parents[1]))  # after an installed package or the GPU scripts' source view
from field_agreement import DATA, VGG_SCALE, VIEW_HEIGHT, agreement, read, scene_photos  # noqa: E402
from tlvg_warp.eval.refs import common_field  # noqa: E402
from tlvg_warp.losses import (field_at_cells, flatten_feats, luminance, matched_view_field, resize_style,  # noqa: E402
                              stroke_field)
from tlvg_warp.losses.vgg import load_vgg  # noqa: E402

RULER_HEIGHT = 256  # the painting's working height in `evaluate` (SPEC §3)


def main(paintings: list[str]) -> None:
    torch.set_num_threads(2)
    vgg = load_vgg("hed", device="cpu")
    for painting in paintings:
        full = read(DATA / "styles" / painting, 1024)
        w256 = resize_style(full, RULER_HEIGHT)
        with torch.no_grad():
            sf256 = vgg(torch.from_numpy(w256))
        ruler_cells = field_at_cells(stroke_field(w256)[2], tuple(sf256.shape[-2:]))
        ruler_feats = torch.nn.functional.normalize(flatten_feats(sf256).double(), dim=0)
        for scene in VIEW_HEIGHT:
            work = resize_style(full, VIEW_HEIGHT[scene])  # x vgg_scale 0.5 x stroke_scale 2
            with torch.no_grad():
                f = vgg(luminance(torch.from_numpy(work)), scale=1.0)  # [1,768,hc,wc]
            sf, shape = flatten_feats(f), tuple(f.shape[-2:])
            cells_work = torch.from_numpy(field_at_cells(stroke_field(work)[2], shape))
            cells_256 = torch.from_numpy(field_at_cells(stroke_field(w256)[2], shape))
            at_work, at_256 = [], []
            for photo in scene_photos(scene):
                ruler = torch.from_numpy(common_field(vgg, photo.numpy(), full, ruler_cells, ruler_feats))
                at_work.append(agreement(matched_view_field(vgg, photo, sf, cells_work, VGG_SCALE), ruler))
                at_256.append(agreement(matched_view_field(vgg, photo, sf, cells_256, VGG_SCALE), ruler))
            print(f"{scene} x {painting}: training's field against the ruler's {np.mean(at_work):.3f}; with the "
                  f"painting's field at {RULER_HEIGHT} rows {np.mean(at_256):.3f} ({len(at_work)} photos)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
