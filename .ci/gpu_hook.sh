#!/usr/bin/env bash
# The tangential hook as a Warp kernel, measured: fern fitted, then stylized (3000 iterations, default config) by
# this code and by the commit before the hook kernel (git archive aeda58d, carried as .gpu/prevhook), each a
# timed process, in the same call; one ruler for both.
# On the device (after staging): source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_hook.sh
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
R=/tmp/tlvg-runs; mkdir -p "$R"; D=/tmp/tlvg-data
FERN="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
metrics() { python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print({k: m.get(k) for k in sys.argv[2:]})" "$@"; }
python3 -m compileall -q -j 16 /tmp/tlvg-gpu/site tlvg_warp kernels .gpu/prevhook > /dev/null 2>&1
python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py tests/test_train_optim.py 2>&1 | tail -n 1
python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 --iterations 7000 --out "$R/fern" --overwrite --quiet \
  > "$R/fit.log" 2>&1; tail -n 1 "$R/fit.log"
for v in "prev:$PWD/.gpu/prevhook" "now:$PWD" "prev2:$PWD/.gpu/prevhook" "now2:$PWD"; do
  IFS=: read -r name root <<< "$v"
  ( cd "$root" && PYTHONPATH=/tmp/tlvg-gpu/site:$root /usr/bin/time -f "fern $name 3000 wall %e s" python3 -m tlvg_warp \
      stylize $FERN --out "$R/fern_$name" --overwrite --quiet > "$R/fern_$name.log" 2>&1 )
  tail -n 1 "$R/fern_$name.log"
  metrics "$R/fern_$name/metrics.json" wall_time_s setup_time_s train_time_s time_per_phase_s outputs_time_s stage_split
done
timeout 300 python3 -m tlvg_warp evaluate "$R/fern_now" "$R/fern_prev" --max-views 10 --out "$R/fern_eval" \
  > "$R/fern_eval.log" 2>&1; tail -n 20 "$R/fern_eval.log"
