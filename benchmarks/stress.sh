#!/usr/bin/env bash
# The rasterizer's stress cases against gsplat 1.5.3, each case run in one process with
# gsplat in it (ratio = ours / gsplat in the same process). Through the entry point:
#   bash benchmarks/run.sh stress [many] [4k] [huge]
#   many: 3M, 10M and 20M random Gaussians at 1008x756 (log-scale -4, SH degree 3)
#   4k:   1M and 3M random Gaussians at 3840x2160
#   huge: huge footprints at 1008x756: 1M at log-scale -2.5 (~70 px radius), 100k at -1.5 (~190 px)
#   ROOT=DIR TAG=_x: run the code in DIR (e.g. an earlier code's git archive under .gpu/) with this script, its
#   logs named stress_x_*
# Prints each process's table rows; the JSON and logs come back in $OUT/stress_logs$TAG.tgz.
set -uo pipefail
[ $# -eq 0 ] && set -- many 4k huge
OUT=${OUT:-/tmp/tlvg-out}; R=/tmp/tlvg-runs; mkdir -p "$OUT" "$R"; ROOT=${ROOT:-$PWD}; TAG=${TAG:-}
source "$(dirname "${BASH_SOURCE[0]}")/source_view.sh"
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16  # gsplat builds its extension on first import
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
bench() {  # name, then `bench raster` arguments
  local name=stress${TAG}_$1; shift
  echo "== $name ($ROOT): $*"
  ( cd "$ROOT" && PYTHONPATH=$(source_view "$ROOT"):/tmp/tlvg-gpu/site:$ROOT /usr/bin/time -f "process wall %e s" timeout 280 python3 -m \
    tlvg_warp bench raster --garden "" --peers tlvg_warp,gsplat --repeats 5 --profile-reps 1 --out "$R/$name" "$@" \
    > "$R/$name.log" 2>&1 )
  grep "^|" "$R/$name.log" | tail -n 8; grep "process wall\|Error\|error" "$R/$name.log" | tail -n 3
}
for job in "$@"; do
  case "$job" in
    many) bench many --sizes 3000000,10000000,20000000;;
    4k) bench 4k --sizes 1000000,3000000 --size 3840x2160;;
    huge) bench huge25 --sizes 1000000 --log-scale -2.5; bench huge15 --sizes 100000 --log-scale -1.5;;
  esac
done
tar -czf "$OUT/stress_logs$TAG.tgz" -C "$R" $(cd "$R" && ls -d stress${TAG}_* 2>/dev/null)
