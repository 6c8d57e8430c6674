"""Host vs GPU timeline of our render (development aid): where the GPU waits for the host.

python3 benchmarks/profile_host.py [SCENE_SPEC] [fwd|fwd_bwd]   (SCENE_SPEC as `bench raster --scene`; default: random 1M)

A CUDA event is recorded at every mark (each stage function's entry and exit, each launch, each sort, the host
sync); per mark: host time since the step started, GPU time at which the event ran, and the gap. Where GPU - host
stays near zero the GPU was idle, waiting for the host to enqueue (host-bound); where it grows the host ran ahead.
Medians over 20 steps of view 0, after warm-up; then the host time per stage (self time, medians)."""
import statistics
import sys
import time

import torch

import tlvg_warp.autograd as autograd
import tlvg_warp.raster as raster
import tlvg_warp.renderer as renderer
from tlvg_warp.eval import bench_raster as br

dev = torch.device("cuda")
spec = sys.argv[1] if len(sys.argv) > 1 and sys.argv[1] not in ("fwd", "fwd_bwd") else None
mode = sys.argv[-1] if sys.argv[-1] in ("fwd", "fwd_bwd") else "fwd"
if spec:
    case = br.scene_case(spec, dev, max_views=1)
    g, cam = case.g, case.cams[0]
else:
    g, cam = br.random_scene(1_000_000, -4.0, 3, dev), br.bench_camera(1008, 756)
fwd, fwd_bwd, _ = br.ours_views(g)(cam)
step = fwd if mode == "fwd" else fwd_bwd
marks, on = [], [False]


def mark(label):
    if on[0]:
        e = torch.cuda.Event(enable_timing=True)
        e.record()
        marks.append((label, time.perf_counter(), e))


def wrap(mod, name, label=None):
    f = getattr(mod, name)

    def wrapped(*a, **k):
        tag = label(a) if label else name
        mark(f"{tag} >")
        r = f(*a, **k)
        mark(f"{tag} <")
        return r
    setattr(mod, name, wrapped)


# each name is wrapped where its callers look it up (the stages call launches, the autograd ops call stages)
for mod in (raster, autograd):
    wrap(mod, "fast_launch", lambda a: f"launch {a[0].key[:36]}")
wrap(raster, "sort_pairs_at", lambda a: f"sort {a[4]}")
wrap(raster, "bin_tiles")
for name in ("project", "count_intersections", "blend", "project_adjoint"):
    wrap(autograd, name)
for fn in (autograd.ShadeFn, autograd.RasterizeFn):  # the two autograd ops, forward and backward
    for phase in ("forward", "backward"):
        wrap(fn, phase, (lambda t: lambda a: t)(f"{fn.__name__}.{phase}"))
wrap(renderer, "check_inputs")
orig_item = torch.Tensor.item


def item(self):
    mark("sync (.item) >")
    r = orig_item(self)
    mark("sync (.item) <")
    return r


torch.Tensor.item = item
for _ in range(5):
    step()
torch.cuda.synchronize()
rows = {}
for it in range(20):
    marks.clear()
    on[0] = True
    mark("step start")
    step()
    mark("step end")
    on[0] = False
    torch.cuda.synchronize()
    h0, e0 = marks[0][1], marks[0][2]
    for i, (label, h, e) in enumerate(marks):
        rows.setdefault((i, label), []).append(((h - h0) * 1e6, e0.elapsed_time(e) * 1e3))
torch.Tensor.item = orig_item
print(f"{g.num:,} Gaussians, {cam.width}x{cam.height}, {mode}: median over 20 steps, microseconds since the step started")
print(f"{'mark':50s} {'host':>8s} {'GPU':>8s} {'GPU-host':>9s}")
for (i, label), v in sorted(rows.items()):
    h = statistics.median(x[0] for x in v)
    gg = statistics.median(x[1] for x in v)
    print(f"{label:50s} {h:8.0f} {gg:8.0f} {gg - h:9.0f}")
