"""GPU kernel time vs wall time of one render + backward (development aid).

Prints, per iteration: wall time (unsynchronized loop, median), the summed GPU time of every kernel and memcpy
(torch.profiler / CUPTI sees Warp's launches too), and the top kernels. wall >> GPU sum means the host
(Python, launches, syncs) bounds the step, not the kernels."""
import statistics
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile

from tlvg_warp.eval.bench_raster import warm_step

n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
which = sys.argv[2] if len(sys.argv) > 2 else "tlvg_warp"
step = warm_step(which, n, torch.device("cuda"))
if which == "tlvg_warp":  # the sizes the radix sorts see (depth order over N, then the tile keys)
    import warp as wp

    sizes, sort = [], wp.utils.radix_sort_pairs
    wp.utils.radix_sort_pairs = lambda k, v, count, *a: (sizes.append(count), sort(k, v, count, *a))[1]
    step()
    wp.utils.radix_sort_pairs = sort
    print(f"radix sort sizes per render: {sizes}")
torch.cuda.synchronize()
torch.cuda.reset_peak_memory_stats()
base = torch.cuda.memory_allocated()
step()
torch.cuda.synchronize()
print(f"torch peak above the resident scene: {(torch.cuda.max_memory_allocated() - base) / 2**20:.0f} MiB")
walls = []
for _ in range(5):
    torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(10):
        step()
    torch.cuda.synchronize()
    walls.append((time.perf_counter() - t) / 10)
cpu0 = time.process_time()
for _ in range(10):
    step()
torch.cuda.synchronize()
cpu = (time.process_time() - cpu0) / 10
reps = 10
with profile(activities=[ProfilerActivity.CUDA]) as prof:
    for _ in range(reps):
        step()
    torch.cuda.synchronize()
evs = [e for e in prof.key_averages() if e.device_time_total > 0]
tot = sum(e.device_time_total for e in evs) / reps / 1e3
print(f"{which} N={n:,}: wall {statistics.median(walls) * 1e3:.3f} ms/it, host CPU {cpu * 1e3:.3f} ms/it, "
      f"GPU kernels+copies {tot:.3f} ms/it")
for e in sorted(evs, key=lambda e: -e.device_time_total)[:18]:
    print(f"  {e.device_time_total / reps / 1e3:7.3f} ms  x{e.count // reps:<3d} {e.key[:90]}")
