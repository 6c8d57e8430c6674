"""Which painting cells a run's view matches, and how textured they are (development aid, CPU).

python benchmarks/match_texture.py RUN PAINTING
View 0 of RUN/renders/ (stylized) and RUN/originals/ (un-stylized): each luminance relu3 cell's nearest painting cell
by cosine (the style term's NNFM match, the painting at the config's working size: the view's height x vgg_scale x
stroke_scale, 0.5 x 2), and the painting's luminance spread over 12 px around each matched cell, against the
painting's median; the share of the view's cells that match the painting's flattest fifth. Pretrained VGG-16 (the
default weights)."""
import sys

import cv2
import numpy as np
import torch

from tlvg_warp.losses import flatten_feats, load_vgg, luminance, resize_style
from tlvg_warp.losses.style import StyleFeatures, _topk_both


def image(path: str) -> torch.Tensor:
    return torch.from_numpy(cv2.imread(path)[..., ::-1].astype(np.float32) / 255.0).contiguous()


def main(run: str, painting: str) -> None:
    vgg = load_vgg(None, torch.device("cpu"))
    views = {"stylized": image(f"{run}/renders/view_000.png"), "un-stylized": image(f"{run}/originals/view_000.png")}
    h = views["stylized"].shape[0]
    style = cv2.imread(painting)[..., ::-1].astype(np.float32) / 255.0
    work = torch.from_numpy(resize_style(style, h)).contiguous()  # vgg_scale 0.5 x stroke_scale 2
    with torch.no_grad():
        sf = vgg(luminance(work), scale=1.0)
        fh, fw = sf.shape[-2:]
        y = luminance(work).numpy()[..., 0]
        var = cv2.blur(y * y, (12, 12)) - cv2.blur(y, (12, 12)) ** 2
        tex = np.sqrt(np.maximum(var, 0))[2::4, 2::4][:fh, :fw].reshape(-1)
        st = StyleFeatures(flatten_feats(sf))
        for name, im in views.items():
            a = flatten_feats(vgg(luminance(im), scale=0.5))
            idx = _topk_both(a, st, 1, need_cols=False)[0][:, 0].numpy()
            print(f"{name}: {a.shape[1]} cells; matched cells' spread median {np.median(tex[idx]):.3f} (the painting's "
                  f"{np.median(tex):.3f}); in the painting's flattest fifth: {np.mean(tex[idx] < np.quantile(tex, 0.2)):.0%}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
