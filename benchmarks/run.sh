#!/usr/bin/env bash
# The one entry point for the GPU benchmarks: every figure in docs/performance.md (and the README's table) names
# the subcommand that reproduces it. Run from the repository root on a machine with an NVIDIA GPU.
set -uo pipefail
cd "$(dirname "$0")/.."

usage() {
  cat <<'EOF'
usage: bash benchmarks/run.sh SUBCOMMAND [ARGS]

  fit [NAME ...]     fit scenes with `reconstruct` (7000 iterations) and keep each as $FITS/NAME.spz: fern
                     (fern_llff, images_4), beer (beer_colmap), lego (lego_blender); default: those whose data is
                     present; FIT_ARGS go to each `reconstruct` (e.g. "--set render_headroom=0"). Reproduces: fit
                     time and held-out PSNR (performance.md, "Scene fitting").
  raster             `bench raster` on the fitted fern, beer and lego (every view) and a random 1M scene against
                     gsplat, REPS processes (default 2), each with gsplat in it. Reproduces: "Rasterizer on fitted
                     scenes" (ours / gsplat, peak memory, GPU time per stage, list lengths).
  stress [many] [4k] [huge]
                     random scenes of 3M-20M Gaussians, 4K frames and huge footprints against gsplat.
                     Reproduces: "Stress cases".
  stylize [--set K=V ...]
                     fern (fern.spz, 504x378, The Starry Night) stylized 3000 iterations, RUNS processes (default
                     2) after a 300-iteration warm-up; arguments go to each run, its folder fern_$TAG$i.
                     Reproduces: "Stylization" (process wall, flow alignment).
  startup            fern stylized for 1 iteration, twice (warm caches the second time): process wall against the
                     run's own wall, where the import time goes (python -X importtime), the process wall with the
                     fast exit against the interpreter's teardown (alternating, twice each), and the timeline from
                     the process's creation to the first iteration (benchmarks/startup_timeline.py), twice with and
                     twice without the CUDA warm-up. Reproduces: the 1-iteration figure of "Stylization", start-up.
  quality            `evaluate` on the runs of `stylize` (first 10 views, one ruler). Reproduces: "Stylization",
                     the quality row.
  demo               the CPU demo with empty kernel and weight caches (`python -m tlvg_warp stylize`).
                     Reproduces: "The demo".
  scaling [JOB ...]  one GPU against two of one host (benchmarks/scaling.sh: fit stylize nccl study table).
                     Reproduces: "Many GPUs".
  cuda-tests         the CUDA tests (rasterizer against the float64 reference; the graphed VGG, orientation and
                     stroke terms).
  host-profile [SCENE_SPEC] [fwd|fwd_bwd]
                     host against GPU timeline of one render (benchmarks/profile_host.py): where the GPU waits.
  cost-curves        time and peak memory of a stylize step and a fit step against Gaussians (0.1M-10M) and pixels (0.1-4 MP) on
                     random scenes (benchmarks/cost_curves.py; the chart and CSV under $OUT/cost_curves).
  outputs-profile SCENE [--views N] [--frames N]
                     where a run's outputs spend their time: the renders alone, beside the scene-file writers and
                     beside the views' encoding and scoring (benchmarks/profile_outputs.py).
  step-profile       is a fern stylize step host-bound? (benchmarks/profile_step.py: wall per step, GPU time
                     per step, top kernels; ARGS go to the run, e.g. --set terms_cuda_graphs=false; WARM, TIMED:
                     the steps timed without the profiler).
  fit-profile [ARGS] is a fern fit step (7000 iterations, images_4) host-bound? benchmarks/profile_step.py on
                     `reconstruct` (WARM, TIMED, CPROF as for step-profile; WARM=4000 TIMED=1000: after densification).
                     Reproduces: "Scene fitting", where a fit step goes.
  setup-profile [N]  where a stylize run's fixed costs go: cProfile of fern stylized for N iterations (default 30),
                     the package's functions by cumulative time (set-up, outputs, start-up).
  intersection-drift [ARGS]
                     fern stylized 3000 iterations with every training render's tile-intersection count recorded:
                     how far a view's count moves between visits (benchmarks/intersection_drift.py), the headroom a
                     buffer sized from the last visit would need.
  fit-vs-gsplat [ARGS]
                     fern (images_4, 7000 iterations) fitted by `reconstruct`'s fit and by a minimal trainer on
                     gsplat 1.5.3's rasterization and DefaultStrategy, same views, loss and schedule
                     (benchmarks/gsplat_trainer.py; ARGS go to it, e.g. --set density.max_gaussians=700000).
                     Reproduces: "Scene fitting", against gsplat.
  ssim               the fused SSIM against its torch twin on CUDA: differences and forward+backward time
                     (benchmarks/ssim_check.py). Reproduces: "Scene fitting", the fused loss.
  paint PART         the paintings study, every (scene, painting) pair with tlvg, abcgs and the anchors
                     (benchmarks/device_paint.sh; PART: carry, stage1, stage2, fit, study, wait, scene).
                     Reproduces: docs/study.md's current tables and gallery.
  study-table        the study's tables from its runs (benchmarks/study_table.py).
  field-agreement    on the CPU: does the palette transfer move the matched stroke field? (benchmarks/
                     field_agreement.py; docs/study.md, the ablations).
  field-vs-ruler PAINTING...
                     on the CPU: the training field against `evaluate`'s common field (benchmarks/field_vs_ruler.py).
  backbone-probe     on the CPU: does the VGG-16 backbone see brushstrokes? (benchmarks/backbone_probe.py;
                     docs/study.md).
  tone-spread RUN PAINTING
                     on the CPU: a run's luminance spread over all pixels, whole regions and strokes against the
                     painting's (benchmarks/tone_spread.py; docs/study.md).
  palette-clamp RUN PAINTING [FLOOR]
                     on the CPU: how much of the painting's luminance spread ARF's clamp takes from a run's photos,
                     and what arf_rank keeps (benchmarks/palette_clamp.py; docs/study.md).
  match-texture RUN PAINTING
                     on the CPU: how textured the painting cells are that a run's view matches (benchmarks/
                     match_texture.py; docs/study.md).
  footprints SCENE DATASET [--downscale F]
                     on the CPU: the share of the views that coarse splats paint, before and after the stroke-size
                     refinement (benchmarks/footprints.py; docs/study.md).
  gallery OUT.jpg PAIRS_DIR scene_painting:variants:label...
                     docs/gallery.jpg from the study's montages (benchmarks/gallery.py).

