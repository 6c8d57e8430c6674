"""Host-only timeline of one render forward+backward on CUDA (perf_counter marks at the ops, launches, sorts and
the harness; no CUDA events): where the host time of a step goes. `python3 .ci/host_gap.py PLY:DATASET:IMAGES ...`"""
import os, statistics, sys, time
import torch
from tlvg_warp import ops
from tlvg_warp.eval import bench_raster as br
from tlvg_warp.renderer import render
from tlvg_warp.types import Gaussians

marks = []
def mark(name):
    marks.append((name, time.perf_counter()))

def wrap(cls, meth, tag):
    orig = getattr(cls, meth)
    def w(ctx, *a):
        mark(tag + ">"); r = orig(ctx, *a); mark(tag + "<"); return r
    setattr(cls, meth, staticmethod(w))
wrap(ops.RasterizeFn, "forward", "raster.fwd"); wrap(ops.RasterizeFn, "backward", "raster.bwd")
wrap(ops.ShadeFn, "forward", "shade.fwd"); wrap(ops.ShadeFn, "backward", "shade.bwd")
of = ops.fast_launch
def fl(kernel, dim, args, device, block_dim=None, adj_args=None):
    k = kernel.key.rsplit("__", 1)[-1].replace("_kernel", "") + (" adj" if adj_args is not None else "")
    mark("L " + k + ">"); of(kernel, dim, args, device, block_dim, adj_args); mark("L " + k + "<")
ops.fast_launch = fl
for name in ("sort_pairs_at", "inclusive_scan_at"):
    o = getattr(ops, name)
    def make(o, name):
        def w(*a):
            mark(name + ">"); o(*a); mark(name + "<")
        return w
    setattr(ops, name, make(o, name))

EXTRA = os.environ.get("EXTRA", "") == "1"  # marks inside autograd: the loss's hook, an identity op on the color


class Marker(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a):
        return a.view_as(a)

    @staticmethod
    def backward(ctx, g):
        mark("sum and mul backward done")
        return g


dev = torch.device(os.environ.get("DEVICE", "cuda"))  # DEVICE=cpu: a smoke run
for spec in sys.argv[1:]:
    case = br.scene_case(spec, dev, max_views=1)
    g, cam = case.g, case.cams[0]
    gp = Gaussians(*br._leaf_params(g))
    up = torch.rand(cam.height, cam.width, 3, device=dev)
    def step():
        mark("start")
        out = render(gp, cam, depth=False)
        mark("render<")
        color = Marker.apply(out.color) if EXTRA else out.color
        loss = (color * up).sum()
        if EXTRA:
            loss.register_hook(lambda g: mark("engine starts (loss hook)"))
        mark("loss")
        del out
        loss.backward()
        mark("backward<")
        if dev.type == "cuda":
            torch.cuda.synchronize()
        mark("synced")
    if os.environ.get("MT", "1") == "0":  # backward on the calling thread
        torch.autograd.set_multithreading_enabled(False).__enter__()
    for _ in range(3):
        step()
    runs = []
    for _ in range(int(os.environ.get("STEPS", 200))):
        marks.clear()
        step()
        t0 = marks[0][1]
        runs.append([(n, (t - t0) * 1e6) for n, t in marks])
    print(f"== {spec.split(':')[0]} ({g.num} G, {cam.width}x{cam.height}): host us since step start, median of {len(runs)}")
    for i, (n, _) in enumerate(runs[0]):
        print(f"{n:40s} {statistics.median(r[i][1] for r in runs):8.1f}")
