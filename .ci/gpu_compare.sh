#!/usr/bin/env bash
# Issue 15, fifth round: this code against an earlier one in one call on one GPU (nvidia-h200). The CUDA tests;
# `bench raster` on fern and beer (the SPZ copies of round 6's fits, carried as .gpu/fits) and a random 1M against
# gsplat 1.5.3, for the earlier code (PREV: a `git archive` of it, carried) and this code, each in its own process
# with gsplat in it; the host/GPU timeline of one fern view; fern fitted 7000 iterations; fern stylized 3000
# iterations by this code twice and the earlier code once, interleaved (process wall).
# On the device: source /tmp/tlvg-gpu/env.sh && PREV=.gpu/prev9 bash .ci/gpu_compare.sh [tests] [raster] [host] [fit] [stylize]
# The fifth session's calls: PREV=.gpu/old15 (efe8cbc, "round 7"), .gpu/prev8 (336b7e5, "round 8"), .gpu/prev9 (the
# commit before the binning launch merge, "round 9"); they ran as copies of this script named gpu_round7/8/9.sh.
set -uo pipefail
[ $# -eq 0 ] && set -- tests raster host fit stylize
source "$(dirname "$0")/gpu_env.sh"
for job in "$@"; do
  case "$job" in
    tests) python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py 2>&1 | tail -n 2;;
    raster) RASTER_ROWS=22 raster_ab prev now;;
    host)
      python3 .ci/profile_host.py "$F/fern.spz:$D/fern_llff:images_4" fwd 2>&1 | grep -v "^Module" | tail -n 45
      python3 .ci/profile_host.py "$F/fern.spz:$D/fern_llff:images_4" fwd_bwd 2>&1 | grep -v "^Module" | tail -n 48;;
    fit)
      /usr/bin/time -f "fern fit wall %e s" python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 \
        --iterations 7000 --out "$R/fern" --overwrite --quiet > "$R/fit.log" 2>&1; tail -n 1 "$R/fit.log"
      metrics "$R/fern/metrics.json" psnr ssim num_gaussians train_time_s wall_time_s;;
    stylize)
      FERN="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
      for v in "now:$PWD" "prev:$PWD/$PREV" "now2:$PWD"; do
        IFS=: read -r name root <<< "$v"
        ( cd "$root" && PYTHONPATH=/tmp/tlvg-gpu/site:$root /usr/bin/time -f "fern stylize $name 3000 wall %e s" \
            python3 -m tlvg_warp stylize $FERN --out "$R/fern_$name" --overwrite --quiet > "$R/fern_$name.log" 2>&1 )
        tail -n 1 "$R/fern_$name.log"
        metrics "$R/fern_$name/metrics.json" wall_time_s setup_time_s train_time_s outputs_time_s stage_split
      done;;
  esac
done
