"""Stage-by-stage timing of one render on the GPU (development aid; synchronizes between stages)."""
import sys
import time

import torch
import warp as wp

import tlvg_warp.ops as ops
from tlvg_warp import render
from tlvg_warp.eval.bench_raster import bench_camera, random_scene

n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
dev = torch.device("cuda")
times = {}


def timed(name, fn):
    def wrapper(*a, **k):
        torch.cuda.synchronize()
        t = time.perf_counter()
        r = fn(*a, **k)
        torch.cuda.synchronize()
        times[name] = times.get(name, 0.0) + time.perf_counter() - t
        return r
    return wrapper


ops.project = timed("project", ops.project)
ops.count_intersections = timed("count_intersections", ops.count_intersections)
ops.bin_tiles = timed("bin_tiles", ops.bin_tiles)
wp.utils.radix_sort_pairs = timed("  radix_sort", wp.utils.radix_sort_pairs)
orig_launch = wp.launch


def launch(kernel, *a, **k):
    return timed(f"  launch {kernel.key}", orig_launch)(kernel, *a, **k)


wp.launch = launch
g = random_scene(n, -4.0, 3, dev)
params = [t.detach().clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
from tlvg_warp import Gaussians  # noqa: E402

gp = Gaussians(*params)
cam = bench_camera(1008, 756)
up = torch.rand(756, 1008, 3, device=dev)
for _ in range(3):
    out = render(gp, cam)
    (out.color * up).sum().backward()
times.clear()
reps = 10
torch.cuda.synchronize()
t0 = time.perf_counter()
for _ in range(reps):
    out = timed("render (fwd total)", render)(gp, cam)
    timed("backward total", lambda: (out.color * up).sum().backward())()
total = time.perf_counter() - t0
print(f"N={n:,}, 1008x756, per iteration (ms), stages synchronized:")
for k, v in times.items():
    print(f"  {k:40s} {v / reps * 1e3:8.3f}")
print(f"  {'total':40s} {total / reps * 1e3:8.3f}")
vis = (out.radii > 0).sum().item()
print(f"visible {vis:,}")
