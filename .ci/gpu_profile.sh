#!/usr/bin/env bash
# One GPU call: CUDA correctness tests, then kernel time vs wall time for ours and gsplat (see profile_trace.py).
# Usage on the device: source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_profile.sh [N...]
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py 2>&1 | tail -3 | tee "$OUT/tests.txt"
for n in "${@:-1000000}"; do
  for peer in tlvg_warp gsplat; do
    python3 .ci/profile_trace.py "$n" "$peer" 2>&1 | grep -v "^Module\|Warning\|warn" | tee -a "$OUT/trace.txt"
  done
done