Environment: DATA (default /tmp/tlvg-data: fern_llff, beer_colmap, lego_blender, styles/starry_night.jpg),
FITS (default /tmp/tlvg-fits), OUT (default /tmp/tlvg-out: logs and JSON), TLVG_VGG_WEIGHTS (the pretrained
VGG-16; see docs/install.md). raster and stress need gsplat importable (e.g. `pip install gsplat`); a folder
/tmp/tlvg-gpu/site, when present, is put on PYTHONPATH for it.
EOF
}

D=${DATA:-/tmp/tlvg-data}; F=${FITS:-/tmp/tlvg-fits}; OUT=${OUT:-/tmp/tlvg-out}; R=/tmp/tlvg-runs
mkdir -p "$F" "$OUT" "$R"
export OUT PYTHONUNBUFFERED=1
# compiled bytecode kept between processes, as a pip install leaves it: under PYTHONDONTWRITEBYTECODE, with no .pyc in
# site-packages, every process compiles the modules it imports again (docs/performance.md: "compiled bytecode").
# BYTECODE=0 measures the environment as it is
if [ "${BYTECODE:-1}" = 1 ]; then
  unset PYTHONDONTWRITEBYTECODE; export PYTHONPYCACHEPREFIX=${PYTHONPYCACHEPREFIX:-/tmp/tlvg-pycache}
