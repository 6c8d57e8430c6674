"""A stylization's inputs from the paths a user names: ``assemble_inputs(cfg, sources, out)`` ->
``(StylizeInputs, input bytes)``, from one of

- nothing: the built-in demo still life (its photos are renders of its own scene);
- ``scene`` + ``data``: a trained scene (INRIA PLY, .compressed.ply or .spz) and the posed photos it was fitted to
  (checked to belong together);
- ``data`` alone: the scene is fitted to the photos first (``reconstruct`` into ``out/reconstruct``);
- ``scene`` alone: cameras orbit it (or come from ``cameras``, the INRIA trainer's cameras.json) and its renders
  stand in for the photos.

The painting is ``sources["style"]`` (``load_style``) or the built-in The Starry Night. Every problem with a named
file is a one-line InputError that names it."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..io import load_dataset, load_ply
from ..io.datasets import dataset_background
from ..io.demo import builtin_painting, demo_dataset
from ..io.images import composite, read_image_fit
from ..io.scene_views import render_stand_in_photos, scene_views
from ..runs import resolve_device
from ..train.init import points_in_front
from ..train.reconstruct import ReconstructConfig, fit_scene
from .pipeline import StylizeInputs

MIN_STYLE_PX = 64  # a painting smaller than this has no brushstrokes left at VGG's relu3 (1/4 resolution)
MAX_STYLE_PX = 8192  # larger paintings are resized (with a warning): the style loss sees height 256 anyway


def load_style(path) -> torch.Tensor:
    """The painting as float32 [H,W,3]; one-line InputError for missing / unreadable / tiny files."""
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


def assemble_inputs(cfg, sources: dict, out: Path, quiet: bool = False, dist=None):
    """(StylizeInputs, input bytes) from the demo, ``scene`` + ``data``, ``data`` alone (fitted first into
    ``out/reconstruct``, whose PLY then becomes ``sources["scene"]``) or ``scene`` alone. ``sources``: absolute
    paths by role (scene, data, style, cameras); input bytes: the scene file's size (None for the demo)."""
    style = load_style(sources["style"]) if sources.get("style") else builtin_painting()
    scene, data = sources.get("scene"), sources.get("data")
    if scene is not None and data is None:  # no photos: the scene's own renders stand in
        return _scene_only_inputs(Path(scene), cfg, style, sources)
    if data is None:  # the demo
        w, h = max(8, round(160 / cfg.downscale)), max(8, round(120 / cfg.downscale))
        # discs sized to the render's pixels: at 1/downscale the same still life from 1/downscale² the discs
        ds = demo_dataset(width=w, height=h, spacing=max(1.0, cfg.downscale))
        g, in_bytes = ds.gaussians, None
    else:
        ds = load_dataset(data, downscale=cfg.downscale if cfg.downscale != 1 else None)
        if scene is not None:
            sp = Path(scene)
            g = load_ply(sp)
            if g.num == 0:
                raise InputError("the scene has no Gaussians (its PLY declares 0 vertices)", sp)
            check_scene_matches(sp, g, ds)
            in_bytes = sp.stat().st_size
        else:
            g, in_bytes = fit_first(ds, cfg, out, quiet, dist)
            sources["scene"] = str(out / "reconstruct" / "point_cloud.ply")
    photos = ds.images()
    return (StylizeInputs(g, list(ds.cameras), list(ds.names), photos, style, dataset_background(ds), dict(sources)),
            in_bytes)


def _scene_only_inputs(sp: Path, cfg, style, sources: dict):
    g = load_ply(sp)
    views = scene_views(g, sources.get("cameras"), cfg.downscale)
    # a scene without photos has no background of its own: white (like the demo) unless the config names one
    bg = tuple(float(v) for v in cfg.background) if cfg.background is not None else (1.0, 1.0, 1.0)
    # rendered where the run will work: a large scene on the CPU takes minutes, and a CUDA-only Warp build has no
    # CPU compiler at all
    photos = render_stand_in_photos(g.to(resolve_device(cfg.device)), views.cameras, bg)
    return StylizeInputs(g, views.cameras, views.names, photos, style, bg, dict(sources)), sp.stat().st_size


def fit_first(ds, cfg, out: Path, quiet: bool = False, dist=None):
    """(Gaussians, PLY bytes): the scene fitted to ``ds`` into ``out/reconstruct`` with the stylization's
    fit_iterations, seed, device and SH choice."""
    rc = ReconstructConfig(iterations=cfg.fit_iterations, holdout_every=0, device=cfg.device, seed=cfg.seed,
                           save_renders=False, sh_degree=3 if cfg.keep_sh else 0, views_per_step=cfg.views_per_step)
    main = dist is None or dist.is_main
    if not quiet and main:
        print(f"fitting the scene to {len(ds.cameras)} photos first ({cfg.fit_iterations} iterations) ...")
    g, m = fit_scene(ds, rc, out / "reconstruct", progress=not quiet and main, overwrite=True, dist=dist)
    if not quiet and main:
        print(f"fitted: PSNR {m['psnr']:.2f} dB, {g.num} Gaussians")
    return g, m["ply_bytes"]


__all__ = ["assemble_inputs", "load_style", "check_scene_matches", "fit_first", "MIN_STYLE_PX", "MAX_STYLE_PX"]
