#!/usr/bin/env bash
# One GPU call: CUDA tests, the full raster benchmark, ours again with fast math off (the A/B of that switch),
# and kernel vs host time at 1M for ours and gsplat (where the host bounds a step: profile_host.py).
# Usage on the device, after setup:
#   bash .ci/gpu_ab.sh [--garden PATH]      (logs under $OUT)
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
echo "== tests on CUDA"
python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py 2>&1 | tail -3 | tee "$OUT/tests.txt"
echo "== benchmark (fast math on, the default)"
python3 -m tlvg_warp bench raster --out "$OUT/bench" "$@" 2>&1 | tee "$OUT/bench.log" | tail -13
echo "== ours with TLVG_WARP_FAST_MATH=0"
[ -n "${AB_NOFAST:-}" ] && TLVG_WARP_FAST_MATH=0 python3 -m tlvg_warp bench raster --peers tlvg_warp --out "$OUT/bench_nofast" "$@" 2>&1 \
  | tee "$OUT/bench_nofast.log" | tail -5
echo "== kernel vs host time at 1M"
for peer in tlvg_warp gsplat; do
  python3 .ci/profile_trace.py 1000000 "$peer" 2>&1 | grep -v "^Module\|Warning\|warn" | tee -a "$OUT/trace.txt"
done
