"""Fit a 3DGS scene to posed photos: ``fit_scene(dataset, config, out_dir=None, ...) -> (Gaussians, metrics)``.

One ``Fit`` phase of the training loop (train/loop.py): one random training view per step (without
replacement per epoch), loss (1−λ)·L1 + λ·(1−SSIM) with λ = 0.2, density control every ``density.interval``
steps (its own schedule, train/density.py), SH degree +1 every ``sh_increase_every`` steps up to
``sh_degree``. The loop reads the device only every ``log_every`` steps.

Faults: Ctrl-C finishes the current step, saves ``checkpoint.pt`` and ``point_cloud.ply`` and raises
KeyboardInterrupt (``resume=DIR`` continues). A non-finite loss or parameter stops the run with
:class:`FitDiverged`; the last good state (from the previous log flush) is written as checkpoint and PLY, a
NaN PLY never is. A checkpoint (with log.jsonl) is written about once a minute, so a killed run loses
about a minute.
"""
from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from .. import config_io, runs
from ..config_io import ConfigError, check_run_settings
from ..errors import InputError
from ..fileio import write_image, write_json
from ..io import save_ply
from ..io.datasets import dataset_background
from ..renderer import render
from ..types import Gaussians
from .density import DENSITY_RENAMED, DensityConfig
from .init import initialize, scene_extent
from .loop import Diverged, Fit, peak_gpu_mib, train
from .optim import LR_RENAMED, GaussianParams, LearningRates
from .session import Session, density_control, new_run, optimizer

CHECKPOINT_FORMAT = "tlvg_warp.reconstruct.v1"
RUN_FILES = ("config.yaml", "checkpoint.pt", "point_cloud.ply", "metrics.json", "cameras.json", "log.jsonl")


class FitDiverged(Diverged):
    """The loss or the parameters became non-finite."""


@dataclass
class FitLoss:
    """The ``loss`` section of a reconstruction."""

    lambda_ssim: float = 0.2  # loss = (1 - lambda) L1 + lambda (1 - SSIM) (3DGS)

    RULES = {"lambda_ssim": ("in", 0, 1)}


def _density() -> DensityConfig:
    # The size rules (3DGS: only after the first opacity reset) prune the large Gaussians that, early in a fit,
    # carry most of the image (fern at 126x94: pruning the 14% larger than 0.1x extent at step 100 drops 21 dB
    # to 8 dB). Without a reset there is no "after the first reset": no size rules. The world rule is off: on
    # forward-facing scenes the extent (camera spread) is small next to the depth, and 0.1x extent pruned the
    # Gaussians covering the background at every densify step after a reset (fern: 20.5 dB -> 8 dB).
    return DensityConfig(phases=["fit"], max_world_size=0.0, opacity_reset_interval=0, max_gaussians=300_000)


