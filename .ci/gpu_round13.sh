#!/usr/bin/env bash
# Issue 15, eighth session: the render's host trims against PREV on one GPU (nvidia-h200).
# On the device: source /tmp/tlvg-gpu/env.sh && PREV=.gpu/prev12 bash .ci/gpu_round13.sh [tests] [host] [raster] [stylize]
#   tests:   the CUDA tests (rasterizer, graphed VGG)
#   host:    host vs wall time of a fern render (.ci/host_wall.py), this code and PREV alternately
#   raster:  `bench raster` on fern, beer and a random 1M against gsplat 1.5.3: this code, PREV, this code again,
#            each in its own process with gsplat in it
#   stylize: fern stylized 3000 iterations, this code and PREV alternately, twice each (process wall)
set -uo pipefail
[ $# -eq 0 ] && set -- tests host raster stylize
source "$(dirname "$0")/gpu_env.sh"
for job in "$@"; do
  case "$job" in
    tests) cuda_tests;;
    host)
      for v in "now:$PWD" "prev:$PWD/$PREV" "now2:$PWD" "prev2:$PWD/$PREV"; do
        IFS=: read -r name root <<< "$v"
        for mode in fwd fwd_bwd; do
          echo -n "$name "; PYTHONPATH=/tmp/tlvg-gpu/site:$root python3 .ci/host_wall.py "$F/fern.spz:$D/fern_llff:images_4" $mode 300
        done
      done;;
    raster) raster_ab now prev now2;;
    stylize) stylize_interleaved wall_time_s train_time_s outputs_time_s flow_alignment time_per_phase_s;;
  esac
done
