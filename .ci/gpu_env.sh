# Sourced by the .ci/gpu_compare.sh and .ci/gpu_round*.sh A/B scripts on the device: PREV (the earlier code), the
# run folders, the staged VGG weights, a metrics printer, the fern stylize arguments, the bench scenes and two A/B
# jobs. Usage: `source .ci/gpu_env.sh "$@"`.
PREV=${PREV:?set PREV to the folder of the earlier code (a git archive under .gpu/)}
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
R=/tmp/tlvg-runs; mkdir -p "$R"; D=/tmp/tlvg-data; F=$PWD/.gpu/fits
nvidia-smi --query-gpu=name --format=csv,noheader
python3 -m compileall -q -j 16 /tmp/tlvg-gpu/site tlvg_warp kernels "$PREV" > /dev/null 2>&1
metrics() { python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print({k: m.get(k) for k in sys.argv[2:]})" "$@"; }
FERN="--scene $F/fern.spz --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
SCENES="--scene $F/fern.spz:$D/fern_llff:images_4 --scene $F/beer.spz:$D/beer_colmap:images"
# the CUDA tests only: the staged Warp has no LLVM, so CPU kernels cannot compile on the device
cuda_tests() { python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py tests/test_losses_vgg.py 2>&1 | tail -n 3; }
# fern stylized 3000 iterations, this code and PREV alternately, twice each (process wall), after one 300-iteration
# warm-up that compiles the kernels; the arguments are the metrics.json keys to print per run
stylize_interleaved() {
  python3 -m tlvg_warp stylize $FERN --iterations 300 --out "$R/warm" --overwrite --quiet > /dev/null 2>&1
  for v in "now:$PWD" "prev:$PWD/$PREV" "now2:$PWD" "prev2:$PWD/$PREV"; do
    IFS=: read -r name root <<< "$v"
    ( cd "$root" && PYTHONPATH=/tmp/tlvg-gpu/site:$root /usr/bin/time -f "fern stylize $name 3000 wall %e s" \
        python3 -m tlvg_warp stylize $FERN --out "$R/fern_$name" --overwrite --quiet > "$R/fern_$name.log" 2>&1 )
    tail -n 2 "$R/fern_$name.log"
    metrics "$R/fern_$name/metrics.json" "$@"
  done
  tar -czf "$OUT/stylize_logs.tgz" -C "$R" $(cd "$R" && ls fern_*/metrics.json fern_*.log 2>/dev/null)
}
# `bench raster` on fern, beer and a random 1M against gsplat 1.5.3, one process per code with gsplat in it, in the
# order given (each argument now, now2, prev or prev2: this code or PREV); prints each process's summary table
raster_ab() {
  for name in "$@"; do
    case "$name" in prev*) root=$PWD/$PREV;; *) root=$PWD;; esac
    echo "== bench raster: $name"
    ( cd "$root" && PYTHONPATH=/tmp/tlvg-gpu/site:$root timeout 300 python3 -m tlvg_warp bench raster \
        --sizes 1000000 --garden "" --peers tlvg_warp,gsplat $SCENES --repeats 10 --out "$R/bench_$name" \
        > "$R/bench_$name.log" 2>&1 )
    grep -v "^Module\|^{" "$R/bench_$name.log" | grep "^|" | tail -n "${RASTER_ROWS:-8}"
  done
  tar -czf "$OUT/bench_logs.tgz" -C "$R" $(cd "$R" && ls -d bench_* 2>/dev/null)
}
