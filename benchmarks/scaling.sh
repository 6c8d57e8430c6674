#!/usr/bin/env bash
# Many GPUs: what a second GPU of the same host buys (2 GPUs, NCCL).
#   1. one-scene stylization: fern (fitted by reconstruct), 1 GPU with views_per_step=2 against
#      `torchrun --nproc-per-node 2` with views_per_step=1 (the same 2 views per step, the same iterations,
#      so the same total views); iterations/s from each run's train_time_s (the loop, not setup/outputs).
#      A 1-GPU views_per_step=1 run is the per-view reference.
#   2. study throughput: 4 jobs (fern x {starry_night, shipwreck} x {tlvg, abcgs}), 1 process on 1 GPU
#      against `torchrun --nproc-per-node 2 -m tlvg_warp study`, the whole launch timed (start-up,
#      stylizations, evaluations, report): jobs per minute.
#   3. NCCL: all-reduce of a fern-sized gradient (300k Gaussians x 59 floats), the per-step price of data
#      parallelism, and the GPUs' link (nvidia-smi topo).
# Needs /tmp/tlvg-data with fern_llff and styles/ (starry_night.jpg, shipwreck.jpg) and a converted VGG at
# $TLVG_VGG_WEIGHTS (default /tmp/tlvg-gpu/vgg16_hed.pt). Through the entry point:
#   bash benchmarks/run.sh scaling [stage] [fit] [stylize] [study] [nccl] [table]
# (`stage` alone: only copy a carried .gpu/vgg or .gpu/data to /tmp, in calls of their own: 64 MiB a call)
# No argument: all of them (about 8-9 minutes: fit ~55 s, warm-up ~30 s, stylize runs ~3 min, studies
# ~4 min). Split over two calls if needed: `fit stylize nccl` then `study table` (runs stay in /tmp while
# the machine is warm). ITS (default 1000) and STUDY_ITS (default 600) set the iterations. The table is last.
set -uo pipefail
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1  # NVLink multicast off
export TLVG_VGG_WEIGHTS=${TLVG_VGG_WEIGHTS:-/tmp/tlvg-gpu/vgg16_hed.pt}
source "$(dirname "${BASH_SOURCE[0]}")/source_view.sh"; export PYTHONPATH=$(source_view .)${PYTHONPATH:+:$PYTHONPATH}  # kernels/ as tlvg_warp.kernels
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
R=/tmp/tlvg-runs; S=$R/scaling; L=$S/logs; mkdir -p "$L"; D=/tmp/tlvg-data  # logs in $L; $OUT gets 3 files
ITS=${ITS:-1000}; STUDY_ITS=${STUDY_ITS:-600}
# STUDY_JOBS=8: two ablations more (4 configs x 2 paintings), so that fixed launch costs weigh less
STUDY_MORE=""; [ "${STUDY_JOBS:-4}" = 8 ] && STUDY_MORE=", no_density: $PWD/configs/ablation_no_density.yaml, rgb_loss: $PWD/configs/ablation_rgb_loss.yaml"
TR="python3 -m torch.distributed.run --standalone --nproc-per-node 2"
FERN="--scene $R/fern/point_cloud.ply --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
QUICK="--quiet --overwrite --set orbit_frames=0 --set comparison_views=1 --set checkpoint_seconds=0 --set loss.fast_refresh=1"  # reuse off: ranks do not share it
now() { date +%s.%N; }
[ $# -eq 0 ] && set -- fit stylize nccl study table
# staging: a call that carries .gpu/vgg or .gpu/data copies it to /tmp (kept while warm)
[ -d .gpu/vgg ] && mkdir -p /tmp/tlvg-gpu && cp .gpu/vgg/*.pt "$TLVG_VGG_WEIGHTS"
[ -d .gpu/data ] && mkdir -p $D && cp -r .gpu/data/* $D/
[ "$*" = stage ] && { ls -la "$TLVG_VGG_WEIGHTS" $D 2>&1; exit 0; }
[ -f "$TLVG_VGG_WEIGHTS" ] && [ -d $D/fern_llff ] && [ -d $D/styles ] || { echo "weights or data not staged"; exit 1; }
nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader | tee "$L/gpus.txt"
python3 -c 'import torch, sys; n = torch.cuda.device_count(); print("torch", torch.__version__, "GPUs", n); sys.exit(n < 2)' \
  || { echo "needs 2 GPUs of one host"; exit 1; }

for job in "$@"; do
  case "$job" in
    fit)
      [ -f "$R/fern/point_cloud.ply" ] || CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp reconstruct $D/fern_llff \
        --images images_4 --iterations 7000 --out "$R/fern" --overwrite --quiet > "$L/fern_fit.log" 2>&1
      ls -la "$R/fern/point_cloud.ply" || { tail -n 20 "$L/fern_fit.log"; exit 1; };;
    stylize)
      # warm-up: compiles/loads every Warp module and the converted weights once (not measured)
      CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp stylize $FERN $QUICK --iterations 20 --out "$S/warmup" \
        > "$L/warmup.log" 2>&1 || tail -n 20 "$L/warmup.log"
      for run in g1v1 g1v2 g2v1; do
        case $run in
          g1v1) cmd="env CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp"; vps=1;;
          g1v2) cmd="env CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp"; vps=2;;
          g2v1) cmd="env CUDA_VISIBLE_DEVICES=0,1 $TR -m tlvg_warp"; vps=1;;
        esac
        t0=$(now)
        $cmd stylize $FERN $QUICK --iterations "$ITS" --set views_per_step=$vps --out "$S/$run" > "$L/$run.log" 2>&1
        rc=$?; t1=$(now)
        echo "{\"rc\": $rc, \"wall_s\": $(awk "BEGIN{print $t1 - $t0}")}" > "$S/$run.launch.json"
        echo "$run rc $rc"; tail -n 2 "$L/$run.log"
      done;;
    nccl)
      nvidia-smi topo -m 2>&1 | head -n 8 | tee "$L/topo.txt"
      cat > "$S/nccl.py" <<'PY'
import json, os, time, torch
from tlvg_warp.distributed import Dist
d = Dist.from_env("cuda")
n = 300_000 * 59  # fern's Gaussians x floats per Gaussian (means 3, quats 4, scales 3, opacity 1, SH 48)
grads = [torch.randn(300_000, k, device=d.device) for k in (3, 4, 3, 1, 48)]
for _ in range(5):
    d.all_reduce_mean_(grads)
torch.cuda.synchronize()
t = time.perf_counter()
for _ in range(20):
    d.all_reduce_mean_(grads)
torch.cuda.synchronize()
ms = (time.perf_counter() - t) / 20 * 1e3
if d.is_main:
    res = {"all_reduce_ms": round(ms, 3), "MB": round(n * 4 / 1e6, 1),
           "bus_GBps": round(2 * (d.world - 1) / d.world * n * 4 / (ms / 1e3) / 1e9, 1)}
    print("NCCL", json.dumps(res))
    open("/tmp/tlvg-runs/scaling/nccl.json", "w").write(json.dumps(res))
d.shutdown()
PY
      $TR "$S/nccl.py" > "$L/nccl.log" 2>&1; grep -v "^W1\|OMP_NUM_THREADS\|^\*\*" "$L/nccl.log" | tail -n 5;;
    study)
      for n in 1 2; do
        rm -rf "$S/study$n"; mkdir -p "$S/study$n/out/scenes/fern"
        cp "$R/fern/point_cloud.ply" "$S/study$n/out/scenes/fern/"  # fitted once already: jobs are stylizations
        cat > "$S/study$n/study.yaml" <<EOF
out: out
device: cuda
iterations: $STUDY_ITS
max_views: 8
set: [orbit_frames=0, comparison_views=1, checkpoint_seconds=0]
configs: {tlvg: $PWD/configs/tlvg.yaml, abcgs: $PWD/configs/abcgs.yaml$STUDY_MORE}
ours: tlvg
baseline: abcgs
scenes: {fern: {data: $D/fern_llff, downscale: 2}}
paintings: {starry_night: $D/styles/starry_night.jpg, shipwreck: $D/styles/shipwreck.jpg}
EOF
        if [ $n = 1 ]; then cmd="env CUDA_VISIBLE_DEVICES=0 python3 -m tlvg_warp"; else cmd="env CUDA_VISIBLE_DEVICES=0,1 $TR -m tlvg_warp"; fi
        t0=$(now)
        $cmd study "$S/study$n/study.yaml" > "$L/study$n.log" 2>&1
        rc=$?; t1=$(now)
        echo "{\"rc\": $rc, \"wall_s\": $(awk "BEGIN{print $t1 - $t0}")}" > "$S/study$n.launch.json"
        echo "study on $n GPU(s): rc $rc"; tail -n 3 "$L/study$n.log"
      done;;
    table)
      python3 - "$S" <<'PY' | tee "$OUT/table.txt"
import json, sys
from pathlib import Path
S = Path(sys.argv[1])
def js(p):
    try:
        return json.loads(Path(p).read_text())
    except (OSError, ValueError):
        return {}
rows = {}
for run, vps, gpus in (("g1v1", 1, 1), ("g1v2", 2, 1), ("g2v1", 1, 2)):
    m, l = js(S / run / "metrics.json"), js(S / f"{run}.launch.json")
    if m.get("train_time_s"):
        its = m["iterations"] / m["train_time_s"]
        rows[run] = {"its": its, "views_s": its * vps * gpus, "train_s": m["train_time_s"], "wall_s": l.get("wall_s"),
                     "flow": m.get("flow_alignment"), "gaussians": m.get("gaussians_final"),
                     "phases": m.get("time_per_phase_s")}
        print(f"{run}: {gpus} GPU(s) x views_per_step {vps}: {m['iterations']} its in {m['train_time_s']:.1f} s "
              f"loop ({l.get('wall_s', 0):.1f} s launch) = {its:.2f} it/s, {its * vps * gpus:.1f} views/s; "
              f"phases {m.get('time_per_phase_s')}; flow alignment {m.get('flow_alignment'):.4f}, "
              f"Gaussians {m.get('gaussians_final')}")
studies = {}
for n in (1, 2):
    l, res = js(S / f"study{n}.launch.json"), js(S / f"study{n}" / "out" / "study.json")
    if l.get("wall_s") and res:
        jobs = sum(v == "ran" for v in res["status"].values())
        studies[n] = {"jobs": jobs, "wall_s": l["wall_s"], "jpm": 60 * jobs / l["wall_s"]}
        print(f"study on {n} GPU(s): {jobs} jobs in {l['wall_s']:.1f} s = {60 * jobs / l['wall_s']:.2f} jobs/min; "
              f"status {res['status']}; stylized by {res.get('ranks', {}).get('stylized_by')}")
nccl = js(S / "nccl.json")
if nccl:
    print(f"NCCL all-reduce of {nccl['MB']} MB (fern's gradients): {nccl['all_reduce_ms']} ms, bus {nccl['bus_GBps']} GB/s")
print("\n| measure | 1 GPU | 2 GPUs | speed-up | goal |")
print("| --- | --- | --- | --- | --- |")
if "g1v2" in rows and "g2v1" in rows:
    a, b = rows["g1v2"], rows["g2v1"]
    print(f"| fern stylization, 2 views/step (it/s) | {a['its']:.2f} | {b['its']:.2f} | {b['its'] / a['its']:.2f}x | >= 1.6x |")
if "g1v1" in rows and "g2v1" in rows:
    a, b = rows["g1v1"], rows["g2v1"]
    print(f"| fern views/s (1 GPU at 1 view/step) | {a['views_s']:.1f} | {b['views_s']:.1f} | {b['views_s'] / a['views_s']:.2f}x | |")
if 1 in studies and 2 in studies:
    a, b = studies[1], studies[2]
    print(f"| study, {a['jobs']} jobs (jobs/min, whole launch) | {a['jpm']:.2f} | {b['jpm']:.2f} | {b['jpm'] / a['jpm']:.2f}x | >= 1.9x |")
json.dump({"stylize": rows, "study": studies, "nccl": nccl}, open(S / "scaling.json", "w"), indent=1)
PY
      cp "$S/scaling.json" "$OUT/" 2>/dev/null
      for f in "$L"/*; do echo "== $f"; tail -n 15 "$f"; done > "$OUT/logs.txt" 2>&1;;
  esac
done
