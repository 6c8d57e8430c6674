"""`python -m tlvg_warp reconstruct DATA --out DIR`: fit a 3DGS scene to posed photos.

Writes DIR/point_cloud.ply (INRIA layout), DIR/cameras.json (INRIA), DIR/config.yaml (resolved),
DIR/test/*.png (held-out renders), DIR/metrics.json (top-level ``psnr`` = mean over held-out views) and
DIR/checkpoint.pt while the run is unfinished (or with --keep-checkpoint). Ctrl-C saves a checkpoint and the PLY;
``--resume DIR`` continues."""
from __future__ import annotations

import contextlib
import sys
from pathlib import Path

from ..errors import InputError
from ..runs import resolve_device, run_folder
from ..runs import drop_checkpoints
from . import KEEP_CHECKPOINT_HELP, check_resumable, peak_memory_note


def add_arguments(p):
    p.add_argument("data", metavar="DATA",
                   help="dataset folder (COLMAP, LLFF, Blender or INRIA; see load_dataset) or 'demo' for the built-in scene")
    p.add_argument("--out", default=None, help="output folder (default: the --resume folder)")
    p.add_argument("--config", default=None,
                   help="YAML config (e.g. configs/reconstruct.yaml, found by name from any folder); default: the "
                        "built-in defaults, which it mirrors")
    p.add_argument("--iterations", type=int, default=None, help="optimizer steps (config: iterations)")
    p.add_argument("--downscale", type=float, default=None, help="image downscale factor (config: downscale)")
    p.add_argument("--images", default=None, help="image sub-folder, e.g. images_8 (config: images)")
    p.add_argument("--sh-degree", type=int, default=None, choices=[0, 1, 2, 3],
                   help="highest SH degree fitted (config: sh_degree, default 3); 0 for a scene you will only "
                        "stylize: stylize keeps degree 0, and fitting it alone is faster and a quarter of the PLY's "
                        "bytes")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config key (repeatable), dotted for sections, e.g. --set density.max_gaussians=300000 "
                        "--set lr.means=0.0016 (configs/reconstruct.yaml lists every key)")
    p.add_argument("--resume", default=None, metavar="DIR", help="continue the run saved in DIR (its checkpoint.pt)")
    p.add_argument("--overwrite", action="store_true", help="replace the run already in --out")
    p.add_argument("--keep-checkpoint", action="store_true", help=KEEP_CHECKPOINT_HELP)
    p.add_argument("--device", default=None, choices=["cuda", "cpu", "auto"], help="(config: device)")
    p.add_argument("--quiet", action="store_true", help="no progress line")


def run(args) -> int:
    # lazy: CLI startup
    from ..config_io import resolve_config
    from ..distributed import Dist
    from ..train.reconstruct import (RUN_FILES, FitDiverged, ReconstructConfig, config_from_dict, fit_scene,
                                     load_checkpoint, load_config)

    if args.out is None and args.resume is None:
        raise InputError("--out DIR is required (or --resume DIR)")
    out = Path(args.out if args.out is not None else args.resume)
    base = None
    if args.resume is not None:
        check_resumable(args.resume)
        base = config_from_dict(load_checkpoint(args.resume)["config"], ReconstructConfig())
    overrides = list(args.set)
    for key, val in (("iterations", args.iterations), ("downscale", args.downscale), ("images", args.images),
                     ("sh_degree", args.sh_degree), ("device", args.device)):
        if val is not None:
            overrides.append(f"{key}={val}")
    cfg = load_config(resolve_config(args.config, default=None), overrides, base)  # a preset by name from any folder
    dataset = _load(args.data, cfg)
    dist = Dist.from_env(str(resolve_device(cfg.device)))  # torchrun: one rank per GPU, views of a step split
    # the main rank owns the folder (locked; bad input leaves nothing behind); the others only read
    folder = (run_folder(out, args.overwrite, args.resume is not None, RUN_FILES, inputs=(args.data,))
              if dist.is_main else contextlib.nullcontext())
    with folder:
        try:
            _, m = fit_scene(dataset, cfg, out, progress=not args.quiet and dist.is_main, resume=args.resume,
                             overwrite=args.overwrite, dist=dist)
        except FitDiverged as e:
            if dist.is_main:
                print(f"error: {e}", file=sys.stderr)
            return 1
    if not dist.is_main:
        return 0
    if not args.keep_checkpoint:  # finished: the outputs are written, the checkpoint goes
        drop_checkpoints(out)
    print(f"{out}: held-out PSNR {m['psnr']:.2f} dB (init {m['psnr_init'] if m['psnr_init'] is None else round(m['psnr_init'], 2)}), "
          f"SSIM {m['ssim']:.4f}, {m['num_gaussians']} Gaussians, {m['ply_bytes'] / 1e6:.1f} MB, "
          f"{m['iterations']} iterations in {m['train_time_s']:.1f} s" + peak_memory_note(m))
    return 0


def _load(data: str, cfg):
    if data == "demo":
        # lazy: CLI startup
        from ..io.demo import demo_dataset

        return demo_dataset()
    # lazy: CLI startup
    from ..io import load_dataset

    kw = {}
    if cfg.images is not None:
        kw["images"] = cfg.images
    if cfg.downscale is not None:
        kw["downscale"] = cfg.downscale
    return load_dataset(data, **kw)
