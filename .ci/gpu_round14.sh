#!/usr/bin/env bash
# Issue 15, ninth session: this session's rasterizer, launch and training-loop changes against PREV on one GPU
# (nvidia-h200).
# On the device: source /tmp/tlvg-gpu/env.sh && PREV=.gpu/prev13 bash .ci/gpu_round14.sh [tests] [costs] [gap] [raster]
#   [stylize] [fit] [quality]
#   [lego]
#   tests:  the CUDA tests (rasterizer, graphed VGG)
#   costs:  host microseconds per render operation (.ci/host_costs.py), this code
#   gap:    the host-only timeline of a beer and a fern forward+backward (.ci/host_gap.py), this code then PREV
#   raster: `bench raster` on fern, beer and a random 1M against gsplat 1.5.3: this code, PREV, this code again,
#           each in its own process with gsplat in it
#   stylize: fern stylized 3000 iterations, this code and PREV alternately, twice each (process wall)
#   fit:    fern fitted by `reconstruct`, 7000 iterations, this code then PREV (training time, PSNR)
#   lego:   lego (Blender, 800x800, all 125 views) fitted by `reconstruct`, 7000 iterations, kept as
#           /tmp/tlvg-fits/lego.spz (and in $OUT); a later raster job on the same machine benches it too. The data
#           comes in its own call: `mkdir -p /tmp/tlvg-data && cp -r .gpu/lego/* /tmp/tlvg-data/` (carry .gpu/lego)
#   quality: after stylize, `evaluate` on its four runs (one ruler: flow alignment, style and content distance,
#           holes), first 10 views
set -uo pipefail
[ $# -eq 0 ] && set -- tests gap raster
source "$(dirname "$0")/gpu_env.sh"
for job in "$@"; do
  case "$job" in
    tests) cuda_tests;;
    costs) python3 .ci/host_costs.py 2>&1 | grep -v "^Module\|^Warp";;
    gap)
      for v in "now:$PWD" "prev:$PWD/$PREV"; do
        IFS=: read -r name root <<< "$v"
        echo "== host gap: $name"
        PYTHONPATH=/tmp/tlvg-gpu/site:$root python3 .ci/host_gap.py "$F/beer.spz:$D/beer_colmap:images" \
          "$F/fern.spz:$D/fern_llff:images_4" 2>&1 | grep -v "^Module" > "$OUT/gap_$name.txt"
        tail -n 3 "$OUT/gap_$name.txt"
      done;;
    raster)
      [ -f /tmp/tlvg-fits/lego.spz ] && SCENES="$SCENES --scene /tmp/tlvg-fits/lego.spz:$D/lego_blender"
      raster_ab now prev now2;;
    lego)
      /usr/bin/time -f "lego fit wall %e s" python3 -m tlvg_warp reconstruct $D/lego_blender --iterations 7000 \
        --out "$R/lego" --overwrite --quiet > "$R/lego.log" 2>&1; tail -n 1 "$R/lego.log"
      metrics "$R/lego/metrics.json" psnr ssim num_gaussians train_time_s wall_time_s
      mkdir -p /tmp/tlvg-fits && python3 -c "import sys; from tlvg_warp.io.ply import load_ply; \
from tlvg_warp.io.splat_formats import save_spz; save_spz(load_ply(sys.argv[1]), sys.argv[2])" \
        "$R/lego/point_cloud.ply" /tmp/tlvg-fits/lego.spz && cp /tmp/tlvg-fits/lego.spz "$OUT/";;
    fit)
      for v in "now:$PWD" "prev:$PWD/$PREV"; do
        IFS=: read -r name root <<< "$v"
        ( cd "$root" && PYTHONPATH=/tmp/tlvg-gpu/site:$root /usr/bin/time -f "fern fit $name wall %e s" \
            python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 --iterations 7000 --out "$R/fit_$name" \
            --overwrite --quiet > "$R/fit_$name.log" 2>&1 ); tail -n 1 "$R/fit_$name.log"
        metrics "$R/fit_$name/metrics.json" psnr ssim num_gaussians train_time_s wall_time_s
      done;;
    quality)
      timeout 400 python3 -m tlvg_warp evaluate "$R/fern_now" "$R/fern_prev" "$R/fern_now2" "$R/fern_prev2" \
        --max-views 10 --out "$R/fern_eval" > "$R/fern_eval.log" 2>&1; tail -n 24 "$R/fern_eval.log"
      cp "$R/fern_eval/evaluation.json" "$OUT/" 2>/dev/null;;
    stylize) stylize_interleaved wall_time_s train_time_s flow_alignment time_per_phase_s;;
  esac
done
