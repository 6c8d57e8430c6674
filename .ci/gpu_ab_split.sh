#!/usr/bin/env bash
# Issue 14 holes, the size rules on fitted fern: split (the default) on GPU0 against always-prune on GPU1, one ruler.
set -uo pipefail
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"; R=/tmp/tlvg-runs; D=/tmp/tlvg-data
ARGS="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg --quiet --overwrite --set orbit_frames=0"
CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 --iterations 7000 --out "$R/fern" --overwrite --quiet > "$OUT/fit.log" 2>&1
tail -n 1 "$OUT/fit.log"
( CUDA_VISIBLE_DEVICES=0 /usr/bin/time -f "split wall %e s" python3 -m tlvg_warp stylize $ARGS --out $R/ab_split > "$OUT/split.log" 2>&1 ) &
( CUDA_VISIBLE_DEVICES=1 python3 -m tlvg_warp stylize $ARGS --set density.size_rules=always --out $R/ab_always > "$OUT/always.log" 2>&1 ) &
wait
for r in split always; do tail -n 3 "$OUT/$r.log" | grep -v "^open"; done
python3 -c "import json; m=json.load(open('$R/ab_split/metrics.json')); print(m['densify_events'][:3], m['densify_events'][-1])"
CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp evaluate $R/ab_split $R/ab_always --max-views 10 --out $R/ab_eval > "$OUT/eval.log" 2>&1
grep -v "^Module" "$OUT/eval.log" | tail -n 20; cp $R/ab_eval/evaluation.json "$OUT/" 2>/dev/null
python3 - "$R/ab_split" "$OUT/split_comparison.jpg" <<'PY'
import sys, cv2
im = cv2.imread(sys.argv[1] + "/comparison.png")
if im is not None:
    cv2.imwrite(sys.argv[2], cv2.resize(im, (1600, round(im.shape[0] * 1600 / im.shape[1]))), [cv2.IMWRITE_JPEG_QUALITY, 75])
PY
