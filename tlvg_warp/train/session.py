"""The frame every training run shares, ``reconstruct`` (train/reconstruct.py) and ``stylize``
(stylize/pipeline.py) alike: the device, the checkpoint it resumes from, its run folder and config.yaml, and the
parts its ``Run`` is built of (density control, Adam, the loop settings) from the command's config.

    s = Session(cfg, dist)                       # the device: one rank per GPU under torchrun, else cfg.device
    s.open(out_dir, names, resume=resume, overwrite=overwrite, read_checkpoint=load_checkpoint,
           run_files=RUN_FILES, config_yaml=config_yaml)   # checkpoint (same views?), run folder, config.yaml
    density = density_control(cfg, g.num, s.device, cams, extent=extent, n_views=len(cams), dist=s.dist)
    opt = optimizer(params, cfg, extent)
    run = new_run(cfg, params, opt, density, phases, cams, device=s.device, dist=s.dist, out=s.out, fmt=FORMAT)
    start_step = s.resume(run)                   # the checkpoint's state, when resuming
    train(run, ...)

A command's config gives the loop its top-level run settings (log_every, checkpoint_every, checkpoint_seconds,
views_per_step, and timing_every / final_checkpoint where it has them), ``seed``, ``lr`` and ``density``."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from .. import runs
from ..distributed import Dist
from ..errors import InputError
from ..fileio import write_text
from .density import DensityControl
from .loop import LoopSettings, Run
from .optim import GaussianOptimizer


class Session:
    """One run's device, checkpoint and folder. ``cfg``: the command's validated config; ``dist``: a ``Dist``
    (torchrun; default one process, whose main rank alone writes files)."""

    def __init__(self, cfg, dist=None):
        self.cfg = cfg
        self.dist = dist or Dist()
        self.device = torch.device(self.dist.device) if self.dist.world > 1 else runs.resolve_device(cfg.device)
        self.out: Path | None = None
        self.checkpoint: dict | None = None
        self.start_step = 0

    def open(self, out_dir, names, *, resume=None, overwrite: bool = False, read_checkpoint, run_files=(),
             config_yaml, render_dirs=()) -> "Session":
        """Read the checkpoint to resume (``read_checkpoint(resume)``; it must be of the same views ``names``) and
        start the run folder ``out_dir`` (None: nothing is written): its run_files checked, replaced with
        ``overwrite``, and ``config_yaml(cfg)`` written as config.yaml (the main rank only)."""
        self.out = Path(out_dir) if out_dir is not None else None
        self.checkpoint = read_checkpoint(resume) if resume is not None else None
        if self.checkpoint is not None and self.checkpoint["names"] != list(names):
            raise InputError("the checkpoint was made on a different dataset (its view names differ)", resume)
        if self.out is not None and self.dist.is_main:
            runs.start_run_dir(self.out, overwrite, self.checkpoint is not None, run_files, render_dirs=render_dirs)
            write_text(self.out / "config.yaml", config_yaml(self.cfg))
        return self

    def resume(self, run: Run) -> int:
        """The checkpoint's state into ``run`` (when resuming); returns the step the run starts from."""
        if self.checkpoint is not None:
            run.load_state_dict(self.checkpoint)
        self.start_step = run.step
        return self.start_step


def density_control(cfg, num: int, device, cams, *, extent: float, n_views: int, dist=None,
                    start_num: int | None = None) -> DensityControl:
    """``cfg.density`` for ``num`` Gaussians trained on ``n_views`` of ``cams``: a gradient window of two epochs,
    the longest image side for the screen-size rules, the split RNG seeded from ``cfg.seed``."""
    longest = max(max(c.width, c.height) for c in cams)
    return DensityControl(cfg.density, num, device, extent=extent, window=2 * n_views - 1, image_size=longest,
                          seed=cfg.seed + 1, dist=dist, start_num=start_num)


def optimizer(params, cfg, extent: float) -> GaussianOptimizer:
    """Adam on ``params`` at ``cfg.lr``, the positions' rate decaying over ``lr.means_steps`` (0: the whole run)."""
    return GaussianOptimizer(params, cfg.lr, extent, cfg.lr.means_steps or cfg.iterations)


def loop_settings(cfg) -> LoopSettings:
    """The loop's settings: the config's top-level keys of the same names (LoopSettings' defaults for the others)."""
    return LoopSettings(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(LoopSettings)
                           if hasattr(cfg, f.name)})


def new_run(cfg, params, opt, density, phases, cams, **kw) -> Run:
    """``Run`` with the config's loop settings and seed (the view order); ``kw``: Run's other keywords."""
    return Run(params, opt, density, phases, cams, loop_settings(cfg), seed=cfg.seed, **kw)


__all__ = ["Session", "density_control", "optimizer", "loop_settings", "new_run"]
