#!/usr/bin/env bash
# GPU run of the pipeline on the real scenes (carry .gpu/data: fern_llff, beer_colmap, starry_night.jpg).
# Usage on the device: source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_pipeline.sh [fern|beer|demo|stylize|abcgs|evaluate]...
# Runs live in /tmp/tlvg-runs (kept while the machine stays warm); logs and small files are copied to $OUT.
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
R=/tmp/tlvg-runs; mkdir -p "$R"
D=.gpu/data
keys="psnr ssim psnr_init num_gaussians ply_bytes wall_time_s train_time_s iterations"
show() { python3 - "$1" $2 <<'PY'
import json, sys
m = json.load(open(sys.argv[1]))
print({k: m.get(k) for k in sys.argv[2:]})
ts = m.get("time_split") or m.get("stage_split")
if ts: print("split", ts)
for k in ("time_per_phase_s", "flow_alignment", "flow_alignment_original", "gaussians_final", "bytes_out", "setup_time_s", "wall_time_s"):
    if k in m: print(k, m[k])
PY
}
for job in "$@"; do
  case "$job" in
    fern) python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 --iterations 7000 --out "$R/fern" --overwrite --quiet \
            > "$OUT/fern.log" 2>&1; tail -n 2 "$OUT/fern.log"; show "$R/fern/metrics.json" "$keys"
          mkdir -p "$OUT/fern"; cp -r "$R/fern/metrics.json" "$R/fern/test" "$OUT/fern/";;
    beer) python3 -m tlvg_warp reconstruct $D/beer_colmap --downscale 2 --iterations 7000 --out "$R/beer" --overwrite --quiet \
            > "$OUT/beer.log" 2>&1; tail -n 2 "$OUT/beer.log"; show "$R/beer/metrics.json" "$keys"
          mkdir -p "$OUT/beer"; cp -r "$R/beer/metrics.json" "$OUT/beer/";;
    demo) /usr/bin/time -f "demo wall %e s" python3 -m tlvg_warp stylize --vgg-weights random --out "$R/demo" --overwrite --quiet \
            > "$OUT/demo.log" 2>&1; tail -n 3 "$OUT/demo.log";;
    stylize|abcgs) cfg=configs/tlvg.yaml; [ "$job" = abcgs ] && cfg=configs/abcgs.yaml
          /usr/bin/time -f "$job wall %e s" python3 -m tlvg_warp stylize --scene "$R/fern/point_cloud.ply" --data $D/fern_llff \
            --config $cfg --style $D/starry_night.jpg --vgg-weights random --out "$R/fern_$job" \
            --overwrite --quiet > "$OUT/fern_$job.log" 2>&1; tail -n 3 "$OUT/fern_$job.log"
          show "$R/fern_$job/metrics.json" "iterations"
          mkdir -p "$OUT/fern_$job"; cp "$R/fern_$job/metrics.json" "$R/fern_$job/comparison.png" "$R/fern_$job/stroke_field.png" "$OUT/fern_$job/";;
    fitstylize) /usr/bin/time -f "fitstylize wall %e s" python3 -m tlvg_warp stylize --data $D/fern_llff --style $D/starry_night.jpg \
            --vgg-weights random --out "$R/fern_fitstylize" --overwrite --quiet > "$OUT/fern_fitstylize.log" 2>&1
          tail -n 3 "$OUT/fern_fitstylize.log"; show "$R/fern_fitstylize/metrics.json" "iterations"
          mkdir -p "$OUT/fern_fitstylize"; cp "$R/fern_fitstylize/metrics.json" "$OUT/fern_fitstylize/";;
    stability) /usr/bin/time -f "stability wall %e s" python3 -m tlvg_warp stability --vgg-weights random --out "$R/stability" \
            > "$OUT/stability.log" 2>&1; tail -n 30 "$OUT/stability.log"; cp -r "$R/stability" "$OUT/";;
    evaluate) python3 -m tlvg_warp evaluate "$R/fern_stylize" --against "$R/fern_abcgs" --vgg-weights random \
            --out "$R/eval" > "$OUT/evaluate.log" 2>&1; tail -n 25 "$OUT/evaluate.log"; cp "$R/eval/evaluation.json" "$OUT/";;
  esac
done
