#!/usr/bin/env bash
# Issue 15 on the GPU: the rasterizer on fitted scenes against gsplat/gswarp, in one process per benchmark.
#   fit    fern and beer fitted by `reconstruct` into /tmp/tlvg-runs/{fern,beer}/point_cloud.ply (skipped when there)
#   tests  tests/test_raster_cuda.py (the CUDA binning/blending against the brute-force set and the float64 oracle)
#   ab     blending variants on fern (4 views, ours only): staged-batch layout, __launch_bounds__, batch walk
#          (AB_VARIANTS="SLAB BLOCKS LOOP;..."), GPU time per stage
#   bench  `bench raster`: fitted fern and beer (every view) + random 1M/3M, all peers; per-stage GPU times,
#          top kernels, list lengths; the table last
#   proxy  without the fitted scenes: a trained splat (PROXY, default .gpu/proxy/biker.compressed.ply, orbit views)
#          and random 1M against gsplat, and the ab variants on it
# On the device:  source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_raster_fitted.sh [fit] [tests] [ab] [bench]
# (no job named: all four; each job keeps going when another fails). Logs and tables under $OUT.
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 PYTHONUNBUFFERED=1
R=/tmp/tlvg-runs; mkdir -p "$R"
D=${TLVG_DATA_DIR:-/tmp/tlvg-data}
[ -d "$D/fern_llff" ] || { [ -d .gpu/data/fern_llff ] && D=.gpu/data; }
FERN="$R/fern/point_cloud.ply:$D/fern_llff:images_4"
BEER="$R/beer/point_cloud.ply:$D/beer_colmap:images"
jobs=("$@"); [ ${#jobs[@]} -eq 0 ] && jobs=(fit tests ab bench)
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import torch, warp; print('torch', torch.__version__, 'warp', warp.__version__)" 2>&1 | tail -1
git log --oneline -1 2>/dev/null || true
echo "data: $D"

fit() {
  [ -f "$R/fern/point_cloud.ply" ] || /usr/bin/time -f "fern fit wall %e s" python3 -m tlvg_warp reconstruct "$D/fern_llff" \
    --images images_4 --iterations 7000 --out "$R/fern" --overwrite --quiet > "$OUT/fit.log" 2>&1
  [ -f "$R/beer/point_cloud.ply" ] || /usr/bin/time -f "beer fit wall %e s" python3 -m tlvg_warp reconstruct "$D/beer_colmap" \
    --downscale 2 --iterations 7000 --out "$R/beer" --overwrite --quiet >> "$OUT/fit.log" 2>&1
  tail -n 6 "$OUT/fit.log" 2>/dev/null; ls -la "$R"/fern/point_cloud.ply "$R"/beer/point_cloud.ply
}

tests() {
  python3 -m pytest -q -p no:cacheprovider -x tests/test_raster_cuda.py 2>&1 | tail -n 25 | tee "$OUT/tests.txt"
}

ab() {
  # one process per variant (the variant is a compile-time choice); ours only, 4 views, GPU time per stage
  local scene=${1:-$FERN}
  [ -f "${scene%%:*}" ] || { echo "ab: no ${scene%%:*}"; return 1; }
  : > "$OUT/ab.txt"
  local variants=("vector 0,0 while" "vector 0,0 for" "scalar 0,0 while" "vector 4,3 while")
  [ -n "${AB_VARIANTS:-}" ] && IFS=';' read -ra variants <<< "$AB_VARIANTS"
  for v in "${variants[@]}"; do
    set -- $v
    echo "== TLVG_WARP_BLEND_SLAB=$1 TLVG_WARP_BLEND_BLOCKS=$2 TLVG_WARP_BLEND_LOOP=$3" | tee -a "$OUT/ab.txt"
    TLVG_WARP_BLEND_SLAB=$1 TLVG_WARP_BLEND_BLOCKS=$2 TLVG_WARP_BLEND_LOOP=$3 timeout 240 python3 -m tlvg_warp bench raster --sizes none --garden "" \
      --peers tlvg_warp --scene "$scene" --views 4 --repeats 10 --out "/tmp/tlvg-ab/$1_${2/,/_}_$3" 2>&1 \
      | grep -E "^\| .*(fwd|fwd\+bwd) \||blend_(forward|backward)|Error|error" | tee -a "$OUT/ab.txt"
  done
}

bench() {
  local scenes=()
  [ -f "$R/fern/point_cloud.ply" ] && scenes+=(--scene "$FERN") || echo "bench: no fitted fern"
  [ -f "$R/beer/point_cloud.ply" ] && scenes+=(--scene "$BEER") || echo "bench: no fitted beer"
  python3 -m tlvg_warp bench raster --sizes 1000000,3000000 --garden "" --peers tlvg_warp,gsplat,gswarp \
    "${scenes[@]}" --repeats 10 --out "$OUT/bench" > "$OUT/bench.log" 2>&1
  echo "bench exit $?"
  grep -v "^Module\|^{" "$OUT/bench.log" | tail -n 120
}

proxy() {
  local ply=${PROXY:-.gpu/proxy/biker.compressed.ply}
  [ -f "$ply" ] || { echo "proxy: no $ply"; return 1; }
  python3 -m tlvg_warp bench raster --sizes 1000000 --garden "" --peers tlvg_warp,gsplat --scene "$ply" --views 8 \
    --repeats 10 --out "$OUT/proxy" > "$OUT/proxy.log" 2>&1
  echo "proxy bench exit $?"
  grep -v "^Module\|^{" "$OUT/proxy.log" | tail -n 70
  ab "$ply"
}

for j in "${jobs[@]}"; do
  echo; echo "==== $j ($(date +%T))"
  "$j" || echo "==== $j failed"
done
[ -f "$OUT/bench/bench_raster.md" ] && { echo; echo "==== table"; cat "$OUT/bench/bench_raster.md"; }
