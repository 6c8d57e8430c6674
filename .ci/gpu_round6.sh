#!/usr/bin/env bash
# Issue 15, fifth round, one call on one GPU (nvidia-h200): fit fern and beer (kept as SPZ under $OUT for later
# rounds), the CUDA tests for each blending variant, then `bench raster` on both fitted scenes against gsplat 1.5.3:
# the session-start code (git archive of efe8cbc, carried as .gpu/old15), this round's code, and its 8x4 warp
# variant, each in its own process with gsplat in the same process; then the host/GPU timeline of one fern view.
# On the device: source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_round6.sh [fit] [tests] [raster] [host]
# FITS=dir: take fern.spz and beer.spz from there instead of fitting.
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 PYTHONUNBUFFERED=1
R=/tmp/tlvg-runs; mkdir -p "$R"; D=/tmp/tlvg-data
[ $# -eq 0 ] && set -- fit tests raster host
nvidia-smi --query-gpu=name --format=csv,noheader
python3 -m compileall -q -j 16 /tmp/tlvg-gpu/site tlvg_warp kernels .gpu/old15 > /dev/null 2>&1  # as an install would
metrics() { python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print({k: m.get(k) for k in sys.argv[2:]})" "$@"; }
FERN_PLY=$R/fern/point_cloud.ply; BEER_PLY=$R/beer/point_cloud.ply
if [ -n "${FITS:-}" ]; then FERN_PLY=$FITS/fern.spz; BEER_PLY=$FITS/beer.spz; fi
SCENES="--scene $FERN_PLY:$D/fern_llff:images_4 --scene $BEER_PLY:$D/beer_colmap:images"
for job in "$@"; do
  case "$job" in
    fit)
      /usr/bin/time -f "fern fit wall %e s" python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 \
        --iterations 7000 --out "$R/fern" --overwrite --quiet > "$R/fit.log" 2>&1; tail -n 1 "$R/fit.log"
      metrics "$R/fern/metrics.json" psnr num_gaussians train_time_s
      /usr/bin/time -f "beer fit wall %e s" python3 -m tlvg_warp reconstruct $D/beer_colmap --downscale 2 \
        --iterations 7000 --out "$R/beer" --overwrite --quiet >> "$R/fit.log" 2>&1; tail -n 1 "$R/fit.log"
      metrics "$R/beer/metrics.json" psnr num_gaussians train_time_s
      python3 - "$R" "$OUT" <<'PY'
import sys, os
from tlvg_warp.io.ply import load_ply
from tlvg_warp.io.splat_formats import save_spz
for s in ("fern", "beer"):
    save_spz(load_ply(f"{sys.argv[1]}/{s}/point_cloud.ply"), f"{sys.argv[2]}/{s}.spz")
    print(s, "spz", os.path.getsize(f"{sys.argv[2]}/{s}.spz") / 2**20, "MiB")
PY
      ;;
    tests)
      for v in "default:" "w84:TLVG_WARP_BLEND_WARP=8x4" "bfly:TLVG_WARP_BLEND_REDUCE=butterfly"; do
        IFS=: read -r name envs <<< "$v"
        echo "CUDA tests, $name"; env $envs python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py 2>&1 | tail -n 2
      done;;
    raster)
      for v in "start:$PWD/.gpu/old15:" "now:$PWD:" "now_8x4:$PWD:TLVG_WARP_BLEND_WARP=8x4" "now_bfly:$PWD:TLVG_WARP_BLEND_REDUCE=butterfly"; do
        IFS=: read -r name root envs <<< "$v"
        echo "== bench raster: $name"
        ( cd "$root" && env $envs PYTHONPATH=/tmp/tlvg-gpu/site:$root timeout 300 python3 -m tlvg_warp bench raster \
            --sizes 1000000 --garden "" --peers tlvg_warp,gsplat $SCENES --repeats 10 ${VIEWS:+--views $VIEWS} \
            --out "$R/bench_$name" > "$R/bench_$name.log" 2>&1 )
        grep -v "^Module\|^{" "$R/bench_$name.log" | tail -n 30
      done
      tar -czf "$OUT/bench_logs.tgz" -C "$R" $(cd "$R" && ls -d bench_* 2>/dev/null);;
    host)
      python3 .ci/profile_host.py "$FERN_PLY:$D/fern_llff:images_4" fwd 2>&1 | grep -v "^Module" | tail -n 45
      python3 .ci/profile_host.py "$FERN_PLY:$D/fern_llff:images_4" fwd_bwd 2>&1 | grep -v "^Module" | tail -n 45;;
  esac
done
