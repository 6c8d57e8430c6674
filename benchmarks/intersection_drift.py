"""How far a view's tile-intersection count moves between two visits of a training run (development aid).

    python benchmarks/intersection_drift.py [stylize arguments]     (no arguments: the built-in demo)

The count sizes the key buffers of a render and is the one host read of a training step (``raster.count_intersections``
reads it with ``.item()``), which keeps a whole step out of one CUDA graph. A buffer sized from the view's count at its
last visit, with some headroom and checked a step later, would drop that read: this measures how much headroom the
training renders need. Runs ``stylize`` in this process, records (phase, view, count) for every training render, and
prints, per phase, the ratio of each visit's count to the same view's previous one: its largest value, its 99th
percentile, and the share of visits above 1.05, 1.10 and 1.25.
"""
from __future__ import annotations

import sys
from collections import defaultdict

import numpy as np

import tlvg_warp.autograd as autograd
import tlvg_warp.train.loop as loop
from tlvg_warp.cli import main

records = []  # (phase, view key, count)
current = {"view": None, "phase": None}


def _record_counts():
    real_count = autograd.count_intersections

    def counting(K, pr, width, height, all_tiles=False, capacity=None):
        order = real_count(K, pr, width, height, all_tiles)  # every render counted exactly (no capacity)
        if current["view"] is not None:  # a training render (the loop's; inside the autograd op grad mode is off)
            records.append((current["phase"], current["view"], order.total))
        return order

    autograd.count_intersections = counting


def _record_views():
    real_render = loop.render

    def render(g, cam, bg, **kw):
        current["view"] = (cam.name, cam.width, cam.height, tuple(cam.world_to_camera.reshape(-1).tolist()))
        try:
            return real_render(g, cam, bg, **kw)
        finally:
            current["view"] = None

    loop.render = render


def _phase_hook():
    real_phase_at = loop.Run.phase_at

    def phase_at(self, step):
        phase, k = real_phase_at(self, step)
        current["phase"] = phase.name
        return phase, k

    loop.Run.phase_at = phase_at


def report() -> None:
    by_phase = defaultdict(list)
    last = {}
    for phase, view, total in records:
        prev = last.get(view)
        if prev:
            by_phase[phase].append(total / prev)
        last[view] = total
    print(f"{len(records)} training renders over {len(last)} views")
    print("| phase | visits after the first | largest ratio | 99th percentile | > 1.05 | > 1.10 | > 1.25 |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for phase, r in by_phase.items():
        r = np.asarray(r)
        print(f"| {phase} | {len(r)} | {r.max():.3f} | {np.percentile(r, 99):.3f} | {np.mean(r > 1.05):.1%} | "
              f"{np.mean(r > 1.10):.1%} | {np.mean(r > 1.25):.1%} |")


if __name__ == "__main__":
    _record_counts()
    _record_views()
    _phase_hook()
    rc = main(["stylize", *sys.argv[1:]]) if len(sys.argv) > 1 else main(["stylize", "--out", "/tmp/tlvg-drift",
                                                                           "--overwrite", "--quiet"])
    report()
    sys.exit(rc)
