#!/usr/bin/env bash
# Cold-start compile time on the GPU (empty Warp kernel cache): first render per scalar type.
set -uo pipefail
WARP_CACHE_PATH=/tmp/tlvg-cold-$$ python3 - <<'PY' 2>&1 | grep -v "^Module\|^Warp\|CUDA Tool\|Devices\|cpu\"\|cuda:0\|Kernel cache\|tlvg-cold"
import time, torch
t0 = time.perf_counter()
from tlvg_warp import render
from tlvg_warp.eval.bench_raster import bench_camera, random_scene
for dt in (torch.float32, torch.float64):
    g = random_scene(1000, -3.0, 3, "cuda").to(dtype=dt)
    g = type(g)(*[t.requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)])
    t = time.perf_counter(); out = render(g, bench_camera(64, 48)); out.color.sum().backward(); torch.cuda.synchronize()
    print(f"first render+backward cuda {dt}: {time.perf_counter() - t:.2f} s (includes compiling the modules)")
print(f"total cold start incl. imports {time.perf_counter() - t0:.2f} s")
PY
