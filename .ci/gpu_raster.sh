#!/usr/bin/env bash
# One GPU call (see ../shared/gpu/README.md): CUDA correctness, cold-start compile time, rasterizer benchmark.
# Usage on the device: source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_raster.sh   (logs under $OUT)
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
echo "== cold start (empty Warp kernel cache)"
WARP_CACHE_PATH=/tmp/tlvg-cold-$$ python3 - <<'PY' 2>&1 | tee "$OUT/cold_start.txt"
import time, torch
t0 = time.perf_counter()
from tlvg_warp import render
from tlvg_warp.eval.bench_raster import bench_camera, random_scene
for dev in ("cuda", "cpu"):
    for dt in ((torch.float32, torch.float64) if dev == "cuda" else ()):
        g = random_scene(1000, -3.0, 3, dev).to(dtype=dt)
        t = time.perf_counter(); render(g, bench_camera(64, 48)); torch.cuda.synchronize()
        print(f"first render {dev} {dt}: {time.perf_counter() - t:.2f} s (includes compiling the module)")
print(f"total cold start {time.perf_counter() - t0:.2f} s")
PY
echo "== tests on CUDA"
python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py 2>&1 | tail -4 | tee "$OUT/tests.txt"
echo "== stage profile"
python3 .ci/profile_raster.py 1000000 2>&1 | grep -v Module | tee "$OUT/profile.txt"
echo "== benchmark"
python3 -m tlvg_warp bench raster --out "$OUT/bench" "$@" 2>&1 | tee "$OUT/bench.log" | tail -16
