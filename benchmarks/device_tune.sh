#!/usr/bin/env bash
# On the lent GPU (after ../shared/gpu's two staging calls): `source /tmp/tlvg-gpu/env.sh && bash
# benchmarks/device_tune.sh PART` where PART is `fit` (copy the carried data and weights to /tmp, fit the
# scenes, return them as SPZ), `tune` (the variants of benchmarks/tune.py on fern) or `study`.
# Carried folders (ignored by git): .carry/vgg/vgg16_hed_fp16.pt, .carry/data/{scenes,styles}, .carry/fits/*.spz.
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
D=/tmp/tlvg-data; F=/tmp/tlvg-fits; R=/tmp/tlvg-runs; mkdir -p "$D" "$F" "$R"
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt PYTHONUNBUFFERED=1
source "$(dirname "${BASH_SOURCE[0]}")/source_view.sh"; export PYTHONPATH=$(source_view .)${PYTHONPATH:+:$PYTHONPATH}  # kernels/ as tlvg_warp.kernels
if [ -f .carry/vgg/vgg16_hed_fp16.pt ] && [ ! -f "$TLVG_VGG_WEIGHTS" ]; then
  python3 -c "import torch,sys; sd=torch.load(sys.argv[1], weights_only=True); torch.save({k: v.float() for k, v in sd.items()}, sys.argv[2])" \
    .carry/vgg/vgg16_hed_fp16.pt "$TLVG_VGG_WEIGHTS"
