"""GPU idle gaps inside one synchronized render + backward (development aid): torch.profiler's CUDA timeline
(Warp's launches included), the gaps between consecutive kernels, and which kernels they sit between."""
import sys
from collections import defaultdict

import torch
from torch.profiler import ProfilerActivity, profile

from tlvg_warp.eval.bench_raster import PEERS, bench_camera, random_scene

n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
which = sys.argv[2] if len(sys.argv) > 2 else "tlvg_warp"
g = random_scene(n, -4.0, 3, torch.device("cuda"))
_, step, _ = PEERS[which](g, bench_camera(1008, 756))
for _ in range(5):
    step()
torch.cuda.synchronize()
reps = 10
with profile(activities=[ProfilerActivity.CUDA]) as prof:
    for _ in range(reps):
        torch.cuda._sleep(1)  # a marker kernel launched the moment the step starts
        step()
        torch.cuda.synchronize()
evs = sorted((e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA),
             key=lambda e: e.time_range.start)
steps = []
for e in evs:  # each step starts at its marker (the gap after it is the host's time to the first launch)
    if "sleep" in e.name or "spin" in e.name:
        steps.append([])
    if steps:
        steps[-1].append(e)
gaps = defaultdict(list)
spans, busy = [], []
for s in steps:
    spans.append(s[-1].time_range.end - s[0].time_range.start)
    busy.append(sum(e.time_range.end - e.time_range.start for e in s))
    for a, b in zip(s, s[1:]):
        gap = b.time_range.start - max(a.time_range.end, a.time_range.start)
        if gap > 3:
            gaps[(a.name[:48], b.name[:48])].append(gap)
k = len(steps)
print(f"{which} N={n:,}: {k} steps, GPU span {sum(spans) / k / 1e3:.3f} ms, kernels {sum(busy) / k / 1e3:.3f} ms")
for (a, b), v in sorted(gaps.items(), key=lambda kv: -sum(kv[1]))[:14]:
    print(f"  gap {sum(v) / k:7.1f} us/step  after {a}  before {b}")