@dataclass
class ReconstructConfig:
    iterations: int = 7000  # optimizer steps
    images: str | None = None  # image sub-folder of the dataset (e.g. images_8); None: the loader's default
    downscale: float | None = None  # resize factor applied when loading (uses images_<f>/ when present)
    holdout_every: int = 8  # views k % holdout_every == 0 (name order) are held out for evaluation; 0: none
    sh_degree: int = 3  # maximum SH degree
    sh_increase_every: int = 1000  # raise the active SH degree by one every this many iterations
    init_opacity: float = 0.1  # opacity of the initial Gaussians (3DGS)
    init_random_points: int = 20000  # random points in the frustums when the dataset has no SfM points
    max_init_points: int = 0  # subsample the SfM points to at most this many (0: all)
    random_background: bool = False  # render over a random background color each iteration
    background: list[float] | None = None  # fixed background RGB; None: the dataset's (black for photos)
    seed: int = 0  # seeds view order, init subsampling, split sampling, random background
    device: str = "auto"  # cuda, cpu or auto (cuda when available)
    views_per_step: int = 1  # training views per step (per rank under torchrun); the loss is their mean
    render_headroom: float = 0.0  # > 1 on a GPU: key buffers sized from a view's last count x this (0: exact counts)
    # A training render then never waits for its intersection count; no faster over a whole run as measured
    # (docs/performance.md)
    log_every: int = 50  # host reads (log rows, progress bar, NaN check, snapshot) every this many iterations
    timing_every: int = 20  # sample the per-stage time split every this many iterations
    checkpoint_every: int = 0  # also write checkpoint.pt every this many iterations (0: by time only, below)
    checkpoint_seconds: float = 60.0  # ... and at the first log point a minute after the last one (0: off): a killed run loses about that
    final_checkpoint: bool = True  # write checkpoint.pt at the end (lets --resume extend a run)
    save_renders: bool = True  # write renders of the held-out views to test/
    lr: LearningRates = field(default_factory=lambda: LearningRates(means_steps=0))  # learning rates (3DGS)
    loss: FitLoss = field(default_factory=FitLoss)  # the photometric loss
    density: DensityConfig = field(default_factory=_density)  # adaptive density control (3DGS)

    RULES = {"iterations": (">=", 1), "holdout_every": (">=", 0), "sh_degree": ("in", 0, 3),
             "sh_increase_every": (">=", 1), "init_random_points": (">=", 0), "max_init_points": (">=", 0),
             "views_per_step": (">=", 1), "log_every": (">=", 1), "timing_every": (">=", 1),
             "checkpoint_every": (">=", 0), "checkpoint_seconds": (">=", 0)}
    RENAMED = {**LR_RENAMED, **DENSITY_RENAMED, "lambda_ssim": "loss.lambda_ssim", "progress_every": "log_every",
               "densify": ("density.phases", lambda cur, on: ["fit"] if config_io.coerce("densify", on, bool) else []),
               "densify_from": "density.start", "densify_until": "density.until",
               "opacity_reset_interval": "density.opacity_reset_interval", "max_gaussians": "density.max_gaussians",
               "min_contribution": "density.min_contribution"}

    def check(self, prefix: str = "") -> None:
        check_run_settings(self, prefix)
        if not 0 < self.init_opacity < 1:
            raise ConfigError(prefix + "init_opacity", f"must be in (0, 1), got {self.init_opacity}")
        if self.downscale is not None and not self.downscale > 0:
            raise ConfigError(prefix + "downscale", f"must be positive, got {self.downscale}")
        unknown = set(self.density.phases) - {"fit"}
        if unknown:
            raise ConfigError(prefix + "density.phases", f"names a phase reconstruct does not have ({sorted(unknown)}; "
                                                         "its one phase is fit)")

    def validate(self) -> "ReconstructConfig":
        return config_io.validate(self)


# --- config I/O --------------------------------------------------------------------------------------
def config_from_dict(d: dict, base: ReconstructConfig | None = None) -> ReconstructConfig:
    return config_io.from_dict(ReconstructConfig, d, base)


def load_config(path=None, overrides=(), base: ReconstructConfig | None = None) -> ReconstructConfig:
    """Defaults (or ``base``), the YAML file (``base:`` chain), then ``key=value`` overrides (dotted keys)."""
    return config_io.load(ReconstructConfig, path, overrides, base)


def config_yaml(cfg: ReconstructConfig) -> str:
    return config_io.config_yaml(cfg, "tlvg_warp reconstruct: resolved configuration")


