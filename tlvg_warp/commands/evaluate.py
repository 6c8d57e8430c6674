"""`python -m tlvg_warp evaluate RUN [RUN ...]`: SPEC §4 metrics of stylization runs of one scene and painting,
all measured with one ruler (eval/refs.py builds the references from the un-stylized scene, the views, the
photos and the painting; nothing a run stored about its own targets is read).

A run folder gives stylized.ply, cameras.json, photos/, style.png (or config.yaml's style), metrics.json
(times, counts) and orbit.mp4. The un-stylized scene: --scene, else the one the run's checkpoint.pt names,
else RUN/reconstruct/point_cloud.ply, else the built-in demo (at the density the run used) when the run was made
on it. Beside the runs, the same ruler scores two anchors that evaluate builds itself: the un-stylized scene
("no stylization") and the painting pasted over every view ("sticker"); a run wins a metric only where it also
beats the anchor that metric exists to beat (eval/metrics.py ANCHOR_TO_BEAT). Writes evaluation.json and
evaluation.html (self-contained) to --out; a line per stage goes to stderr.
"""
from __future__ import annotations

from pathlib import Path

import torch

from ..errors import InputError
from ..eval import CPU_MAX_VIEWS, DEFAULT_EVAL_HEIGHT, MIN_EVAL_HEIGHT, default_cache
from ..fileio import write_json, write_text


def add_arguments(p):
    p.add_argument("runs", nargs="+", metavar="RUN", help="stylization run folders of one scene and painting")
    p.add_argument("--against", action="append", default=[], metavar="RUN", help="alias: one more run to score")
    p.add_argument("--scene", default=None, metavar="PLY", help="the un-stylized scene (default: from the runs)")
    p.add_argument("--vgg-weights", default=None, help="VGG-16 weights path, 'hed', or 'random' (then style and "
                   "content metrics are not measured)")
    p.add_argument("--out", default=None, help="folder for evaluation.json/.html (default: RUN for one run, "
                   "else RUN's parent/evaluation)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--max-views", type=int, default=None,
                   help=f"evaluate only the first N cameras (0: all; default: all on a GPU, the first {CPU_MAX_VIEWS} on "
                        "a CPU, where every view costs seconds)")
    p.add_argument("--eval-height", type=int, default=None, help="height of the style/content evaluation size "
                   f"(default: the views' height, between {MIN_EVAL_HEIGHT} and {DEFAULT_EVAL_HEIGHT})")
    p.add_argument("--cache", default=None, help=f"reference cache folder (default {default_cache()})")


def run(args) -> int:
    # what an evaluation runs (OpenCV, Warp) loads here, not when the parser is built
    from ..eval.engine import evaluate_runs, pick_weights, print_table, report_html, stage_logger
    from ..losses.vgg import load_vgg

    log = stage_logger()
    dirs = list(dict.fromkeys([*args.runs, *args.against]))
    if args.eval_height is not None and args.eval_height < 16:
        raise InputError(f"--eval-height must be at least 16, got {args.eval_height}")
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    out = Path(args.out) if args.out else (Path(dirs[0]) if len(dirs) == 1 else Path(dirs[0]).parent / "evaluation")
    log(f"loading VGG-16 on {device}")
    net = load_vgg(pick_weights(args.vgg_weights, dirs), device=device)
    max_views = args.max_views
    if max_views is None:
        max_views = CPU_MAX_VIEWS if device.type == "cpu" else 0
        if max_views:
            log(f"on the CPU: the first {max_views} views of each run (--max-views 0 scores all)")
    res, runs, refs = evaluate_runs(dirs, net, device, scene=args.scene, max_views=max_views,
                                    eval_height=args.eval_height, log=log,
                                    cache_dir=Path(args.cache) if args.cache else default_cache())
    write_json(out / "evaluation.json", res)
    log("writing the report")
    write_text(out / "evaluation.html", report_html(res, runs, refs))
    log("done")
    print_table(res)
    if net.is_random:
        print("note: VGG-16 weights are random: style, content and flow alignment are not measured")
    print(f"wrote {out / 'evaluation.json'} and {out / 'evaluation.html'}")
    return 0
