#!/usr/bin/env bash
# Where the fern numbers moved: the session's start (commit 173c8bd, carried in .gpu/old) against HEAD, and HEAD with
# the old always-on size rules, on one fitted fern, all scored by HEAD's evaluate (one ruler). nvidia-h200-x2.
set -uo pipefail
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"; R=/tmp/tlvg-runs; D=/tmp/tlvg-data; HEAD=$PWD
rm -rf /tmp/old && cp -r .gpu/old /tmp/old
ARGS="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg --quiet --overwrite --set orbit_frames=0"
CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 --iterations 7000 --out "$R/fern" --overwrite --quiet > "$OUT/fit.log" 2>&1
tail -n 1 "$OUT/fit.log"
( CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp stylize $ARGS --out $R/ab_head > "$OUT/head.log" 2>&1
  CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp stylize $ARGS --set density.size_rules=always --out $R/ab_always > "$OUT/always.log" 2>&1 ) &
( cd /tmp/old && CUDA_VISIBLE_DEVICES=1 PYTHONPATH=/tmp/tlvg-gpu/site:/tmp/old python3 -m tlvg_warp stylize $ARGS --out $R/ab_old > "$OUT/old.log" 2>&1 ) &
wait
for r in head always old; do tail -n 2 "$OUT/$r.log" | head -n 1; done
CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp evaluate $R/ab_head $R/ab_always $R/ab_old --max-views 10 --out $R/ab_eval > "$OUT/eval.log" 2>&1
grep -v "^Module" "$OUT/eval.log" | tail -n 22; cp $R/ab_eval/evaluation.json "$OUT/" 2>/dev/null
