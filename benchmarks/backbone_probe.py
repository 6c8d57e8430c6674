"""Does the VGG-16 the style loss uses see brushstrokes? Per painting and per layer set, the NNFM distance (mean over
cells of min over the painting's cells of 1 - cos) from three images to the painting (at the style working height
256, luminance as the style term sees it):

- same: the painting's other half (left half against right half: the floor, same strokes, other content),
- blurred: the painting under a Gaussian blur of sigma 2 px (its composition and tones, no strokes),
- photo: photos of the scenes recoloured to the painting's palette (ARF's transfer), no strokes either.

stroke sensitivity = (blurred - same) / (photo - same): how far removing the strokes moves the painting, relative to
how far a photo is. Near 0, the layer cannot tell a painting from its blurred copy, so a loss on it cannot ask for
strokes. The pretrained HED backbone against the same network with random weights (seeded), on the CPU:

    python benchmarks/backbone_probe.py
"""
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.append(str(Path(__file__).resolve().parents[1]))  # after an installed package or the GPU scripts' source view
from field_agreement import DATA, PAINTINGS, read  # noqa: E402
from tlvg_warp.losses import color_transfer, luminance  # noqa: E402
from tlvg_warp.losses.vgg import load_vgg  # noqa: E402

torch.set_num_threads(2)
SETS = {"relu1_2": ("relu1_2",), "relu2_2": ("relu2_2",), "relu3 (the loss)": ("relu3_1", "relu3_2", "relu3_3"),
        "relu4_3": ("relu4_3",)}


def feats(net, img: np.ndarray, names) -> torch.Tensor:
    """[C, N] unit columns of the named layers (deeper layers upsampled to the first one's grid)."""
    with torch.no_grad():
        f = net.layers(luminance(torch.from_numpy(img)), names)
    maps = [f[n] for n in names]
    size = maps[0].shape[-2:]
    maps = [m if m.shape[-2:] == size else torch.nn.functional.interpolate(m, size=size, mode="bilinear") for m in maps]
    x = torch.cat(maps, 1)[0].flatten(1)
    return torch.nn.functional.normalize(x, dim=0)


def nnfm(a: torch.Tensor, s: torch.Tensor) -> float:
    return float((1 - (a.T @ s).max(1).values).mean())


def main() -> None:
    photos = [read(DATA / "scenes/beer_colmap/images" / f"{i:04d}.jpg", 256) for i in (0, 30)]
    fern = sorted(os.listdir(DATA / "scenes/fern_llff/images_8"))
    photos += [read(DATA / "scenes/fern_llff/images_8" / f, 256) for f in fern[::10][:2]]
    nets = {"HED (pretrained)": load_vgg("hed"), "random weights": load_vgg("random")}
    print("| painting | backbone | layers | same | blurred | photo | stroke sensitivity |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name in PAINTINGS:
        p = read(DATA / "styles" / name, 256)
        half = p.shape[1] // 2
        blurred = cv2.GaussianBlur(p, (0, 0), 2.0)
        rec = [r.numpy() for r in color_transfer([torch.from_numpy(x) for x in photos], torch.from_numpy(p))[0]]
        for bname, net in nets.items():
            for lname, names in SETS.items():
                ref = feats(net, np.ascontiguousarray(p[:, half:]), names)
                same = nnfm(feats(net, np.ascontiguousarray(p[:, :half]), names), ref)
                blur = nnfm(feats(net, np.ascontiguousarray(blurred[:, :half]), names), ref)
                photo = float(np.mean([nnfm(feats(net, r, names), ref) for r in rec]))
                # undefined where a photo is no farther than the painting's other half (the layer tells nothing apart)
                sens = f"{(blur - same) / (photo - same):.2f}" if photo - same > 0.005 else "n/a"
                print(f"| {name.split('.')[0]} | {bname} | {lname} | {same:.3f} | {blur:.3f} | {photo:.3f} | {sens} |",
                      flush=True)


if __name__ == "__main__":
    main()
