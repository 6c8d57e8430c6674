"""Does the palette transfer move the stroke field? Per scene x painting, the field matched from each photo and from
its palette-recoloured version (the pre-process's target) are compared: coherence-weighted mean cos 2(θa−θb) of the
two doubled-angle fields (1 = the same field). The match as training makes it: luminance features of the view at
x0.5 against the painting at its working height (view height x vgg_scale 0.5 x stroke_scale 2), top-k cells. On the
CPU, from ../shared/data (SHARED overrides ../shared):

    python benchmarks/field_agreement.py
"""
import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.append(str(Path(__file__).resolve().parents[1]))  # after an installed package or the GPU scripts' source view
from tlvg_warp.io.images import read_image  # noqa: E402
from tlvg_warp.losses import (  # noqa: E402
    color_transfer, field_at_cells, flatten_feats, luminance, matched_view_field, resize_style, stroke_field)
from tlvg_warp.losses.vgg import load_vgg  # noqa: E402

DATA = Path(os.environ.get("SHARED", "../shared")) / "data"
PAINTINGS = ("starry_night.jpg", "shipwreck.jpg", "starry_night_over_the_rhone.png", "monet_san_giorgio.jpg")
VIEW_HEIGHT = {"beer": 640, "fern": 378}  # the study's view heights
VGG_SCALE = 0.5  # the view's scale before VGG in training (configs/tlvg.yaml's vgg_scale)


def read(path: Path, height: int) -> np.ndarray:
    """An image as float RGB [height, w, 3], aspect kept (INTER_AREA)."""
    return np.ascontiguousarray(resize_style(read_image(path)[..., :3], height))


def scene_photos(scene: str) -> list:
    if scene == "beer":
        files = [DATA / "scenes/beer_colmap/images" / f"{i:04d}.jpg" for i in range(0, 60, 10)]
    else:
        folder = DATA / "scenes/fern_llff/images_4"
        files = [folder / f for f in sorted(os.listdir(folder))[::4]]
    return [torch.from_numpy(read(f, VIEW_HEIGHT[scene])) for f in files]


def agreement(a: torch.Tensor, b: torch.Tensor) -> float:
    """Coherence-weighted mean cos 2Δθ of two doubled-angle fields [H,W,2]."""
    a, b = a.double(), b.double()
    return float((a * b).sum() / (a.norm(dim=-1) * b.norm(dim=-1)).sum())


def main() -> None:
    torch.set_num_threads(2)
    vgg = load_vgg("hed", device="cpu")
    for painting in PAINTINGS:
        for scene in VIEW_HEIGHT:
            photos = scene_photos(scene)
            work = read(DATA / "styles" / painting, VIEW_HEIGHT[scene])  # x vgg_scale 0.5 x stroke_scale 2
            with torch.no_grad():
                sf = vgg(luminance(torch.from_numpy(work)), scale=1.0)
            cells = torch.from_numpy(field_at_cells(stroke_field(work)[2], tuple(sf.shape[-2:])))
            recoloured = color_transfer(photos, torch.from_numpy(work))[0]
            sf = flatten_feats(sf)
            scores = [agreement(matched_view_field(vgg, p, sf, cells, VGG_SCALE),
                                matched_view_field(vgg, r, sf, cells, VGG_SCALE)) for p, r in zip(photos, recoloured)]
            print(f"{scene} x {painting}: original against recoloured field {np.mean(scores):.3f} "
                  f"({len(scores)} photos)", flush=True)


if __name__ == "__main__":
    main()
