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
    stylize) stylize_interleaved wall_time_s setup_time_s train_time_s outputs_time_s load_split_s outputs_split_s flow_alignment time_per_phase_s;;
  esac
done
