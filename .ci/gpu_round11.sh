#!/usr/bin/env bash
# Issue 15, sixth session: this code against PREV (a `git archive` of the session's start, c1cd00b) on one GPU.
# On the device: source /tmp/tlvg-gpu/env.sh && PREV=.gpu/prev10 bash .ci/gpu_round11.sh [tests] [stylize] [step]
#   tests:   the CUDA tests (rasterizer, graphed VGG)
#   stylize: fern stylized 3000 iterations by this code, PREV, this code (process wall, interleaved)
#   step:    wall and GPU time per stylize step of this code (.ci/profile_step.py)
# Raster and fit jobs: .ci/gpu_compare.sh with the same PREV.
set -uo pipefail
[ $# -eq 0 ] && set -- tests stylize
source "$(dirname "$0")/gpu_env.sh"
for job in "$@"; do
  case "$job" in
    tests) cuda_tests;;
    stylize)
      for v in "now:$PWD" "prev:$PWD/$PREV" "now2:$PWD"; do
        IFS=: read -r name root <<< "$v"
        ( cd "$root" && PYTHONPATH=/tmp/tlvg-gpu/site:$root /usr/bin/time -f "fern stylize $name 3000 wall %e s" \
            python3 -m tlvg_warp stylize $FERN --out "$R/fern_$name" --overwrite --quiet > "$R/fern_$name.log" 2>&1 )
        tail -n 2 "$R/fern_$name.log"
        metrics "$R/fern_$name/metrics.json" wall_time_s setup_time_s train_time_s outputs_time_s flow_alignment stage_split
      done
      tar -czf "$OUT/stylize_logs.tgz" -C "$R" $(cd "$R" && ls fern_*/metrics.json fern_*.log 2>/dev/null);;
    step)
      WARM=1000 TIMED=1000 python3 .ci/profile_step.py stylize -- $FERN --out "$R/step" --overwrite --quiet 2>&1 \
        | grep -v "^Module" > "$OUT/step_now.txt"; grep "wall per step\|GPU kernel time" "$OUT/step_now.txt";;
  esac
done
