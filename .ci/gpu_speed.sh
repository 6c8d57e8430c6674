#!/usr/bin/env bash
# Issue 15, one GPU call: fit fern (and beer), profile the rasterizers on the fitted scenes against gsplat, time a
# 3000-iteration fern stylization with the pretrained backbone, and profile a short one.
# On the device:  source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_speed.sh [fit] [raster] [stylize] [profile]
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt
R=/tmp/tlvg-runs; mkdir -p "$R"; D=/tmp/tlvg-data
nvidia-smi --query-gpu=name --format=csv,noheader
for job in "$@"; do
  case "$job" in
    fit) [ -f "$R/fern/point_cloud.ply" ] || /usr/bin/time -f "fern fit wall %e s" python3 -m tlvg_warp reconstruct $D/fern_llff \
           --images images_4 --iterations 7000 --out "$R/fern" --overwrite --quiet > "$OUT/fern_fit.log" 2>&1
         tail -n 3 "$OUT/fern_fit.log"
         [ -f "$R/beer/point_cloud.ply" ] || /usr/bin/time -f "beer fit wall %e s" python3 -m tlvg_warp reconstruct $D/beer_colmap \
           --downscale 2 --iterations 7000 --out "$R/beer" --overwrite --quiet > "$OUT/beer_fit.log" 2>&1
         tail -n 3 "$OUT/beer_fit.log";;
    raster) python3 .ci/profile_fitted.py "$R/fern/point_cloud.ply" $D/fern_llff images_4 2>&1 | grep -v "^Module" | tee "$OUT/raster_fern.txt"
            python3 .ci/profile_fitted.py "$R/beer/point_cloud.ply" $D/beer_colmap images 2>&1 | grep -v "^Module" | tee "$OUT/raster_beer.txt";;
    stylize) /usr/bin/time -f "fern stylize 3000 wall %e s" python3 -m tlvg_warp stylize --scene "$R/fern/point_cloud.ply" \
               --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg --out "$R/fern_tlvg" --overwrite --quiet \
               > "$OUT/fern_stylize.log" 2>&1; tail -n 4 "$OUT/fern_stylize.log"
             python3 -c "import json; m=json.load(open('$R/fern_tlvg/metrics.json')); print({k: m[k] for k in m if 'time' in k or 'gaussians' in k})";;
    styleval) # tlvg (timed), tlvg with the FAST match reused for 4 of a view's steps, abcgs; then one ruler for all three
             for v in "tlvg:configs/tlvg.yaml:" "tlvg_r4:configs/tlvg.yaml:loss.fast_refresh=4" "abcgs:configs/abcgs.yaml:"; do
               IFS=: read -r name cfg set <<< "$v"
               /usr/bin/time -f "fern $name 3000 wall %e s" python3 -m tlvg_warp stylize --scene "$R/fern/point_cloud.ply" \
                 --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg --config $cfg ${set:+--set $set} \
                 --out "$R/fern_$name" --overwrite --quiet > "$OUT/fern_$name.log" 2>&1; tail -n 3 "$OUT/fern_$name.log"
               python3 -c "import json; m=json.load(open('$R/fern_$name/metrics.json')); print({k: m[k] for k in m if 'time' in k or 'gaussians' in k or 'stage' in k})"
             done
             python3 -m tlvg_warp evaluate "$R/fern_tlvg" "$R/fern_tlvg_r4" "$R/fern_abcgs" --max-views 6 --out "$R/fern_eval" \
               > "$OUT/fern_eval.log" 2>&1; tail -n 30 "$OUT/fern_eval.log"; cp "$R/fern_eval/evaluation.json" "$OUT/" 2>/dev/null;;
    profile) python3 .ci/profile_stylize.py "$R/fern_prof" -- --scene "$R/fern/point_cloud.ply" --data $D/fern_llff --downscale 2 \
               --style $D/styles/starry_night.jpg --iterations 300 2>&1 | grep -v "^Module" > "$OUT/profile_stylize.txt"
             head -c 9000 "$OUT/profile_stylize.txt";;
  esac
done
