"""Host time against wall time of one render (development aid, issue 15), without the marks of profile_host.py.

python3 .ci/host_wall.py SCENE_SPEC fwd|fwd_bwd [ITERATIONS]   (SCENE_SPEC as `bench raster --scene`; view 0)

Per iteration: the wall time with a device sync after it, and the host time until the call returned (the forward's
one sync included). Where the two are close the render is host-bound. Medians, after 20 warm-up iterations."""
import statistics
import sys
import time

import torch

from tlvg_warp.eval import bench_raster as br

dev = torch.device("cuda")
spec, mode = sys.argv[1], sys.argv[2]
iterations = int(sys.argv[3]) if len(sys.argv) > 3 else 300
case = br.scene_case(spec, dev, max_views=1)
fwd, fwd_bwd, _ = br.ours_views(case.g)(case.cams[0])
step = fwd if mode == "fwd" else fwd_bwd
for _ in range(20):
    step()
torch.cuda.synchronize()
walls, hosts = [], []
for _ in range(iterations):
    t0 = time.perf_counter()
    step()
    t1 = time.perf_counter()
    torch.cuda.synchronize()
    walls.append(time.perf_counter() - t0)
    hosts.append(t1 - t0)
print(f"{mode}: wall {statistics.median(walls) * 1e3:.3f} ms, host until return {statistics.median(hosts) * 1e3:.3f} ms"
      f" (median of {iterations})")
