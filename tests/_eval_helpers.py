"""A stylization run folder written by hand (save_ply + JSON + PNGs from the demo scene), so the evaluation
tests do not depend on the stylization pipeline."""
import json
from pathlib import Path

import torch
import yaml

from tlvg_warp import render, save_ply
from tlvg_warp.fileio import write_image
from tlvg_warp.io.demo import builtin_painting, demo_scene
from tlvg_warp.types import SH_C0

BG = (1.0, 1.0, 1.0)


def cameras_json(cams):
    out = []
    for i, c in enumerate(cams):
        c2w = torch.linalg.inv(c.world_to_camera.double())
        out.append({"id": i, "img_name": c.name, "width": c.width, "height": c.height,
                    "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(), "fx": c.fx, "fy": c.fy})
    return out


def stylized_version(g, view_dependent=0.0, seed=0):
    """A "stylized" scene: colors inverted and tinted; ``view_dependent`` > 0 adds random degree-1 SH (colors
    that change with the viewing direction, i.e. multi-view inconsistent)."""
    rgb = (g.sh[:, 0] * SH_C0 + 0.5).clamp(0, 1)
    new = (1.0 - rgb) * torch.tensor([0.9, 0.8, 1.0])
    sh = torch.zeros(g.num, 4 if view_dependent else 1, 3)
    sh[:, 0] = (new - 0.5) / SH_C0
    if view_dependent:
        gen = torch.Generator().manual_seed(seed)
        sh[:, 1:] = view_dependent * torch.randn(g.num, 3, 3, generator=gen)
    out = g.clone()
    out.sh = sh
    return out


def make_run(root, n_views=7, width=48, height=36, view_dependent=0.0, metrics=None):
    root = Path(root)
    g, cams = demo_scene(n_views=n_views, width=width, height=height)
    sg = stylized_version(g, view_dependent)
    save_ply(sg, root / "stylized.ply")
    (root / "cameras.json").write_text(json.dumps(cameras_json(cams)))
    with torch.no_grad():
        for c in cams:
            write_image(root / "renders" / f"{c.name}.png", render(sg, c, BG).color)
            orig = render(g, c, BG).color
            write_image(root / "originals" / f"{c.name}.png", orig)
            write_image(root / "photos" / f"{c.name}.png", orig)
    p = builtin_painting().numpy()
    write_image(root / "style.png", p[::4, ::4])
    (root / "config.yaml").write_text(yaml.safe_dump({"style": str(root / "style.png"), "background": list(BG)}))
    m = {"time": {"pre": 1.0, "stylize": 2.0, "post": 0.5}, "gaussians_in": g.num, "gaussians_out": sg.num,
         "vgg_random": True}
    (root / "metrics.json").write_text(json.dumps(metrics if metrics is not None else m))
    return root, g, sg, cams