fi
[ -d .carry/data ] && cp -r .carry/data/* "$D/"
[ -d .carry/data2 ] && cp -r .carry/data2/* "$D/"
[ -d .carry/fits ] && cp .carry/fits/*.spz "$F/" 2>/dev/null
[ -d .carry/fits2 ] && cp .carry/fits2/*.spz "$F/" 2>/dev/null
[ -d .carry/styles ] && cp -r .carry/styles/* "$D/"
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
  tune)  # the tuning split: fern x (starry_night, shipwreck)
    shift
    C="loss.w_style_color=1.0;style_height=0;stroke_scale=2;loss.w_tv=0;loss.w_align=0.5;loss.w_aniso=0.05"
    V=(--variant "tlvg:" --variant "abcgs:config=configs/abcgs.yaml"
       --variant "abcgs_split:config=configs/abcgs.yaml;density.size_rules=split"
       --variant "color:loss.w_style_color=1.0" --variant "big:style_height=0;stroke_scale=2"
       --variant "nnfm:loss.style_loss=nnfm" --variant "combo:$C" --variant "combo_nnfm:$C;loss.style_loss=nnfm"
       --variant "combo_s2:$C;loss.strength=2")
    B="loss.w_content=0.001;loss.strength=4;loss.w_style_color=2;style_height=0;stroke_scale=2;loss.w_tv=0"
    FREE="loss.w_scale_reg=0;loss.w_opacity_reg=0"
    [ "${ROUND:-1}" = 2 ] && V=(--variant "tlvg:" --variant "abcgs_split:config=configs/abcgs.yaml;density.size_rules=split"
       --variant "bold:$B" --variant "bold_free:$B;$FREE" --variant "bold_nnfm:$B;loss.style_loss=nnfm"
       --variant "bold_free_nnfm:$B;$FREE;loss.style_loss=nnfm" --variant "nolab:loss.w_lab_start=0;loss.w_lab_end=0"
       --variant "nodens:density.phases=[pre]" --variant "rgb:loss.luminance_only=false;loss.w_lab_start=0;loss.w_lab_end=0"
       --variant "keepc:keep_colors=true")
    B2="loss.style_loss=nnfm;$B"; AL="loss.w_align=8;loss.w_aniso=0.8"
    [ "${ROUND:-1}" = 3 ] && V=(--variant "tlvg:" --variant "abcgs_split:config=configs/abcgs.yaml;density.size_rules=split"
       --variant "r3a:$B2;loss.w_chroma_tv=1" --variant "r3b:$B2;loss.w_chroma_tv=10"
       --variant "r3c:$B2;loss.w_chroma_tv=3;$AL" --variant "r3d:$B2;loss.w_chroma_tv=3;$AL;$FREE"
       --variant "r3e:$B2;loss.w_chroma_tv=3;$AL;loss.strength=2")
    timeout "${TUNE_LIMIT:-520}" python3 benchmarks/tune.py --scene "$F/fern.spz" --data "$D/scenes/fern_llff" \
      --styles "${STYLES:-$D/styles/starry_night.jpg,$D/styles/shipwreck.jpg}" --out "$R/tune" "${V[@]}" "$@" 2>&1 \
      | grep -v "^Module\|^Warp" | tail -n 80
    ;;
  tune4)  # round 4 (ROUND=5: the style term; ROUND=6: the Gram term; ROUND=7: the coverage hinge), the stroke-size refinement: TUNE_SCENE=name:dataset:downscale x (starry_night, shipwreck)
    shift
    for spec in ${TUNE_SCENE:-beer:beer_colmap:2}; do
    IFS=: read -r s d ds <<< "$spec"
    V=(--variant "tlvg:" --variant "ref8:refine_radius=8" --variant "ref4:refine_radius=4"
       --variant "ref8_c3:refine_radius=8;loss.w_content=0.003" --variant "ref8_nopre:refine_radius=8;density.phases=[stylize]")
    [ "${ROUND:-4}" = 5 ] && V=(--variant "ref8:refine_radius=8" --variant "gram:refine_radius=8;loss.style_loss=gram"
       --variant "fast:refine_radius=8;loss.style_loss=fast" --variant "rgb:refine_radius=8;loss.luminance_only=false"
       --variant "s2:refine_radius=8;loss.strength=2" --variant "vgg1:refine_radius=8;vgg_scale=1.0")
    [ "${ROUND:-4}" = 6 ] && V=(--variant "ref8:refine_radius=8" --variant "g05:refine_radius=8;loss.w_style_gram=0.5"
       --variant "g15:refine_radius=8;loss.w_style_gram=1.5")
    [ "${ROUND:-4}" = 7 ] && V=(--variant "tlvg:" --variant "cov1:loss.w_coverage=1" --variant "cov10:loss.w_coverage=10")
    timeout "${TUNE_LIMIT:-540}" python3 benchmarks/tune.py --scene "$F/$s.spz" --data "$D/scenes/$d" --downscale "$ds" \
      --styles "${TUNE_STYLES:-$D/styles/starry_night.jpg,$D/styles/shipwreck.jpg}" --out "$R/tune4_$s" "${V[@]}" \
      --montage "$OUT/tune4_$s.jpg" --view "${VIEW:-0}" "$@" 2>&1 | grep -v "^Module\|^Warp\|^open \|^orbit\|^\[evaluate" | tail -n 60
    done
    ;;
  validate)  # tlvg and abcgs with the anchors on VALIDATE="scene:dataset:downscale:painting,painting ..."
    for spec in ${VALIDATE:-lego:lego_blender:0:starry_night.jpg}; do
      IFS=: read -r s d ds st <<< "$spec"
      styles=$(echo "$st" | tr ',' '\n' | sed "s|^|$D/styles/|" | paste -sd, -)
      timeout "${TUNE_LIMIT:-560}" python3 benchmarks/tune.py --scene "$F/$s.spz" --data "$D/scenes/$d" --downscale "$ds" \
        --styles "$styles" --out "$R/validate_$s" --variant "tlvg:" --variant "abcgs:config=configs/abcgs.yaml" \
        --montage "$OUT/validate_$s.jpg" --view "${VIEW:-0}" 2>&1 | grep -v "^Module\|^Warp\|^open \|^orbit\|^\[evaluate" | grep -v "^/tmp\|^run /tmp"
      (cd "$R" && tar -czf "$OUT/validate_$s.tgz" $(ls -d validate_$s/*/evaluation/evaluation.json validate_$s/*/*/metrics.json 2>/dev/null))
    done
    ;;
  study)  # the study: fern, beer, lego x the four paintings; abcgs and tlvg everywhere, the ablations on the
          # tuning pairs (fern x starry_night, shipwreck). STUDY_PART: abcgs | tlvg | eval
    P="$D/styles/starry_night.jpg,$D/styles/shipwreck.jpg,$D/styles/starry_night_over_the_rhone.png,$D/styles/monet_san_giorgio.jpg"
    ABL=(--variant "no_advection:config=configs/ablation_no_advection.yaml" --variant "rgb_loss:config=configs/ablation_rgb_loss.yaml"
         --variant "no_density:config=configs/ablation_no_density.yaml" --variant "canvas_field:config=configs/ablation_canvas_field.yaml")
    for spec in ${STUDY_SCENES:-fern:fern_llff:0 beer:beer_colmap:2 lego:lego_blender:0}; do
      IFS=: read -r s d ds <<< "$spec"
      args=(--scene "$F/$s.spz" --data "$D/scenes/$d" --downscale "$ds" --out "$R/study/$s")
      case "${STUDY_PART:-abcgs}" in
        abcgs) python3 benchmarks/tune.py "${args[@]}" --styles "$P" --phase run --variant "abcgs:config=configs/abcgs.yaml" ;;
        tlvg) python3 benchmarks/tune.py "${args[@]}" --styles "$P" --phase run --variant "tlvg:"
              [ "$s" = fern ] && python3 benchmarks/tune.py "${args[@]}" --styles "$D/styles/starry_night.jpg,$D/styles/shipwreck.jpg" --phase run "${ABL[@]}" ;;
        eval) python3 benchmarks/tune.py "${args[@]}" --styles "$P" --phase eval --variant "abcgs:" --variant "tlvg:" "${ABL[@]}" \
                --montage "$OUT/study_$s.jpg" --view "${VIEW:-0}" ;;
      esac
    done 2>&1 | grep -v "^Module\|^Warp\|^open \|^orbit\|^\[evaluate" | tail -n 150
    (cd "$R/study" && tar -czf "$OUT/study_eval.tgz" $(ls -d */*/evaluation/evaluation.json */*/*/metrics.json 2>/dev/null))
    ;;
  controls)  # the stylize controls on fern x The Starry Night: --strength, --stroke-scale, --keep-colors
    timeout 560 python3 benchmarks/tune.py --scene "$F/fern.spz" --data "$D/scenes/fern_llff" \
      --styles "$D/styles/starry_night.jpg" --out "$R/controls" --variant "tlvg:" --variant "strength_0.5:loss.strength=0.5" \
      --variant "strength_2:loss.strength=2" --variant "stroke_1:stroke_scale=1" --variant "stroke_4:stroke_scale=4" \
      --variant "keep_colors:keep_colors=true" --montage "$OUT/controls.jpg" --view 3 2>&1 | grep "^|\|^run\|^evaluate" | tail -30
    (cd "$R/controls" && tar -czf "$OUT/controls_eval.tgz" $(ls -d */evaluation/evaluation.json */*/metrics.json 2>/dev/null))
    ;;
esac