# --- helpers ---------------------------------------------------------------------------------------------
def split_views(n: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """(train, test) indices: k % holdout_every == 0 is held out (LLFF convention)."""
    if holdout_every and holdout_every > 0:
        test = [i for i in range(n) if i % holdout_every == 0]
        train_ = [i for i in range(n) if i % holdout_every != 0]
        if not train_:
            train_, test = list(range(n)), []
    else:
        train_, test = list(range(n)), []
    return train_, test


def cameras_json(dataset) -> list[dict]:
    """INRIA ``cameras.json`` entries: position = camera center, rotation = camera-to-world 3x3 (rows)."""
    out = []
    for i, (cam, name) in enumerate(zip(dataset.cameras, dataset.names)):
        c2w = torch.linalg.inv(cam.world_to_camera.double())
        out.append({"id": i, "img_name": Path(name).stem, "width": cam.width, "height": cam.height,
                    "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(), "fy": cam.fy, "fx": cam.fx})
    return out


def _image_list(dataset, device):
    out = []
    for i in range(len(dataset.cameras)):
        img = torch.as_tensor(dataset.image(i))
        cam = dataset.cameras[i]
        if tuple(img.shape) != (cam.height, cam.width, 3):
            raise InputError(f"image {i} is {tuple(img.shape)}, expected [{cam.height}, {cam.width}, 3]")
        out.append(img.to(device=device, dtype=torch.float32).contiguous())
    return out


def load_checkpoint(path) -> dict:
    ck = runs.read_checkpoint(path, CHECKPOINT_FORMAT, "reconstruct")
    if "split_rng" in ck:  # written before the loop moved into train/loop.py: the split RNG was top-level
        ck["density"] = dict(ck["density"] or {}, rng=ck.pop("split_rng"))
    return ck


def _save_ply_checked(g: Gaussians, path: Path) -> int:
    bad = sum(int((~torch.isfinite(getattr(g, f))).sum()) for f in Gaussians.FIELDS)
    if bad:
        raise FitDiverged(f"refusing to write a PLY with {bad} non-finite values")
    save_ply(g.to(device="cpu", dtype=torch.float32), path)
    return os.path.getsize(path)


# --- the fitter -----------------------------------------------------------------------------------------
def fit_scene(dataset, config: ReconstructConfig | None = None, out_dir=None, gaussians: Gaussians | None = None,
              progress: bool = True, *, resume=None, overwrite: bool = False, callback=None, dist=None):
    """Fit Gaussians to ``dataset`` (anything with ``.cameras``, ``.names``, ``.image(i)``, ``.points``).

    out_dir: where the run's files go (None: nothing is written, Ctrl-C just stops).
    gaussians: start from these instead of initializing from the dataset's points (their SH bands all active).
    resume: a run folder (or checkpoint path) to continue from.
    callback: ``fn(step, run)`` after every iteration (tests). dist: a ``Dist`` (torchrun; default: one process).
    Returns (Gaussians, metrics)."""
    t_start = time.perf_counter()
    cfg = (config or ReconstructConfig()).validate()
    session = Session(cfg, dist)
    dist, device = session.dist, session.device
    cams, names = list(dataset.cameras), list(dataset.names)
    if len(cams) == 0:
        raise InputError("dataset has no images")
    if len(cams) < 2:
        raise InputError(f"dataset has a single view ({names[0] if names else '?'}); fitting needs at least 2")
    session.open(out_dir, names, resume=resume, overwrite=overwrite, read_checkpoint=load_checkpoint,
                 run_files=RUN_FILES, config_yaml=config_yaml, render_dirs=("test", "train"))
    out, ck = session.out, session.checkpoint

    train_idx, test_idx = split_views(len(cams), cfg.holdout_every)
    targets = _image_list(dataset, device)
    bg_fixed = tuple(float(v) for v in cfg.background) if cfg.background is not None else dataset_background(dataset)
    g0, ext, init_note = _initial_state(dataset, cams, cfg, ck, gaussians, device)
    density = density_control(cfg, g0.num, device, cams, extent=ext, n_views=len(train_idx), dist=dist)
    if ck is None:
        g0 = density.fit_budget(g0)  # the budget holds from the start: the most opaque
    params = GaussianParams(g0, max(cfg.sh_degree, g0.sh_degree))
    opt = optimizer(params, cfg, ext)
    max_deg = params.max_sh_degree
    fit = Fit("fit", cfg.iterations, targets, lambda_ssim=cfg.loss.lambda_ssim, random_background=cfg.random_background,
              sh=(max_deg if gaussians is not None else 0, cfg.sh_increase_every, max_deg), psnr=True,
              density="fit" in cfg.density.phases, label="reconstruct")
    run = new_run(cfg, params, opt, density, [fit], cams, device=device, view_ids=train_idx, background=bg_fixed,
                  dist=dist, out=out, fmt=CHECKPOINT_FORMAT,
                  extra=lambda: {"extent": ext, "config": dataclasses.asdict(cfg), "names": names})
    start_step = session.resume(run)
    if ck is not None:
        init_note = f"resumed at iteration {run.step} from {resume}"

    eval_idx = test_idx if test_idx else train_idx
    psnr_init = None
    if start_step == 0:
        pi, _, _ = _eval_views(run.params.detached(), cams, targets, eval_idx, bg_fixed)
        psnr_init = sum(pi) / len(pi)

    def write_ply(run_, note):
        _save_ply_checked(run_.params.detached(), out / "point_cloud.ply")
        return [out / "point_cloud.ply"]

    train(run, progress=progress, callback=callback, diverged=FitDiverged, on_stop=write_ply if dist.is_main else None,
          hint=". Lower the learning rates or check the input images")

    final = run.params.detached()
    ps, ss, renders = _eval_views(final, cams, targets, eval_idx, bg_fixed)
    metrics = {
        "psnr": sum(ps) / len(ps), "ssim": sum(ss) / len(ss),
        "eval_split": "test" if test_idx else "train",
        "views": [names[i] for i in eval_idx], "psnr_per_view": ps, "ssim_per_view": ss,
        "psnr_init": psnr_init, "num_gaussians": final.num, "ply_bytes": None,
        "iterations": run.step, "resumed_from": start_step if start_step else None,
        "train_time_s": run.loop_time, "wall_time_s": None, "peak_gpu_mib": peak_gpu_mib(device),
        "it_per_s": (run.step - start_step) / max(run.loop_time, 1e-9),
        "time_split": run.timer.summary(), "extent": ext, "init": init_note,
        "num_train_views": len(train_idx), "num_test_views": len(test_idx), "device": str(device),
        "loss_history": [[r["step"], round(r["loss"], 6)] for r in run.log
                         if r["step"] % cfg.log_every == 0 or r["step"] == cfg.iterations],
        "densify_events": list(density.events), "render_counts": run.render_counts(),
    }
    if out is not None and dist.is_main:
        metrics["ply_bytes"] = _write_fit_outputs(out, final, dataset, cfg.save_renders,
                                                  [(names[i], img) for i, img in zip(eval_idx, renders)],
                                                  "test" if test_idx else "train")
    metrics["wall_time_s"] = time.perf_counter() - t_start
    if out is not None and dist.is_main:
        write_json(out / "metrics.json", metrics)
    dist.barrier()
    return final, metrics


def _initial_state(dataset, cams: list, cfg: ReconstructConfig, ck, gaussians, device) -> tuple:
    """(Gaussians, scene extent, a note saying where they came from): the checkpoint's, the given ones, or the
    dataset's points initialized (its cameras set the extent of given Gaussians; the caller names the resumed
    iteration)."""
    if ck is not None:
        return GaussianParams.from_state_dict(ck["params"], device).detached(), float(ck["extent"]), "resumed"
    if gaussians is not None:
        return gaussians.detach().to(device=device, dtype=torch.float32), scene_extent(cams), \
            "given Gaussians"
    return initialize(dataset, cfg.sh_degree, cfg.init_opacity, cfg.init_random_points, cfg.max_init_points, device,
                      cfg.seed)


def _eval_views(g, cams, targets, which, background) -> tuple:
    """PSNR and SSIM of ``g``'s renders of views ``which`` against their photos, and the renders (clamped)."""
    from ..losses import psnr, ssim  # lazy: imports Warp

    ps, ss, renders = [], [], []
    with torch.no_grad():
        for i in which:
            img = render(g, cams[i], background).color.clamp(0, 1)
            ps.append(psnr(img, targets[i]))
            ss.append(float(ssim(img, targets[i])))
            renders.append(img)
    return ps, ss, renders


def _write_fit_outputs(out: Path, final, dataset, save_renders: bool, renders: list, split: str) -> int:
    """point_cloud.ply (checked finite), cameras.json and, with ``save_renders``, the evaluated views' renders
    ((name, image) pairs) under ``split``/. Returns the PLY's size in bytes."""
    size = _save_ply_checked(final, out / "point_cloud.ply")
    write_json(out / "cameras.json", cameras_json(dataset))
    if save_renders:
        for name, img in renders:
            write_image(out / split / f"{Path(name).stem}.png", img)
    return size


__all__ = ["ReconstructConfig", "FitLoss", "FitDiverged", "fit_scene", "load_config", "config_yaml",
           "config_from_dict", "split_views", "cameras_json", "load_checkpoint", "CHECKPOINT_FORMAT", "RUN_FILES"]
