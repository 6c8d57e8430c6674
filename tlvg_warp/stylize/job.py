"""A stylization as ``python -m tlvg_warp stylize`` runs it, from the paths and flags a user gives to the written
run folder:

    job = StylizeJob.start(data="fern", style="starry.jpg", overrides=["loss.w_align=8"])  # config, device, VGG
    with job.folder():                       # the run folder, claimed (locked; bad input leaves nothing behind)
        inp, input_bytes = job.inputs()      # stylize/inputs.py: the demo, a scene, a dataset, or both
        result = job.stylize(inp)            # run_stylize
        metrics = job.write(result, input_bytes)

or all of it in one call, the checkpoint dropped once the outputs are written: ``metrics, result = job.run()``.

``start`` resolves everything that can fail before a file is written: the config (a checkpoint's on resume; else
--config, else configs/tlvg.yaml (the source tree's or the installed copy); the demo's size when no scene or data
is named and the user chose none), the sources, the device (one rank per GPU under torchrun) and the VGG weights."""
from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..config_io import canonical, resolve_config
from ..distributed import Dist
from ..errors import InputError
from ..runs import drop_checkpoints, resolve_device, run_folder
from .config import StylizeConfig, config_from_dict, load_config
from .inputs import assemble_inputs
from .outputs import write_outputs
from .pipeline import RUN_FILES, load_checkpoint, run_stylize

# The no-argument demo's settings (a user's flag or --set wins). On 2 CPU cores: 160x120 views (18,733 discs),
# the render fed to VGG at x0.5 (80x60) and the painting at the view's size times the config's stroke scale, SH DC
# learning rate x4 so that a preview of 240 iterations moves the colours (docs/performance.md gives its time).
# On a GPU: 640x480 views, 600 iterations, the same colour learning rate (against the config's: chroma noise
# 0.560 against 0.682, k1 0.071 against 0.082, the rest within their intervals; docs/performance.md).
DEMO_CPU = {"iterations": 240, "downscale": 1.0, "density.interval": 20,
            "style_height": 0, "vgg_scale": 0.5, "lr.sh_dc": 0.01}
DEMO_GPU = {"iterations": 600, "downscale": 0.25, "density.interval": 100, "lr.sh_dc": 0.01}


