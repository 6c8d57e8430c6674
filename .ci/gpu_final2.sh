#!/usr/bin/env bash
# Issue 15, the round's closing measurement on one GPU (nvidia-h200), one call: the CUDA tests and the fused SSIM
# check; fern fitted (7000 iterations, the fit's time); fern stylized 3000 iterations by this round's code (default:
# the FAST projection reused for 4 of a view's steps), by this code with the reuse off (loss.fast_refresh=1), and by
# the session-start code (git archive of 914217b, carried as .gpu/old914), each timed as a process; then one ruler
# (`evaluate`, 10 views) for the three.
# On the device (after staging): source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_final2.sh   (with .gpu/old914 carried)
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
R=/tmp/tlvg-runs; mkdir -p "$R"; D=/tmp/tlvg-data
FERN="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
metrics() { python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print({k: m.get(k) for k in sys.argv[2:]})" "$@"; }
nvidia-smi --query-gpu=name --format=csv,noheader
python3 -m compileall -q -j 16 /tmp/tlvg-gpu/site tlvg_warp kernels .gpu/old914 > /dev/null 2>&1  # as an install would
python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py 2>&1 | tail -n 2
python3 .ci/ssim_cuda_check.py 2>&1 | grep -v "^Module"
/usr/bin/time -f "fern fit wall %e s" python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 --iterations 7000 \
  --out "$R/fern" --overwrite --quiet > "$R/fit.log" 2>&1; tail -n 2 "$R/fit.log"
metrics "$R/fern/metrics.json" psnr ssim num_gaussians train_time_s wall_time_s time_split
for v in "now:$PWD:" "now_r1:$PWD:loss.fast_refresh=1" "start:$PWD/.gpu/old914:"; do
  IFS=: read -r name root set <<< "$v"
  ( cd "$root" && PYTHONPATH=/tmp/tlvg-gpu/site:$root /usr/bin/time -f "fern $name 3000 wall %e s" python3 -m tlvg_warp \
      stylize $FERN ${set:+--set $set} --out "$R/fern_$name" --overwrite --quiet > "$R/fern_$name.log" 2>&1 )
  tail -n 3 "$R/fern_$name.log"
  metrics "$R/fern_$name/metrics.json" wall_time_s load_split_s setup_time_s setup_split_s train_time_s time_per_phase_s \
    outputs_time_s outputs_split_s stage_split gaussians_final
done
timeout 300 python3 -m tlvg_warp evaluate "$R/fern_now" "$R/fern_now_r1" "$R/fern_start" --max-views 10 --out "$R/fern_eval" \
  > "$R/fern_eval.log" 2>&1; tail -n 22 "$R/fern_eval.log"; cp "$R/fern_eval/evaluation.json" "$R/fern_now/comparison.png" "$OUT/" 2>/dev/null
