#!/usr/bin/env bash
# Issue 15, seventh session: the stylize run's fixed costs (imports, outputs) against PREV on one GPU.
# On the device: source /tmp/tlvg-gpu/env.sh && PREV=.gpu/prev11 bash .ci/gpu_round12.sh [tests] [stylize]
#   tests:   the CUDA tests (rasterizer, graphed VGG, the capture's imports)
#   stylize: fern stylized 3000 iterations, this code and PREV alternately, twice each (process wall), after one
#            300-iteration warm-up that compiles the kernels (they are the same in both)
set -uo pipefail
[ $# -eq 0 ] && set -- tests stylize
source "$(dirname "$0")/gpu_env.sh"
for job in "$@"; do
  case "$job" in
    tests) cuda_tests;;
    stylize)
      python3 -m tlvg_warp stylize $FERN --iterations 300 --out "$R/warm" --overwrite --quiet > /dev/null 2>&1
      for v in "now:$PWD" "prev:$PWD/$PREV" "now2:$PWD" "prev2:$PWD/$PREV"; do
        IFS=: read -r name root <<< "$v"
        ( cd "$root" && PYTHONPATH=/tmp/tlvg-gpu/site:$root /usr/bin/time -f "fern stylize $name 3000 wall %e s" \
            python3 -m tlvg_warp stylize $FERN --out "$R/fern_$name" --overwrite --quiet > "$R/fern_$name.log" 2>&1 )
        tail -n 2 "$R/fern_$name.log"
        metrics "$R/fern_$name/metrics.json" wall_time_s setup_time_s train_time_s outputs_time_s load_split_s \
          outputs_split_s flow_alignment time_per_phase_s
      done
      tar -czf "$OUT/stylize_logs.tgz" -C "$R" $(cd "$R" && ls fern_*/metrics.json fern_*.log 2>/dev/null);;
  esac
done
