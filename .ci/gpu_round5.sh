#!/usr/bin/env bash
# Issue 15, fifth round, one call on one GPU (nvidia-h200): byte-compile the staged packages (a user's install has
# .pyc files; the staged copy does not, which cost every process ~2-5 s of start-up), the CUDA tests and the fused SSIM
# against torch, fits of fern and beer with the fused SSIM and with the torch one (TLVG_WARP_FUSED_SSIM=0) in the
# same call, where a stylization step spends its time (torch.profiler), and fern stylized with the default and with
# the FAST projection reused (loss.fast_refresh=4, loss.fast_cache=projection), timed, then one ruler for both.
# On the device: source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_round5.sh [compile] [tests] [fit] [profile] [styleval]
# Everything is printed; $OUT gets round5.log (tee'd by the caller), profile_stylize.txt and evaluation.json.
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
R=/tmp/tlvg-runs; mkdir -p "$R"; D=/tmp/tlvg-data
FERN="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
[ $# -eq 0 ] && set -- compile tests fit profile styleval
nvidia-smi --query-gpu=name --format=csv,noheader
metrics() { python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print({k: m.get(k) for k in sys.argv[2:]})" "$@"; }
fit() {  # name, SSIM switch, dataset args...
  local name=$1 fused=$2; shift 2
  TLVG_WARP_FUSED_SSIM=$fused /usr/bin/time -f "$name fit wall %e s" python3 -m tlvg_warp reconstruct "$@" \
    --iterations 7000 --out "$R/$name" --overwrite --quiet > "$R/$name.log" 2>&1; tail -n 2 "$R/$name.log"
  metrics "$R/$name/metrics.json" psnr ssim num_gaussians train_time_s wall_time_s time_split
}
for job in "$@"; do
  case "$job" in
    compile) t0=$(date +%s.%N); python3 -m compileall -q -j 16 /tmp/tlvg-gpu/site tlvg_warp kernels > /dev/null 2>&1
             echo "compileall $(awk "BEGIN{print $(date +%s.%N) - $t0}") s";;
    tests) python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py 2>&1 | tail -n 2
           python3 .ci/ssim_cuda_check.py 2>&1 | grep -v "^Module";;
    fit) fit fern 1 $D/fern_llff --images images_4
         fit beer 1 $D/beer_colmap --downscale 2
         fit beer_torchssim 0 $D/beer_colmap --downscale 2
         fit fern_torchssim 0 $D/fern_llff --images images_4;;
    profile)  # the stylize phase alone: 300 steps
      python3 .ci/profile_stylize.py "$R/fern_prof" -- $FERN --iterations 300 --set "phases=[0,300,0]" \
        --set orbit_frames=0 --set web_formats=false --set comparison_views=1 2>&1 | grep -v "^Module" > "$OUT/profile_stylize.txt"
      grep -m1 "totals" "$OUT/profile_stylize.txt"; metrics "$R/fern_prof/metrics.json" train_time_s stage_split;;
    styleval)
      for v in "tlvg::" "tlvg_p4:loss.fast_refresh=4:loss.fast_cache=projection"; do
        IFS=: read -r name s1 s2 <<< "$v"
        /usr/bin/time -f "fern $name 3000 wall %e s" python3 -m tlvg_warp stylize $FERN ${s1:+--set $s1} ${s2:+--set $s2} \
          --out "$R/fern_$name" --overwrite --quiet > "$R/fern_$name.log" 2>&1; tail -n 3 "$R/fern_$name.log"
        metrics "$R/fern_$name/metrics.json" wall_time_s load_split_s setup_time_s setup_split_s train_time_s \
          time_per_phase_s outputs_time_s outputs_split_s stage_split gaussians_final
      done
      timeout 300 python3 -m tlvg_warp evaluate "$R/fern_tlvg" "$R/fern_tlvg_p4" --max-views 10 --out "$R/fern_eval" \
        > "$R/fern_eval.log" 2>&1; tail -n 22 "$R/fern_eval.log"; cp "$R/fern_eval/evaluation.json" "$OUT/" 2>/dev/null;;
  esac
done
