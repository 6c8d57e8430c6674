#!/usr/bin/env bash
# Flow-term weights on the demo (GPU): abcgs vs tlvg at several w_align / w_aniso; prints flow alignment.
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
run() {  # name, args...
  local name=$1; shift
  python3 -m tlvg_warp stylize --vgg-weights random --quiet --out "$OUT/sweep_$name" "$@" > "$OUT/sweep_$name.log" 2>&1 \
    || { echo "$name failed"; tail -3 "$OUT/sweep_$name.log"; }
}
run abcgs --config configs/abcgs.yaml
run tlvg --config configs/tlvg.yaml
run tlvg_a0.5 --config configs/tlvg.yaml --set w_align=0.5 --set w_aniso=0.05
run tlvg_a2 --config configs/tlvg.yaml --set w_align=2.0 --set w_aniso=0.2
run tlvg_a2_canvas --config configs/tlvg.yaml --set w_align=2.0 --set w_aniso=0.2 --set field_mapping=canvas
run tlvg_a8 --config configs/tlvg.yaml --set w_align=8.0 --set w_aniso=0.5
python3 - "$OUT" <<'PY'
import json, sys, pathlib
for d in sorted(pathlib.Path(sys.argv[1]).glob("sweep_*")):
    if d.is_dir() and (d / "metrics.json").exists():
        m = json.loads((d / "metrics.json").read_text())
        print(f"{d.name:22s} flow {m.get('flow_alignment'):.4f}  orig {m.get('flow_alignment_original', float('nan')) if isinstance(m.get('flow_alignment_original'), float) else m.get('flow_alignment_original')}"
              f"  gaussians {m.get('gaussians_final')}  train {m.get('train_time_s'):.1f}s")
PY
for d in "$OUT"/sweep_*/; do rm -rf "$d/fields" "$d/checkpoint.pt" "$d/renders" "$d/originals" "$d/photos" "$d/orbit.mp4" "$d/stylized.ply"; done
