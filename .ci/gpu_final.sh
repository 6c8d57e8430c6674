#!/usr/bin/env bash
# Issues 15 + 18 in ONE call on nvidia-h200-x2 (device time was short): GPU0 fits fern while GPU1 runs the CUDA
# tests; then GPU0 benchmarks the rasterizers on fitted fern (every view) + random 1M against gsplat while GPU1 times
# a 3000-iteration fern stylization (and evaluates it: holes, flow); then one-scene scaling: 1 GPU x 2 views per
# step against torchrun 2 ranks x 1 view (ITS iterations). Tables under $OUT.
# On the device: source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_final.sh
set -uo pipefail
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
R=/tmp/tlvg-runs; S=$R/scaling; mkdir -p "$S"; D=/tmp/tlvg-data; ITS=${ITS:-1000}
FERN="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
QUICK="--quiet --overwrite --set orbit_frames=0 --set comparison_views=1 --set checkpoint_seconds=0"
nvidia-smi --query-gpu=index,name --format=csv,noheader
# 1. fit fern (GPU0) | CUDA tests + gsplat's extension build (GPU1)
( CUDA_VISIBLE_DEVICES=0 /usr/bin/time -f "fern fit wall %e s" python3 -m tlvg_warp reconstruct $D/fern_llff --images images_4 \
    --iterations 7000 --out "$R/fern" --overwrite --quiet > "$OUT/fit.log" 2>&1 ) &
( CUDA_VISIBLE_DEVICES=1 python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py > "$OUT/tests.txt" 2>&1
  CUDA_VISIBLE_DEVICES=1 python3 -c "import gsplat, torch; from gsplat import rasterization" > /dev/null 2>&1 ) &
wait; tail -n 2 "$OUT/fit.log"; tail -n 2 "$OUT/tests.txt"
python3 -c "import json; m=json.load(open('$R/fern/metrics.json')); print({k: m.get(k) for k in ('psnr','num_gaussians','train_time_s','wall_time_s','time_split')})"
# 2. raster bench (GPU0) | stylize 3000 + evaluate (GPU1)
( CUDA_VISIBLE_DEVICES=0 timeout 300 python3 -m tlvg_warp bench raster --sizes 1000000 --garden "" --peers tlvg_warp,gsplat \
    --scene "$R/fern/point_cloud.ply:$D/fern_llff:images_4" --repeats 10 --out "$OUT/bench" > "$OUT/bench.log" 2>&1 ) &
( CUDA_VISIBLE_DEVICES=1 /usr/bin/time -f "fern stylize 3000 wall %e s" python3 -m tlvg_warp stylize $FERN --out "$R/fern_tlvg" \
    --overwrite --quiet > "$OUT/stylize.log" 2>&1
  CUDA_VISIBLE_DEVICES=1 timeout 200 python3 -m tlvg_warp evaluate "$R/fern_tlvg" --max-views 5 --out "$R/fern_eval" > "$OUT/eval.log" 2>&1
  cp "$R/fern_eval/evaluation.json" "$OUT/" 2>/dev/null ) &
wait
tail -n 3 "$OUT/stylize.log"
python3 -c "import json; m=json.load(open('$R/fern_tlvg/metrics.json')); print({k: m[k] for k in m if 'time' in k or 'gaussians' in k or 'stage' in k})"
grep -i "holes\|flow" "$OUT/eval.log" | head -n 12
grep -v "^Module\|^{" "$OUT/bench.log" | tail -n 45
# 3. one-scene scaling (both GPUs)
now() { date +%s.%N; }
for run in g1v2 g2v1; do
  case $run in
    g1v2) cmd="env CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp"; vps=2;;
    g2v1) cmd="env CUDA_VISIBLE_DEVICES=0,1 python3 -m torch.distributed.run --standalone --nproc-per-node 2 -m tlvg_warp"; vps=1;;
  esac
  t0=$(now); timeout 200 $cmd stylize $FERN $QUICK --iterations "$ITS" --set views_per_step=$vps --out "$S/$run" > "$OUT/$run.log" 2>&1
  rc=$?; t1=$(now)
  python3 -c "import json; m=json.load(open('$S/$run/metrics.json')); its=m['iterations']/m['train_time_s']; print('$run rc $rc', 'launch %.1f s' % ($t1-$t0), 'train %.1f s' % m['train_time_s'], '%.2f it/s' % its, 'phases', m.get('time_per_phase_s'), 'flow', m.get('flow_alignment'), 'gaussians', m.get('gaussians_final'))" 2>&1 | tail -n 1 | tee -a "$OUT/scaling.txt"
  [ $rc = 0 ] || tail -n 8 "$OUT/$run.log"
done
