"""What the stylize loss asks for with no scene in the way: the pixels of one photo optimized directly.

    python benchmarks/loss_on_pixels.py PHOTO PAINTING OUT.png [STEPS] [HEIGHT] [LR]

The terms and weights are configs/tlvg.yaml's image terms, read from it (NNFM on luminance, NNFM on RGB, content, chroma TV; the
painting at its working size, the render seen by VGG at x0.5); the flow, depth and geometry terms need a scene and are
left out. OUT.png shows the photo, its palette transfer (the starting point) and the result side by side. On a 2-core
CPU 300 steps at 378 rows take about 5 minutes.
"""
from __future__ import annotations

import sys

import cv2
import numpy as np
import torch

from tlvg_warp.losses import StyleLoss, color_transfer, content_loss, flatten_feats, load_vgg, luminance, resize_style
from tlvg_warp.stylize.config import load_config
from tlvg_warp.stylize.pipeline import chroma_tv_loss, content_scale


def read_rgb(path: str) -> torch.Tensor:
    img = cv2.imread(path)
    if img is None:
        raise SystemExit(f"{path}: not a readable image")
    return torch.from_numpy(cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255)


def main(photo_path: str, painting_path: str, out: str, steps: int = 300, height: int = 378, lr: float = 0.05) -> None:
    cfg = load_config("configs/tlvg.yaml")
    w = cfg.loss
    photo = read_rgb(photo_path)
    width = int(round(photo.shape[1] * height / photo.shape[0]))
    photo = torch.from_numpy(cv2.resize(photo.numpy(), (width, height), interpolation=cv2.INTER_AREA))
    vgg = load_vgg(device="cpu")
    painting = torch.from_numpy(resize_style(read_rgb(painting_path).numpy(), cfg.style_work_height(height)))
    with torch.no_grad():
        lum_target, rgb_target = flatten_feats(vgg(luminance(painting))), flatten_feats(vgg(painting))
        photo_feats = vgg.features_of([photo], cfg.vgg_scale)[0]
    w_content = w.w_content * content_scale(photo_feats, w.content_norm)
    start = color_transfer([photo], painting)[0][0]
    style_lum, style_rgb = StyleLoss(lum_target, kind=w.style_loss), StyleLoss(rgb_target, kind=w.style_loss)
    logits = torch.logit(start.clamp(0.02, 0.98)).clone().requires_grad_(True)  # pixels stay in (0, 1)
    opt = torch.optim.Adam([logits], lr=lr)
    for k in range(steps):
        img = torch.sigmoid(logits)
        a_lum, a_rgb = vgg.features_of([luminance(img), img], cfg.vgg_scale)
        loss = (w.style_scale * (w.w_style * style_lum(a_lum) + w.w_style_color * style_rgb(a_rgb))
                + w_content * content_loss(a_rgb, photo_feats) + w.w_chroma_tv * chroma_tv_loss(img))
        opt.zero_grad()
        loss.backward()
        opt.step()
        if k % 50 == 0 or k == steps - 1:
            print(f"step {k}: loss {loss.item():.4f}", flush=True)
    row = np.concatenate([photo.numpy(), start.numpy(), torch.sigmoid(logits).detach().numpy()], 1)
    cv2.imwrite(out, cv2.cvtColor((row * 255).clip(0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    a = sys.argv[1:]
    if len(a) < 3:
        raise SystemExit(__doc__)
    main(a[0], a[1], a[2], *(f(x) for f, x in zip((int, int, float), a[3:])))
