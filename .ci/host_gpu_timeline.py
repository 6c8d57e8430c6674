"""Host vs GPU timeline of one synchronized render + backward (development aid). A CUDA event is recorded before
every Warp launch and around the ops stages; per event: host time since the step started, GPU time at which the
event executed, and their difference. A difference near zero means the GPU sat idle waiting for the host there
(host-bound); a large one means the host was ahead (GPU-bound)."""
import sys
import time

import torch
import warp as wp

import tlvg_warp.ops as ops
from tlvg_warp.eval.bench_raster import warm_step

n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
step = warm_step("tlvg_warp", n, torch.device("cuda"))
marks = []


def mark(label):
    if marks_on[0]:
        e = torch.cuda.Event(enable_timing=True)
        e.record()
        marks.append((label, time.perf_counter(), e))


marks_on = [False]
orig_launch = wp.launch


def launch(kernel, *a, **k):
    mark(f"launch {kernel.key[:40]}")
    return orig_launch(kernel, *a, **k)


wp.launch = launch
import tlvg_warp.renderer as renderer  # noqa: E402

for mod, name in [(ops, n) for n in ("kernels_for", "input_array", "camera_values", "project", "count_intersections",
                                     "shade", "bin_tiles", "blend", "attach_grads")] + [(renderer, "check_inputs")]:
    f = getattr(mod, name)

    def wrapped(*a, _f=f, _name=name, **k):
        mark(f"{_name} >")
        r = _f(*a, **k)
        mark(f"{_name} <")
        return r
    setattr(mod, name, wrapped)
orig_fwd = ops.RasterizeFn.forward


def fwd(ctx, *a):
    mark("forward >")
    return orig_fwd(ctx, *a)


ops.RasterizeFn.forward = staticmethod(fwd)
orig_bwd = ops.RasterizeFn.backward


def bwd(ctx, *grads):
    mark("backward >")
    r = orig_bwd(ctx, *grads)
    mark("backward <")
    return r


ops.RasterizeFn.backward = staticmethod(bwd)
rows = {}
for it in range(20):
    marks.clear()
    marks_on[0] = True
    mark("step start")
    step()
    mark("step end")
    marks_on[0] = False
    torch.cuda.synchronize()
    h0, e0 = marks[0][1], marks[0][2]
    for i, (label, h, e) in enumerate(marks):
        rows.setdefault((i, label), []).append(((h - h0) * 1e6, e0.elapsed_time(e) * 1e3))
print(f"N={n:,}: median over 20 steps, microseconds since the step started")
print(f"{'event':55s} {'host':>8s} {'GPU':>8s} {'GPU-host':>9s}")
for (i, label), v in sorted(rows.items()):
    h = sorted(x[0] for x in v)[len(v) // 2]
    gg = sorted(x[1] for x in v)[len(v) // 2]
    print(f"{label:55s} {h:8.0f} {gg:8.0f} {gg - h:9.0f}")
