"""How much multi-view error (k1) a texture that cannot be view-inconsistent costs on a run's scene: the un-stylized
scene with each Gaussian's colour moved by its own luminance offset (amplitude x N(0, 1), fixed per Gaussian, so
every view shows the same texture on the same surface), scored by `evaluate`'s own k1 and detail, beside the run.

    python benchmarks/k1_texture_control.py RUN_DIR [--views 12] [--amplitudes 0,0.05,0.1,0.2,0.3] [--grey]

A stylization's k1 above the controls' at the same detail is inconsistency of its own; at or under them, it is what
the scene's depth and the metric's resampling charge any texture of that strength. ``--grey`` paints the
un-stylized and the stylized Gaussians one grey first (the texture alone on each geometry) and adds the share of
the pixels the un-stylized scene covers where a view's alpha is under 0.95: what the geometry alone costs.
docs/study.md quotes it.
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import torch

from tlvg_warp.eval.engine import auto_eval_height, load_run, resolve_scene
from tlvg_warp.eval.metrics import interval
from tlvg_warp.eval.refs import build_references, score_views, stylized_views
from tlvg_warp.losses.vgg import load_vgg
from tlvg_warp.types import SH_C0


def jittered(g, amplitude: float, seed: int = 0):
    """``g`` with every Gaussian's band-0 colour moved by ``amplitude`` x z (z ~ N(0, 1), one per Gaussian, the same
    on R, G and B: a luminance offset that travels with the Gaussian into every view)."""
    z = torch.randn(g.num, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    sh = g.sh.clone()
    sh[:, 0] += (amplitude * z / SH_C0).to(sh.dtype).to(sh.device)[:, None]
    return dataclasses.replace(g, sh=sh)


def grey(g):
    """``g`` with every Gaussian's colour 0.5 on every channel and no view dependence."""
    return dataclasses.replace(g, sh=torch.zeros_like(g.sh))


def thin_share(views, refs) -> float:
    """Share of the pixels the un-stylized scene covers (alpha >= 0.5) where ``views``' alpha is under 0.95."""
    n = d = 0
    for v, b in zip(views, refs.base):
        cov = np.asarray(b["alpha"]) >= 0.5
        n += int((np.asarray(v["alpha"])[cov] < 0.95).sum())
        d += int(cov.sum())
    return n / max(d, 1)


def summary(per: dict) -> str:
    def mean(k):  # `evaluate`'s own mean over views (NaN views dropped)
        return interval(per[k])["mean"]
    return f"k1 {mean('consistency_k1'):.4f}  detail {mean('detail'):.3f}  detail inside {mean('detail_inside'):.3f}"


@torch.no_grad()
def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--amplitudes", default="0,0.05,0.1,0.2,0.3")
    ap.add_argument("--grey", action="store_true", help="the texture on one grey, on both geometries")
    a = ap.parse_args(argv)
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    run = load_run(a.run, max_views=a.views)
    net = load_vgg("random", device=dev)  # k1 and detail need no features
    g0 = resolve_scene(run).to(device=dev)
    refs = build_references(g0, run["cameras"], run["background"], run["painting"], run["photos"], net, device=dev,
                            eval_height=auto_eval_height(run["cameras"]), log=lambda _m: None)  # as `evaluate`
    print(f"{'the run':28s} {summary(score_views(*stylized_views(run['gaussians'].to(device=dev), refs, dev), refs, net))}")
    amps = [float(x) for x in a.amplitudes.split(",")]
    if a.grey:
        for name, g in (("un-stylized", g0), ("stylized", run["gaussians"].to(device=dev))):
            views, a2 = stylized_views(grey(g), refs, dev)
            print(f"{name} geometry: alpha under 0.95 on {thin_share(views, refs):.2%} of the covered pixels")
            for amp in amps:
                per = score_views(*stylized_views(jittered(grey(g), amp), refs, dev), refs, net)
                print(f"{name + ' grey, jitter ' + format(amp, '.2f'):28s} {summary(per)}")
        return
    for amp in amps:
        per = score_views(*stylized_views(jittered(g0, amp), refs, dev), refs, net)
        print(f"{'un-stylized, jitter ' + format(amp, '.2f'):28s} {summary(per)}")


if __name__ == "__main__":
    main()
