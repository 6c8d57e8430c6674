"""Mean luminance (BT.601), its spread and the mean chroma (CIELAB's |a,b|: how saturated; a washed-out render has
less than its colour target) over the pixels a run's un-stylized scene covers (alpha >= 0.5), beside
the painting's and those of ARF's map of the un-stylized renders (over all pixels and over the covered ones); and
the stylized renders' alpha there (rendered on black, so a thin render shows as low alpha, not as a lighter colour).

    python benchmarks/covered_luminance.py RUN_DIR [--views 8]

docs/study.md, "Why lego on a dark painting comes out pale", quotes it.
"""
from __future__ import annotations

import argparse

import cv2
import numpy as np
import torch

from tlvg_warp.config_io import read_yaml_mapping
from tlvg_warp.eval.engine import load_run, resolve_scene
from tlvg_warp.losses.color import luminance
from tlvg_warp.losses.palette import palette_transfer
from tlvg_warp.renderer import render


def line(name: str, px: torch.Tensor, alpha: torch.Tensor | None = None) -> str:  # px [N,3]
    y = luminance(px)[:, 0]  # [N]
    lab = cv2.cvtColor(np.ascontiguousarray(px.numpy(), np.float32)[:, None], cv2.COLOR_RGB2LAB)[:, 0]  # [N,3]
    chroma = float(np.hypot(lab[:, 1], lab[:, 2]).mean())
    s = (f"{name:30s} mean RGB {px.mean(0).numpy().round(3)} luminance {float(y.mean()):.3f} spread "
         f"{float(y.std()):.3f} chroma {chroma:.1f}")
    if alpha is not None:
        s += f" alpha mean {float(alpha.mean()):.3f} 10th percentile {float(alpha.quantile(0.1)):.3f}"
    return s


@torch.no_grad()
def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("--views", type=int, default=8)
    a = ap.parse_args(argv)
    run = load_run(a.run, max_views=a.views)
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    g_sty, g_un = run["gaussians"].to(device=dev), resolve_scene(run).to(device=dev)
    black = torch.zeros(3, device=dev)
    un = [render(g_un, c, black) for c in run["cameras"]]
    st = [render(g_sty, c, black) for c in run["cameras"]]
    covered = torch.cat([o.alpha.reshape(-1).cpu() >= 0.5 for o in un])

    def pixels(imgs):  # list of [H,W,3] -> [N,3] over the covered pixels
        return torch.cat([i.reshape(-1, 3).cpu() for i in imgs])[covered]
    painting = torch.from_numpy(run["painting"]).float()
    print(line("painting (every pixel)", painting.reshape(-1, 3)))
    print(line("un-stylized", pixels([o.color.clamp(0, 1) for o in un]),
               torch.cat([o.alpha.reshape(-1).cpu() for o in un])[covered]))
    print(line("stylized", pixels([o.color.clamp(0, 1) for o in st]),
               torch.cat([o.alpha.reshape(-1).cpu() for o in st])[covered]))
    on_white = [o.color + (1 - o.alpha[..., None]) for o in un]  # as the pipeline sees the photos' renders
    coverage = [o.alpha[..., None] for o in un]
    floor = float(read_yaml_mapping(run["dir"] / "config.yaml").get("palette_floor", 0.0))  # the run's own
    for where in ("all", "covered"):
        rec, _ = palette_transfer(on_white, painting.to(dev), "arf", coverage=coverage, floor=floor, where=where)
        print(line(f"ARF ({where}) of un-stylized", pixels(rec)))


if __name__ == "__main__":
    main()
