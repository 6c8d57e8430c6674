#!/usr/bin/env bash
# On the lent GPU (after ../shared/gpu's two staging calls): `source /tmp/tlvg-gpu/env.sh && bash
# benchmarks/device_tune.sh PART` where PART is `fit` (copy the carried data and weights to /tmp, fit the
# scenes, return them as SPZ), `tune` (the variants of benchmarks/tune.py on fern) or `study`.
# Carried folders (ignored by git): .carry/vgg/vgg16_hed_fp16.pt, .carry/data/{scenes,styles}, .carry/fits/*.spz.
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
D=/tmp/tlvg-data; F=/tmp/tlvg-fits; R=/tmp/tlvg-runs; mkdir -p "$D" "$F" "$R"
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
if [ -f .carry/vgg/vgg16_hed_fp16.pt ] && [ ! -f "$TLVG_VGG_WEIGHTS" ]; then
  python3 -c "import torch,sys; sd=torch.load(sys.argv[1], weights_only=True); torch.save({k: v.float() for k, v in sd.items()}, sys.argv[2])" \
    .carry/vgg/vgg16_hed_fp16.pt "$TLVG_VGG_WEIGHTS"
fi
[ -d .carry/data ] && cp -r .carry/data/* "$D/"
[ -d .carry/fits ] && cp .carry/fits/*.spz "$F/" 2>/dev/null
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
date -u
fit() {  # fit DATASET NAME: reconstruct (7000 iterations), then an SH-0 SPZ copy that comes back under $OUT
  [ -f "$F/$2.spz" ] && return
  /usr/bin/time -f "fit $2 wall %e s" python3 -m tlvg_warp reconstruct "$D/scenes/$1" --out "$R/fit_$2" --overwrite --quiet 2>&1 | tail -n 3
  python3 -c "
import sys; from tlvg_warp.io.ply import load_ply; from tlvg_warp.io.splat_formats import save_spz
g = load_ply(sys.argv[1]); save_spz(g.with_sh_degree(0), sys.argv[2]); print(sys.argv[2], g.num)" \
    "$R/fit_$2/point_cloud.ply" "$F/$2.spz"
  cp "$F/$2.spz" "$OUT/"
}
case "${1:-tune}" in
  fit) shift; for s in "$@"; do fit "${s%%:*}" "${s##*:}"; done ;;
  tune)
    shift
    timeout "${TUNE_LIMIT:-520}" python3 benchmarks/tune.py --scene "$F/fern.spz" --data "$D/scenes/fern_llff" \
      --styles "$D/styles/starry_night.jpg,$D/styles/shipwreck.jpg" --out "$R/tune" "$@" 2>&1 | grep -v "^Module\|^Warp" | tail -n 80
    ;;
esac