fi
[ -d /tmp/tlvg-gpu/site ] && export PYTHONPATH=/tmp/tlvg-gpu/site:$PWD${PYTHONPATH:+:$PYTHONPATH}
source "$(dirname "${BASH_SOURCE[0]}")/source_view.sh"; export PYTHONPATH=$(source_view .)${PYTHONPATH:+:$PYTHONPATH}  # kernels/ as tlvg_warp.kernels
[ -z "${TLVG_VGG_WEIGHTS:-}" ] && [ -f /tmp/tlvg-gpu/vgg16_hed.pt ] && export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt
FERN="--scene $F/fern.spz --data $D/fern_llff --downscale 2 --style $D/styles/starry_night.jpg"
metrics() { python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print({k: m.get(k) for k in sys.argv[2:]})" "$@"; }
gpu() { nvidia-smi --query-gpu=name,memory.total --format=csv,noheader; date -u; }

fit_one() {  # NAME DATASET [reconstruct arguments]
  local name=$1 data=$2; shift 2
  [ -d "$D/$data" ] || { echo "$name: $D/$data missing, skipped"; return; }
  /usr/bin/time -f "fit $name wall %e s" python3 -m tlvg_warp reconstruct "$D/$data" "$@" --iterations 7000 \
    --out "$R/fit_$name" --overwrite --quiet ${FIT_ARGS:-} > "$R/fit_$name.log" 2>&1; tail -n 1 "$R/fit_$name.log"
  metrics "$R/fit_$name/metrics.json" psnr ssim num_gaussians train_time_s wall_time_s
  python3 -c "import sys; from tlvg_warp.io.ply import load_ply; from tlvg_warp.io.splat_formats import save_spz; \
save_spz(load_ply(sys.argv[1]), sys.argv[2])" "$R/fit_$name/point_cloud.ply" "$F/$name.spz"
}

cmd=${1:-}; [ $# -gt 0 ] && shift
case "$cmd" in
  fit)
    gpu; [ $# -eq 0 ] && set -- fern beer lego
    for s in "$@"; do
      case "$s" in
        fern) fit_one fern fern_llff --images images_4;;
        beer) fit_one beer beer_colmap --images images;;
        lego) fit_one lego lego_blender;;
        *) echo "unknown scene $s (fern, beer, lego)";;
      esac
    done;;
  raster)
    gpu; SCENES=""
    [ -f "$F/fern.spz" ] && SCENES="$SCENES --scene $F/fern.spz:$D/fern_llff:images_4"
    [ -f "$F/beer.spz" ] && SCENES="$SCENES --scene $F/beer.spz:$D/beer_colmap:images"
    [ -f "$F/lego.spz" ] && SCENES="$SCENES --scene $F/lego.spz:$D/lego_blender"
    for i in $(seq 1 "${REPS:-2}"); do
      echo "== bench raster, process $i"
      timeout 300 python3 -m tlvg_warp bench raster --sizes 1000000 --garden "" --peers tlvg_warp,gsplat $SCENES \
        --repeats 10 --out "$R/bench_$i" > "$R/bench_$i.log" 2>&1
      grep "^|" "$R/bench_$i.log" | tail -n "${RASTER_ROWS:-10}"
    done
    tar -czf "$OUT/bench_logs.tgz" -C "$R" $(cd "$R" && ls -d bench_* 2>/dev/null);;
  stress) exec bash benchmarks/stress.sh "$@";;
  stylize)
    gpu
    python3 -m tlvg_warp stylize $FERN --iterations 300 --out "$R/warm" --overwrite --quiet > /dev/null 2>&1
    for i in $(seq 1 "${RUNS:-2}"); do
      n=fern_${TAG:-}$i
      /usr/bin/time -f "$n stylize 3000 wall %e s" python3 -m tlvg_warp stylize $FERN --iterations 3000 \
        --out "$R/$n" --overwrite --quiet "$@" > "$R/$n.log" 2>&1; tail -n 2 "$R/$n.log"
      metrics "$R/$n/metrics.json" wall_time_s train_time_s training_field_alignment time_per_phase_s
    done;;
  startup)
    gpu
    for i in 1 2; do
      /usr/bin/time -f "1-iteration stylize $i: process wall %e s" python3 -m tlvg_warp stylize $FERN --iterations 1 \
        --out "$R/one" --overwrite --quiet 2>&1 | tail -n 1
      metrics "$R/one/metrics.json" wall_time_s train_time_s outputs_time_s
    done
    python3 -X importtime -c "import tlvg_warp.cli, tlvg_warp.stylize.job" 2> "$R/importtime.txt"  # what stylize imports
    sort -t'|' -k2 -n "$R/importtime.txt" | tail -n 6
    for e in full fast full fast; do  # the process's end: `python -m tlvg_warp` (fast: os._exit after the outputs)
      # against the same command ended by the interpreter's teardown
      if [ $e = fast ]; then cmd=(-m tlvg_warp); else cmd=(-c 'import sys; from tlvg_warp.warmup import start_cuda_warmup
start_cuda_warmup(sys.argv[1:]); from tlvg_warp.cli import main; sys.exit(main())'); fi
      /usr/bin/time -f "1-iteration stylize, $e exit: process wall %e s" python3 "${cmd[@]}" stylize $FERN --iterations 1 \
        --out "$R/one" --overwrite --quiet 2>&1 | tail -n 1
    done
    for w in "" --no-warmup "" --no-warmup; do  # from the process's creation to the first iteration, mark by mark,
      # with and without the CUDA context made beside the imports
      echo "== timeline ${w:-with the warm-up}"
      python3 benchmarks/startup_timeline.py $w $FERN --iterations 1 --out "$R/one" --overwrite --quiet 2>&1 | tail -n 17
    done;;
  quality)
    runs=$(ls -d "$R"/fern_*/metrics.json 2>/dev/null | xargs -r -n1 dirname)
    [ -n "$runs" ] || { echo "no runs: run \`stylize\` first"; exit 1; }
    timeout 400 python3 -m tlvg_warp evaluate $runs --max-views 10 --out "$R/fern_eval" > "$R/fern_eval.log" 2>&1
    tail -n 24 "$R/fern_eval.log"; cp "$R/fern_eval/evaluation.json" "$OUT/" 2>/dev/null;;
  demo)
    tmp=$(mktemp -d)
    WARP_CACHE_PATH=$tmp/warp TLVG_CACHE_DIR=$tmp/tlvg /usr/bin/time -f "demo wall %e s" \
      python3 -m tlvg_warp stylize --out "$R/demo" --overwrite
    rm -rf "$tmp";;
  scaling) exec bash benchmarks/scaling.sh "$@";;
  cuda-tests) python3 -m pytest -q -p no:cacheprovider tests/test_raster_cuda.py tests/test_losses_vgg.py tests/test_losses_stroke.py \
    tests/test_losses_style.py::test_cuda_chunk_budget_changes_no_match \
    tests/test_losses_palette.py::test_the_smoothed_sliced_map_on_cuda_matches_the_cpu \
    tests/test_stroke_hinge.py::test_field_terms_as_a_cuda_graph_match_eager tests/test_stylize_graph.py::test_stylize_terms_as_one_cuda_graph_match_eager;;  # the other tests of those two files run Warp's CPU kernels
  host-profile) exec python3 benchmarks/profile_host.py "$@";;
  intersection-drift) exec python3 benchmarks/intersection_drift.py $FERN --iterations 3000 --out "$R/drift" --overwrite \
    --quiet "$@";;
  cost-curves) gpu; exec python3 benchmarks/cost_curves.py --out "$OUT/cost_curves" "$@";;
  outputs-profile) exec python3 benchmarks/profile_outputs.py "$@";;
  step-profile) exec python3 benchmarks/profile_step.py stylize -- $FERN --out "$R/profile" --overwrite --quiet "$@";;
  fit-profile) exec python3 benchmarks/profile_step.py reconstruct -- "$D/fern_llff" --images images_4 --iterations 7000 \
    --out "$R/fit_profile" --overwrite --quiet "$@";;
  setup-profile)
    python3 -m cProfile -o "$OUT/setup.prof" -m tlvg_warp stylize $FERN --iterations "${1:-30}" --out "$R/setup_run" \
      --overwrite --quiet > "$R/setup_run.log" 2>&1; tail -n 3 "$R/setup_run.log"
    metrics "$R/setup_run/metrics.json" wall_time_s setup_time_s train_time_s outputs_time_s
    python3 -c "import pstats, sys; s = pstats.Stats(sys.argv[1]); s.sort_stats('cumulative').print_stats(70)" \
      "$OUT/setup.prof" | grep -v "^$" | cut -c1-170;;
  ssim) exec python3 benchmarks/ssim_check.py;;
  tone-spread) exec python3 benchmarks/tone_spread.py "$@";;
  match-texture) exec python3 benchmarks/match_texture.py "$@";;
  palette-clamp) exec python3 benchmarks/palette_clamp.py "$@";;
  fit-vs-gsplat) gpu; TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16} exec python3 \
    benchmarks/gsplat_trainer.py "$D/fern_llff" --images images_4 --iterations 7000 --raster ours,gsplat --out "$OUT" "$@";;
  paint) PART=${1:?paint needs a PART} exec bash benchmarks/device_paint.sh;;
  study-table) exec python3 benchmarks/study_table.py "$@";;
  field-agreement) exec python3 benchmarks/field_agreement.py "$@";;
  field-vs-ruler) exec python3 benchmarks/field_vs_ruler.py "$@";;
  backbone-probe) exec python3 benchmarks/backbone_probe.py "$@";;
  footprints) exec python3 benchmarks/footprints.py "$@";;
  gallery) exec python3 benchmarks/gallery.py "$@";;
  -h|--help|help|"") usage;;
  *) echo "unknown subcommand: $cmd"; usage; exit 2;;
esac
