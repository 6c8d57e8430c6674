#!/usr/bin/env bash
# Beer with this round's defaults (holes: issue 14's size_rules split; the FAST reuse): fit beer (--downscale 2),
# stylize it with tlvg.yaml and abcgs.yaml (3000 / 1400 iterations, The Starry Night), one ruler for both.
# On the device (after staging): source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_beer.sh
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
R=/tmp/tlvg-runs; mkdir -p "$R"; D=/tmp/tlvg-data
python3 -m compileall -q -j 16 /tmp/tlvg-gpu/site tlvg_warp kernels > /dev/null 2>&1
python3 -m tlvg_warp reconstruct $D/beer_colmap --downscale 2 --iterations 7000 --out "$R/beer" --overwrite --quiet \
  > "$R/beer_fit.log" 2>&1; tail -n 1 "$R/beer_fit.log"
for c in tlvg abcgs; do
  /usr/bin/time -f "beer $c wall %e s" python3 -m tlvg_warp stylize --scene "$R/beer/point_cloud.ply" --data $D/beer_colmap \
    --downscale 2 --style $D/styles/starry_night.jpg --config configs/$c.yaml --out "$R/beer_$c" --overwrite --quiet \
    > "$R/beer_$c.log" 2>&1; tail -n 3 "$R/beer_$c.log"
done
timeout 300 python3 -m tlvg_warp evaluate "$R/beer_tlvg" "$R/beer_abcgs" --max-views 10 --out "$R/beer_eval" \
  > "$R/beer_eval.log" 2>&1; tail -n 22 "$R/beer_eval.log"; cp "$R/beer_eval/evaluation.json" "$R/beer_tlvg/comparison.png" "$OUT/" 2>/dev/null