@dataclass
class StylizeJob:
    cfg: StylizeConfig
    sources: dict  # absolute paths by role: scene, data, style, cameras (recorded in sources.json and checkpoints)
    out: Path  # the run folder
    device: torch.device
    dist: Dist
    vgg: object  # the loaded feature network
    resume: str | None = None
    overwrite: bool = False
    quiet: bool = False  # no progress line or notes (every rank but the main one is quiet anyway)
    named: tuple = ()  # the input paths as given: the run folder may not be one of them
    wall_start: float = field(default_factory=time.perf_counter)
    load_split: dict = field(default_factory=dict)  # seconds: loading VGG, assembling the inputs (metrics.json)

    @classmethod
    def start(cls, *, scene=None, data=None, style=None, cameras=None, config=None, overrides=(), iterations=None,
              downscale=None, device=None, vgg_weights=None, strength=None, stroke_scale=None, keep_colors=False,
              resume=None, out=None, overwrite=False, quiet=False) -> "StylizeJob":
        """Resolve the config, sources, run folder path, device and VGG (InputError before anything is written).
        The keyword flags are the command line's (None: not given); ``overrides`` are its --set KEY=VALUE."""
        wall0 = time.perf_counter()
        ck = load_checkpoint(resume) if resume is not None else None
        over = list(overrides)
        for key, val in (("iterations", iterations), ("downscale", downscale), ("device", device),
                         ("vgg_weights", vgg_weights), ("loss.strength", strength),
                         ("stroke_scale", stroke_scale), ("keep_colors", True if keep_colors else None)):
            if val is not None:
                over.append(f"{key}={val}")
        if ck is not None:
            sources = dict(ck.get("sources") or {})
            cfg = load_config(None, over, config_from_dict(ck["config"]))
        else:
            sources = {}
            cfg_path = resolve_config(config)
            base_over = []
            if scene is None and data is None:  # the demo's size, unless the user chose one
                gpu = torch.cuda.is_available() and device != "cpu"
                size = DEMO_GPU if gpu else DEMO_CPU
                flags = {"iterations": iterations, "downscale": downscale}
                base_over += [f"{k}={v}" for k, v in size.items()
                              if flags.get(k) is None and not _names_key(overrides, k)]
            cfg = load_config(cfg_path, base_over + over)
        if cameras is not None and (scene is None or data is not None):
            raise InputError("--cameras goes with --scene and no --data")
        for key, val in (("scene", scene), ("data", data), ("style", style), ("cameras", cameras)):
            if val is not None:
                sources[key] = str(Path(val).resolve())
        if sources.get("style") is None and cfg.style is not None:
            sources["style"] = cfg.style
        if sources.get("style") is not None:
            cfg.style = sources["style"]
        if style is not None and not Path(style).exists():  # fail before any work
            raise InputError("style image does not exist", style)

        if out is not None:
            out = Path(out)
        elif resume is not None:
            out = Path(resume)
        else:
            out = Path("runs") / time.strftime("stylize_%Y%m%d_%H%M%S")
        from ..losses import load_vgg  # lazy: imports Warp (after the checks above: bad input fails before it)

        dev = resolve_device(cfg.device)
        dist = Dist.from_env(str(dev))  # torchrun: one rank per GPU, data-parallel over the views of a step
        if dist.world > 1:
            dev = torch.device(dist.device)
        t_vgg = time.perf_counter()
        vgg = load_vgg(cfg.vgg_weights, dev)  # InputError (how to get the weights) before anything is written
        t_vgg = time.perf_counter() - t_vgg
        return cls(cfg, sources, out, dev, dist, vgg, resume, overwrite, quiet, (data, scene, style), wall0,
                   {"vgg": t_vgg})

    @property
    def speaks(self) -> bool:
        """This process prints progress and notes (not quiet, the main rank)."""
        return not self.quiet and self.dist.is_main

    def folder(self):
        """The run folder claimed for the run (a context): the main rank owns it (locked; bad input leaves nothing
        behind); the others only read."""
        if not self.dist.is_main:
            return contextlib.nullcontext()
        return run_folder(self.out, self.overwrite, self.resume is not None, RUN_FILES, inputs=self.named)

    def inputs(self):
        """(StylizeInputs, input bytes): see stylize/inputs.py."""
        t = time.perf_counter()
        res = assemble_inputs(self.cfg, self.sources, self.out, self.quiet, self.dist)
        self.load_split["inputs"] = time.perf_counter() - t
        return res

    def stylize(self, inp, on_progress=None):
        """run_stylize on the job's config, folder, device and VGG (resuming ``resume``)."""
        quiet = not self.speaks
        return run_stylize(inp, self.cfg, self.out, resume=self.resume, overwrite=True, progress=not quiet,
                           vgg=self.vgg, quiet=quiet, on_progress=on_progress, dist=self.dist)

    def run(self, keep_checkpoint: bool = False, on_start=None) -> tuple[dict, object]:
        """The whole run in the claimed folder: inputs, run_stylize, the outputs (main rank), and the checkpoint
        dropped once they are written (unless ``keep_checkpoint``). ``on_start(inputs)`` is called once the inputs
        are assembled and may return an ``on_progress(step, gaussians)`` callback (the live viewer's).
        Returns (metrics.json's content, the StylizeResult); the content is {} on every rank but the main one."""
        with self.folder():
            inp, input_bytes = self.inputs()
            on_progress = on_start(inp) if on_start is not None else None
            res = self.stylize(inp, on_progress)
            if not self.dist.is_main:
                return {}, res  # every rank holds the same result; the main rank writes it
            metrics = self.write(res, input_bytes)
            if not keep_checkpoint:  # finished: the outputs are written, the checkpoint goes
                drop_checkpoints(self.out, "reconstruct")
            return metrics, res

    def write(self, res, input_bytes) -> dict:
        """The run folder's outputs (stylize/outputs.py; the main rank only); returns metrics.json's content."""
        res.metrics["load_split_s"] = {k: round(self.load_split.get(k, 0.0), 3) for k in ("vgg", "inputs")}
        return write_outputs(self.out, res, input_bytes=input_bytes, wall_start=self.wall_start)


def stylize_run(keep_checkpoint: bool = False, **start) -> dict:
    """One stylization from its inputs to its written run folder (what `stylize` does without a viewer), with
    ``start`` as StylizeJob.start's keywords. Returns metrics.json's content ({} on every rank but the main one).
    InputError, WriteError and StylizeDiverged reach the caller."""
    return StylizeJob.start(**start).run(keep_checkpoint)[0]


def _names_key(overrides, key: str) -> bool:
    """One of the KEY=VALUE ``overrides`` sets ``key`` (under its current or an old name)."""
    return any(canonical(StylizeConfig, s.split("=", 1)[0].strip()) == key for s in overrides)


__all__ = ["StylizeJob", "DEMO_CPU", "DEMO_GPU"]
