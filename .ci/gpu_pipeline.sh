#!/usr/bin/env bash
# GPU run of the pipeline on the real scenes (carry .gpu/data: fern_llff, beer_colmap, starry_night.jpg).
# Usage on the device: source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_pipeline.sh [fern|beer|stylize]...
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
D=.gpu/data
for job in "$@"; do
  case "$job" in
    fern) python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 --iterations 7000 --out "$OUT/fern" --quiet \
            > "$OUT/fern.log" 2>&1; tail -5 "$OUT/fern.log";
          python3 -c "import json;m=json.load(open('$OUT/fern/metrics.json'));print({k:m.get(k) for k in ('psnr','ssim','num_gaussians','ply_bytes','wall_time_s','iterations','time_split_ms','time_split')})";;
    beer) python3 -m tlvg_warp reconstruct $D/beer_colmap --downscale 2 --iterations 7000 --out "$OUT/beer" --quiet \
            > "$OUT/beer.log" 2>&1; tail -5 "$OUT/beer.log";
          python3 -c "import json;m=json.load(open('$OUT/beer/metrics.json'));print({k:m.get(k) for k in ('psnr','ssim','num_gaussians','ply_bytes','wall_time_s','iterations')})";;
    demo) /usr/bin/time -v python3 -m tlvg_warp stylize --vgg-weights random --out "$OUT/demo" > "$OUT/demo.log" 2>&1;
          grep -E "Elapsed|Maximum resident" "$OUT/demo.log"; tail -3 "$OUT/demo.log";;
    stylize) python3 -m tlvg_warp stylize --scene "$OUT/fern/point_cloud.ply" --data $D/fern_llff --set images=images_4 \
            --style $D/starry_night.jpg --vgg-weights random --out "$OUT/fern_tlvg" > "$OUT/fern_tlvg.log" 2>&1;
          tail -5 "$OUT/fern_tlvg.log";;
  esac
done
rm -f "$OUT"/*/checkpoint.pt  # keep what comes back small
