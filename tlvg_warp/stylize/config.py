"""``StylizeConfig``: every knob of the stylization (SPEC §3), and YAML loading with ``base:`` inheritance.

A config file is a YAML mapping of field names; ``base: other.yaml`` (relative to the file) is loaded first,
so an ablation states only what differs. ``key=value`` overrides (values parsed as YAML) come last. An
unknown key is an InputError that names it and lists close matches.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, field
from pathlib import Path

from .. import config_io
from ..config_io import apply_overrides, coerce as _coerce, field_comments as _field_comments
from ..errors import InputError


@dataclass
class StylizeConfig:
    # --- schedule ---------------------------------------------------------------------------------
    iterations: int = 3000  # total optimizer steps, split over the phases in `phases` proportions (paper)
    phases: list = field(default_factory=lambda: [500.0, 2000.0, 500.0])  # relative lengths pre / stylize / post
    seed: int = 0  # seeds the view order, split sampling and torch's RNG
    device: str = "auto"  # cuda, cpu or auto (cuda when available)
    downscale: float = 1.0  # render resolution divisor (dataset images are loaded at 1/downscale)
    palette_init: bool = True  # pre-process starts from the Gaussians recolored by the photos' palette map (ours)
    fit_iterations: int = 7000  # reconstruction steps when only --data is given (the scene is fitted first)
    style: str | None = None  # the painting's path (None: the built-in Starry Night); --style sets it
    # --- style / content losses ---------------------------------------------------------------------
    style_loss: str = "fast"  # fast (FAST, reference code) | nnfm (ARF) | gram
    luminance_only: bool = True  # style loss on Y = 0.299R+0.587G+0.114B for render and painting (paper §3.3)
    vgg_weights: str | None = None  # torchvision vgg16 state dict path, "random", or None (env / torch hub cache)
    vgg_scale: float = 0.5  # the render is resized by this before VGG (SPEC §3: x0.5)
    style_height: int = 256  # the painting is resized to this height before VGG (SPEC §3)
    w_style: float = 2.0  # style loss weight (reference code)
    w_content: float = 0.01  # VGG feature MSE vs the original photo of the view (reference code)
    w_depth: float = 0.01  # MSE of inverse depth vs the un-stylized scene (reference code)
    w_tv: float = 0.02  # total variation of the render, horizontal + vertical (reference code, corrected)
    w_opacity_reg: float = 1.0  # ||opacity_logits - value at stylize start||_2 (reference code)
    w_scale_reg: float = 1.0  # ||log_scales - value at stylize start||_2 (reference code)
    w_lab_start: float = 0.2  # Lab chroma statistics weight at the first stylize step (paper, linear schedule)
    w_lab_end: float = 0.05  # ... and at the last stylize step
    # --- flow guidance (ours, SPEC §3) -----------------------------------------------------------------
    w_align: float = 2.0  # flow-alignment energy weight (paper eq. 1; tuned on the demo, see README)
    w_aniso: float = 0.2  # anisotropy energy weight (across-stroke footprint energy + λmin/λmax)
    field_mapping: str = "matched"  # matched (FAST match carries the painting's field) | canvas (painting stretched)
    # --- geometry ------------------------------------------------------------------------------------------
    lock_xyz: bool = False  # freeze Gaussian positions during stylize (ABC-GS); False = advection (paper)
    tangential_lambda: float = 1.0  # λ of the tangential update hook (paper eq. 3), in [0, 1]; 0 = off
    lr_means: float = 1.6e-4  # xyz learning rate at step 0, times the scene extent (3DGS)
    lr_means_final: float = 1.6e-6  # xyz learning rate at the end of the decay, times the extent
    lr_means_steps: int = 30000  # steps of the exponential xyz decay (3DGS)
    lr_sh_dc: float = 2.5e-3  # SH DC learning rate (3DGS)
    lr_sh_rest: float = 1.25e-4  # higher SH bands (3DGS)
    lr_opacity: float = 0.05  # opacity logits (3DGS)
    lr_scales: float = 5e-3  # log scales (3DGS)
    lr_quats: float = 1e-3  # rotations (3DGS)
    # --- density control -------------------------------------------------------------------------------------
    density_in_pre: bool = True  # clone/split/prune during the pre-process fit (reference code)
    density_in_stylize: bool = True  # clone/split/prune during stylize (paper: unlike ABC-GS)
    densify_interval: int = 100  # densify every this many iterations of a phase (3DGS)
    densify_grad_threshold: float = 2e-4  # mean NDC screen-gradient norm for clone/split (3DGS)
    percent_dense: float = 0.01  # clone below this fraction of the extent, split above (3DGS)
    split_mode: str = "moments"  # split into 2 children keeping the parent's mean/covariance (ours); 3dgs: sampled, /1.6
    min_opacity: float = 0.005  # prune below this opacity (3DGS)
    max_screen_size: float = 20.0  # prune above this 2D radius in pixels (3DGS)
    max_world_size: float = 0.1  # prune above this fraction of the extent (3DGS)
    gaussian_budget: int = 0  # hard cap on the Gaussian count; 0: budget_factor x the starting count
    budget_factor: float = 1.2  # budget relative to the input scene when gaussian_budget is 0 (demo: reached either way)
    use_budget: bool = True  # cap the Gaussian count at the budget (ours; ABC-GS has no cap)
    prune_unseen: bool = True  # prune Gaussians that contribute to no view over an epoch (ours; ABC-GS has none)
    # --- output --------------------------------------------------------------------------------------------------
    keep_sh: bool = False  # keep view-dependent SH bands in stylized.ply (default: degree 0, ~3.6x smaller)
    web_formats: bool = True  # also write stylized.compressed.ply (SuperSplat/PlayCanvas) and stylized.spz (Niantic)
    background: list | None = None  # render background RGB; None: the dataset's (white for the demo)
    log_every: int = 50  # host reads (log flush, progress bar, NaN check, last-good snapshot) every N iterations
    checkpoint_every: int = 0  # also write checkpoint.pt every N iterations (0: by time only, below)
    checkpoint_seconds: float = 60.0  # ... and at the first log point a minute after the last one (0: off); a
    # killed run (SIGKILL, power loss) loses about this much; log.jsonl is written at the same point
    orbit_frames: int = 96  # frames of orbit.mp4 (interpolated between the dataset cameras)
    orbit_fps: int = 24  # frame rate of orbit.mp4
    comparison_views: int = 4  # rows of comparison.png

    # ------------------------------------------------------------------------------------------------------
    def phase_steps(self) -> tuple[int, int, int]:
        """(pre, stylize, post) step counts summing to ``iterations`` (stylize gets the rounding rest)."""
        p = [max(0.0, float(x)) for x in self.phases]
        tot = sum(p)
        pre = int(round(self.iterations * p[0] / tot))
        post = int(round(self.iterations * p[2] / tot))
        return pre, self.iterations - pre - post, post

    def lab_weight(self, k: int, n: int) -> float:
        """Lab chroma weight at stylize step ``k`` (0-based) of ``n``: linear w_lab_start -> w_lab_end."""
        if n <= 1:
            return self.w_lab_start
        t = min(max(k / (n - 1), 0.0), 1.0)
        return self.w_lab_start + (self.w_lab_end - self.w_lab_start) * t

    def validate(self) -> "StylizeConfig":
        if self.iterations < 1:
            raise InputError(f"config iterations must be >= 1, got {self.iterations}")
        if len(self.phases) != 3 or any(not (x >= 0) for x in self.phases) or sum(self.phases) <= 0:
            raise InputError(f"config phases must be 3 non-negative numbers (pre, stylize, post), got {self.phases}")
        choices = {"style_loss": ("fast", "nnfm", "gram"), "field_mapping": ("matched", "canvas"),
                   "split_mode": ("moments", "3dgs")}
        for k, opts in choices.items():
            if getattr(self, k) not in opts:
                raise InputError(f"config {k} must be one of {', '.join(opts)}, got {getattr(self, k)!r}")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if (f.name.startswith(("w_", "lr_")) or f.name in ("checkpoint_seconds", "max_screen_size", "max_world_size", "min_opacity",
                                                               "percent_dense", "densify_grad_threshold")):
                if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                    raise InputError(f"config {f.name} must be a finite number >= 0, got {v}")
        if not 0.0 <= self.tangential_lambda <= 1.0:
            raise InputError(f"config tangential_lambda must be in [0, 1], got {self.tangential_lambda}")
        for k in ("log_every", "densify_interval", "orbit_fps", "style_height", "lr_means_steps"):
            if getattr(self, k) < 1:
                raise InputError(f"config {k} must be >= 1, got {getattr(self, k)}")
        for k in ("gaussian_budget", "checkpoint_every", "fit_iterations", "orbit_frames", "comparison_views"):
            if getattr(self, k) < 0:
                raise InputError(f"config {k} must be >= 0, got {getattr(self, k)}")
        if not (self.downscale > 0 and math.isfinite(self.downscale)):
            raise InputError(f"config downscale must be a positive number, got {self.downscale}")
        if not (0 < self.vgg_scale <= 4):
            raise InputError(f"config vgg_scale must be in (0, 4], got {self.vgg_scale}")
        if not self.budget_factor >= 1:
            raise InputError(f"config budget_factor must be >= 1, got {self.budget_factor}")
        if self.device not in ("auto", "cpu", "cuda") and not str(self.device).startswith("cuda:"):
            raise InputError(f"config device must be auto, cpu or cuda, got {self.device!r}")
        if self.background is not None and len(self.background) != 3:
            raise InputError(f"config background must be 3 numbers, got {self.background!r}")
        return self


# --- loading -------------------------------------------------------------------------------------------------
def field_comments() -> dict:
    return _field_comments(StylizeConfig)



def _unknown(key: str, known) -> InputError:
    close = difflib.get_close_matches(key, known, n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else f" (known keys: {', '.join(known)})"
    return InputError(f"unknown config key {key!r}{hint}")


def config_from_dict(d: dict, base: StylizeConfig | None = None) -> StylizeConfig:
    cfg = dataclasses.replace(base) if base is not None else StylizeConfig()
    types = {f.name: f.type for f in dataclasses.fields(StylizeConfig)}
    for k, v in (d or {}).items():
        if k not in types:
            raise _unknown(str(k), list(types))
        setattr(cfg, k, _coerce(k, v, types[k]))
    return cfg


def read_yaml_chain(path, _seen=None) -> dict:
    """The merged mapping of ``path`` and its ``base:`` ancestors (the file's own keys win)."""
    from ..config_io import read_yaml_mapping

    p = Path(path)
    seen = set() if _seen is None else _seen
    d = read_yaml_mapping(p)
    key = p.resolve()
    if key in seen:
        raise InputError("config base: chain loops back to this file", p)
    seen.add(key)
    base = d.pop("base", None)
    if base is None:
        return d
    merged = read_yaml_chain(p.parent / str(base), seen)
    merged.update(d)
    return merged


def load_config(path=None, overrides=(), base: StylizeConfig | None = None) -> StylizeConfig:
    """Defaults (or ``base``), then the YAML file with its ``base:`` chain, then ``key=value`` overrides."""
    cfg = base if base is not None else StylizeConfig()
    if path is not None:
        cfg = config_from_dict(read_yaml_chain(path), cfg)
    return apply_overrides(cfg, overrides, config_from_dict).validate()


def config_yaml(cfg: StylizeConfig, header: str = "tlvg_warp stylize: resolved configuration") -> str:
    return config_io.config_yaml(cfg, header)


__all__ = ["StylizeConfig", "load_config", "config_from_dict", "config_yaml", "read_yaml_chain", "field_comments"]
