#!/usr/bin/env bash
# Fern 1008x756 fits side by side on the GPU: which setting drives the held-out PSNR (diagnosis).
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; R=/tmp/tlvg-runs; mkdir -p "$R" "$OUT"
D=.gpu/data/fern_llff
fit() { local name=$1; shift
  python3 -m tlvg_warp reconstruct $D --images images_4 --out "$R/v_$name" --overwrite --quiet "$@" > "$OUT/v_$name.log" 2>&1; }
fit noreset --iterations 7000 --set opacity_reset_interval=0 &
fit world01 --iterations 7000 --set max_world_size=0.1 &
fit sh0 --iterations 7000 --set sh_degree=0 &
fit it3000 --iterations 3000 &
wait
for f in "$OUT"/v_*.log; do echo "$(basename $f .log): $(grep -v CUDAEvent $f | tail -n 1)"; done
