"""How much of a scene's views comes from coarse splats: the share of all blend weight (Σ αT over the pixels of the
views) that splats wider than 8, 16, 32 and 64 px on screen contribute, before and after the stroke-size
refinement (train/refine.py). Runs on the CPU.

    python benchmarks/footprints.py SCENE.spz DATASET [--downscale F] [--every K] [--radius PX]
"""
import argparse

import torch

from tlvg_warp.io.datasets import load_dataset
from tlvg_warp.io.ply import load_ply
from tlvg_warp.train.refine import refine_to_radius, view_footprints


def shares(g, cams) -> list:
    r, w = view_footprints(g, cams)
    return [round(float(w[r > t].sum() / w.sum()), 3) for t in (8, 16, 32, 64)]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("data")
    ap.add_argument("--downscale", type=float, default=None)
    ap.add_argument("--every", type=int, default=6, help="every K-th view (the CPU is slow)")
    ap.add_argument("--radius", type=float, default=16.0, help="the refinement's radius in px (0: none)")
    a = ap.parse_args()
    g = load_ply(a.scene)
    cams = load_dataset(a.data, downscale=a.downscale).cameras[:: a.every]
    print(f"{a.scene}: {g.num} Gaussians, {len(cams)} views; share of blend weight from splats over 8/16/32/64 px")
    print("  as fitted:", shares(g, cams))
    if a.radius > 0:
        with torch.no_grad():
            g2, info = refine_to_radius(g, cams, a.radius, int(1.2 * g.num))
        print(f"  refined at {a.radius:g} px ({info}):", shares(g2, cams))


if __name__ == "__main__":
    main()
