#!/usr/bin/env bash
# Issue 15, fourth round, one call on one GPU (nvidia-h200): fit fern and beer (the fit's time with the fused SSIM),
# the CUDA tests and the fused SSIM against torch, `bench raster` on both fitted scenes and a random 1M against
# gsplat in the same process, where a stylization step spends its GPU time (torch.profiler, stylize phase only),
# where setup and outputs spend their host time (cProfile), and fern stylized 3000 iterations with the default and
# with loss.fast_refresh=4, timed, then both evaluated with one ruler (holes, flow, style, content, consistency).
# On the device: source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_round4.sh [fit] [tests] [raster] [profile] [cprof] [styleval]
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
R=/tmp/tlvg-runs; mkdir -p "$R"; D=/tmp/tlvg-data
FERN="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
[ $# -eq 0 ] && set -- fit tests raster profile cprof styleval
nvidia-smi --query-gpu=name --format=csv,noheader
metrics() { python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print({k: m.get(k) for k in sys.argv[2:]})" "$@"; }
for job in "$@"; do
  case "$job" in
    fit)
      /usr/bin/time -f "fern fit wall %e s" python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 \
        --iterations 7000 --out "$R/fern" --overwrite --quiet > "$OUT/fit.log" 2>&1; tail -n 2 "$OUT/fit.log"
      metrics "$R/fern/metrics.json" psnr ssim num_gaussians train_time_s wall_time_s stage_split
      /usr/bin/time -f "beer fit wall %e s" python3 -m tlvg_warp reconstruct $D/beer_colmap --downscale 2 \
        --iterations 7000 --out "$R/beer" --overwrite --quiet >> "$OUT/fit.log" 2>&1; tail -n 2 "$OUT/fit.log"
      metrics "$R/beer/metrics.json" psnr ssim num_gaussians train_time_s wall_time_s stage_split;;
    tests)
      python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py 2>&1 | tail -n 2
      python3 .ci/ssim_cuda_check.py 2>&1 | grep -v "^Module";;
    raster)
      timeout 420 python3 -m tlvg_warp bench raster --sizes 1000000 --garden "" --peers tlvg_warp,gsplat \
        --scene "$R/fern/point_cloud.ply:$D/fern_llff:images_4" --scene "$R/beer/point_cloud.ply:$D/beer_colmap:images" \
        --repeats 10 --out "$OUT/bench" > "$OUT/bench.log" 2>&1; grep -v "^Module\|^{" "$OUT/bench.log" | tail -n 40;;
    profile)  # the stylize phase alone: 300 steps, no pre/post, no outputs worth the name
      python3 .ci/profile_stylize.py "$R/fern_prof" -- $FERN --iterations 300 --set "phases=[0,300,0]" \
        --set orbit_frames=0 --set web_formats=false --set comparison_views=1 2>&1 | grep -v "^Module" > "$OUT/profile_stylize.txt"
      head -c 7000 "$OUT/profile_stylize.txt";;
    cprof)  # host time of setup and outputs: the default outputs, 300 iterations
      python3 -m cProfile -o "$R/cprof.prof" -m tlvg_warp stylize $FERN --iterations 300 --out "$R/fern_cprof" \
        --overwrite --quiet > "$OUT/cprof.log" 2>&1; tail -n 2 "$OUT/cprof.log"
      metrics "$R/fern_cprof/metrics.json" setup_time_s train_time_s outputs_time_s wall_time_s
      python3 - "$R/cprof.prof" <<'PY' | tee "$OUT/cprof.txt" | head -n 70
import pstats, sys
p = pstats.Stats(sys.argv[1])
p.sort_stats("cumulative").print_stats(r"tlvg_warp|warp/_src/context.py:.*(load|build)|torch/serialization|imread|imwrite", 45)
p.sort_stats("tottime").print_stats(20)
PY
      ;;
    styleval)  # default (timed) and fast_refresh=4, then one ruler
      for v in "tlvg::" "tlvg_r4:loss.fast_refresh=4"; do
        IFS=: read -r name set <<< "$v"
        /usr/bin/time -f "fern $name 3000 wall %e s" python3 -m tlvg_warp stylize $FERN ${set:+--set $set} \
          --out "$R/fern_$name" --overwrite --quiet > "$OUT/fern_$name.log" 2>&1; tail -n 3 "$OUT/fern_$name.log"
        metrics "$R/fern_$name/metrics.json" setup_time_s train_time_s outputs_time_s wall_time_s time_per_phase_s stage_split \
          gaussians_final
      done
      timeout 300 python3 -m tlvg_warp evaluate "$R/fern_tlvg" "$R/fern_tlvg_r4" --max-views 10 --out "$R/fern_eval" \
        > "$OUT/fern_eval.log" 2>&1; tail -n 25 "$OUT/fern_eval.log"; cp "$R/fern_eval/evaluation.json" "$OUT/" 2>/dev/null;;
  esac
done
