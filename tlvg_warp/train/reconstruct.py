"""Fit a 3DGS scene to posed photos: ``fit_scene(dataset, config, out_dir=None, ...) -> (Gaussians, metrics)``.

The loop (one random training view per iteration, without replacement per epoch):
render → loss (1−λ)·L1 + λ·(1−SSIM), λ=0.2 → backward → density statistics → Adam step (+ hooks) →
densify / prune every ``densify_interval`` → opacity reset. SH degree +1 every ``sh_increase_every``
iterations up to ``sh_degree``. Everything stays on the device; the host reads a value only every
``progress_every`` iterations (progress bar, NaN check, last-good snapshot) and at densify steps.

Faults: Ctrl-C finishes the current iteration, saves ``checkpoint.pt`` and ``point_cloud.ply`` and raises
KeyboardInterrupt (``resume=DIR`` continues). A non-finite loss or parameter stops the run with
:class:`FitDiverged`; the last good state (from the previous check) is written as checkpoint and PLY, a NaN
PLY never is.
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from .. import runs
from .. import config_io
from ..config_io import apply_overrides, coerce as _coerce
from ..errors import InputError
from ..runs import Interrupt as _Interrupt, StageTimer, resolve_device
from ..fileio import atomic_path, write_image, write_json, write_text
from ..types import Gaussians
from .density import DensityConfig, DensityControl
from .optim import GaussianOptimizer, GaussianParams, LearningRates

TIMED_STAGES = ("render", "loss", "backward", "optimizer", "density")  # the time split in metrics.json
RUN_FILES = ("config.yaml", "checkpoint.pt", "point_cloud.ply", "metrics.json", "cameras.json")


class FitDiverged(RuntimeError):
    """The loss or the parameters became non-finite."""


@dataclass
class ReconstructConfig:
    iterations: int = 7000  # optimizer steps
    images: str | None = None  # image sub-folder of the dataset (e.g. images_8); None: the loader's default
    downscale: float | None = None  # resize factor applied when loading (uses images_<f>/ when present)
    holdout_every: int = 8  # views k % holdout_every == 0 (name order) are held out for evaluation; 0: none
    sh_degree: int = 3  # maximum SH degree
    sh_increase_every: int = 1000  # raise the active SH degree by one every this many iterations
    lr_means: float = 1.6e-4  # xyz learning rate at the start, times the scene extent (3DGS)
    lr_means_final: float = 1.6e-6  # xyz learning rate at the end of the decay, times the extent (3DGS)
    lr_means_steps: int = 0  # steps of the exponential xyz decay; 0: the number of iterations
    lr_sh_dc: float = 2.5e-3  # SH DC learning rate (3DGS)
    lr_sh_rest: float = 1.25e-4  # higher SH bands (3DGS: DC / 20)
    lr_opacity: float = 0.05  # opacity logits (3DGS original release; its 2024 update uses 0.025)
    lr_scales: float = 5e-3  # log scales (3DGS)
    lr_quats: float = 1e-3  # rotations (3DGS)
    lambda_ssim: float = 0.2  # loss = (1 - lambda) L1 + lambda (1 - SSIM)
    init_opacity: float = 0.1  # opacity of the initial Gaussians (3DGS)
    init_random_points: int = 20000  # random points in the frustums when the dataset has no SfM points
    max_init_points: int = 0  # subsample the SfM points to at most this many (0: all)
    densify: bool = True  # adaptive density control on
    densify_from: int = 500  # first densify iteration (3DGS)
    densify_until: int = 15000  # no densification from this iteration on (3DGS)
    densify_interval: int = 100  # densify every this many iterations (3DGS)
    densify_grad_threshold: float = 2e-4  # mean NDC screen-gradient norm for clone/split (3DGS)
    percent_dense: float = 0.01  # clone below this fraction of the extent, split above (3DGS)
    min_opacity: float = 0.005  # prune below this opacity (3DGS)
    max_screen_size: float = 20.0  # prune above this 2D radius in pixels, after the first reset (3DGS)
    max_world_size: float = 0.0  # prune above this fraction of the extent, after the first reset (3DGS: 0.1); 0: off
    opacity_reset_interval: int = 0  # opacity reset period; 0: never (3DGS: 3000, which lost ~16 dB on fern here, README)
    max_gaussians: int = 300_000  # hard Gaussian budget (fern reaches its quality under it, README)
    prune_unseen: bool = True  # prune Gaussians that contribute to no training view over an epoch
    min_contribution: float = 0.5  # Σ αT (pixels) over the check window (2 epochs - 1 view) under which a Gaussian is unseen
    random_background: bool = False  # render over a random background color each iteration
    background: list | None = None  # fixed background RGB; None: the dataset's (black for photos)
    seed: int = 0  # seeds view order, init subsampling, split sampling, random background
    device: str = "auto"  # cuda, cpu or auto (cuda when available)
    progress_every: int = 50  # host reads (progress bar, NaN check, snapshot) every this many iterations
    timing_every: int = 20  # sample the per-phase time split every this many iterations
    checkpoint_every: int = 0  # also write checkpoint.pt every this many iterations (0: by time only, below)
    checkpoint_seconds: float = 60.0  # ... and a minute after the last one (0: off): a killed run loses about that
    final_checkpoint: bool = True  # write checkpoint.pt at the end (lets --resume extend a run)
    save_renders: bool = True  # write renders of the held-out views to test/

    # ------------------------------------------------------------------------------------------------
    def learning_rates(self) -> LearningRates:
        return LearningRates(self.lr_means, self.lr_means_final, self.lr_means_steps or self.iterations,
                             self.lr_sh_dc, self.lr_sh_rest, self.lr_opacity, self.lr_scales, self.lr_quats)

    def density_config(self, n_train_views: int) -> DensityConfig:
        # The size rules (3DGS: only after the first opacity reset) prune the large Gaussians that, early in a
        # fit, carry most of the image (fern at 126x94: pruning the 14% larger than 0.1x extent at step 100
        # drops 21 dB to 8 dB). Without a reset there is no "after the first reset": no size rules.
        # The world rule (3DGS 0.1) is off by default: on forward-facing scenes the extent (camera spread) is
        # small next to the depth, and 0.1x extent pruned the Gaussians covering the background at every
        # densify step after a reset (fern: 20.5 dB -> 8 dB; held-out 12 dB vs 24 dB without it).
        sized = self.opacity_reset_interval > 0
        world = self.max_world_size if sized and self.max_world_size > 0 else math.inf
        return DensityConfig(
            grad_threshold=self.densify_grad_threshold, percent_dense=self.percent_dense, min_opacity=self.min_opacity,
            max_screen_size=self.max_screen_size if sized else math.inf,
            max_world_size=world,
            interval=self.densify_interval, start=self.densify_from, until=self.densify_until,
            opacity_reset_interval=self.opacity_reset_interval, max_gaussians=self.max_gaussians,
            prune_unseen=self.prune_unseen, min_contribution=self.min_contribution,
            contribution_window=2 * n_train_views - 1)  # any 2n-1 consecutive steps hold a whole epoch

    def validate(self) -> "ReconstructConfig":
        pos = {"iterations": 1, "sh_increase_every": 1, "progress_every": 1, "timing_every": 1,
               "densify_interval": 1, "max_gaussians": 1}
        for k, lo in pos.items():
            if getattr(self, k) < lo:
                raise InputError(f"config {k} must be >= {lo}, got {getattr(self, k)}")
        if not 0 <= self.sh_degree <= 3:
            raise InputError(f"config sh_degree must be 0..3, got {self.sh_degree}")
        if self.downscale is not None and not self.downscale > 0:
            raise InputError(f"config downscale must be positive, got {self.downscale}")
        if not 0 < self.init_opacity < 1:
            raise InputError(f"config init_opacity must be in (0, 1), got {self.init_opacity}")
        if not 0 <= self.lambda_ssim <= 1:
            raise InputError(f"config lambda_ssim must be in [0, 1], got {self.lambda_ssim}")
        if self.device not in ("auto", "cpu", "cuda") and not self.device.startswith("cuda:"):
            raise InputError(f"config device must be auto, cpu or cuda, got {self.device!r}")
        if self.background is not None and len(self.background) != 3:
            raise InputError(f"config background must be 3 numbers, got {self.background!r}")
        for k in ("checkpoint_seconds", "lr_means", "lr_means_final", "lr_sh_dc", "lr_sh_rest", "lr_opacity", "lr_scales", "lr_quats"):
            if not getattr(self, k) >= 0:
                raise InputError(f"config {k} must be >= 0, got {getattr(self, k)}")
        return self


# --- config I/O --------------------------------------------------------------------------------------

def config_from_dict(d: dict, base: ReconstructConfig | None = None) -> ReconstructConfig:
    cfg = dataclasses.replace(base) if base is not None else ReconstructConfig()
    types = {f.name: f.type for f in dataclasses.fields(ReconstructConfig)}
    for k, v in (d or {}).items():
        if k not in types:
            raise InputError(f"unknown config key {k!r} (known: {', '.join(types)})")
        setattr(cfg, k, _coerce(k, v, types[k]))
    return cfg


def load_config(path=None, overrides=(), base: ReconstructConfig | None = None) -> ReconstructConfig:
    """YAML file (optional) then ``key=value`` overrides (values parsed as YAML)."""
    from ..config_io import read_yaml_mapping

    cfg = base if base is not None else ReconstructConfig()
    if path is not None:
        cfg = config_from_dict(read_yaml_mapping(path), cfg)
    return apply_overrides(cfg, overrides, config_from_dict).validate()


def config_yaml(cfg: ReconstructConfig) -> str:
    return config_io.config_yaml(cfg, "tlvg_warp reconstruct: resolved configuration")


# --- helpers ---------------------------------------------------------------------------------------------


def split_views(n: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """(train, test) indices: k % holdout_every == 0 is held out (LLFF convention)."""
    if holdout_every and holdout_every > 0:
        test = [i for i in range(n) if i % holdout_every == 0]
        train = [i for i in range(n) if i % holdout_every != 0]
        if not train:
            train, test = list(range(n)), []
    else:
        train, test = list(range(n)), []
    return train, test


def cameras_json(dataset) -> list[dict]:
    """INRIA ``cameras.json`` entries: position = camera center, rotation = camera-to-world 3x3 (rows)."""
    out = []
    for i, (cam, name) in enumerate(zip(dataset.cameras, dataset.names)):
        c2w = torch.linalg.inv(cam.world_to_camera.double())
        out.append({"id": i, "img_name": Path(name).stem, "width": cam.width, "height": cam.height,
                    "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(), "fy": cam.fy, "fx": cam.fx})
    return out


# --- the fitter -----------------------------------------------------------------------------------------
@dataclass
class FitState:
    """Everything the loop carries; the stylization loop may keep using ``params`` / ``opt`` / ``density``."""

    params: GaussianParams
    opt: GaussianOptimizer
    density: DensityControl | None
    extent: float
    step: int = 0  # optimizer steps taken
    sh_active: int = 0
    order: list = field(default_factory=list)  # remaining training views of the current epoch
    generator: torch.Generator | None = None  # view order and background colors (CPU)


def _image_list(dataset, device):
    out = []
    for i in range(len(dataset.cameras)):
        img = torch.as_tensor(dataset.image(i))
        cam = dataset.cameras[i]
        if tuple(img.shape) != (cam.height, cam.width, 3):
            raise InputError(f"image {i} is {tuple(img.shape)}, expected [{cam.height}, {cam.width}, 3]")
        out.append(img.to(device=device, dtype=torch.float32).contiguous())
    return out


def _loss(color, gt, lam):
    from ..losses import ssim

    l1 = (color - gt).abs().mean()
    if lam == 0:
        return l1
    return (1.0 - lam) * l1 + lam * (1.0 - ssim(color, gt))


def _save_checkpoint(path: Path, st: FitState, config: ReconstructConfig, names, note="") -> None:
    ckpt = {"format": "tlvg_warp.reconstruct.v1", "iteration": st.step, "sh_active": st.sh_active,
            "extent": st.extent, "params": st.params.state_dict(), "optimizer": st.opt.state_dict(),
            "density": st.density.state_dict() if st.density is not None else None,
            "order": list(st.order), "rng": st.generator.get_state() if st.generator is not None else None,
            "split_rng": (st.density.generator.get_state()
                          if st.density is not None and st.density.generator is not None else None),
            "torch_rng": torch.get_rng_state(), "config": dataclasses.asdict(config), "names": list(names),
            "note": note}
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(ckpt, f)  # to a file object: a full disk raises OSError (a path gives a RuntimeError)


def load_checkpoint(path) -> dict:
    return runs.read_checkpoint(path, "tlvg_warp.reconstruct.v1", "reconstruct")


def _snapshot(st: FitState) -> dict:
    return {"step": st.step, "params": st.params.state_dict(), "opt": st.opt.state_dict(),
            "density": st.density.state_dict() if st.density is not None else None,
            "order": list(st.order), "sh_active": st.sh_active,
            "rng": st.generator.get_state() if st.generator is not None else None}


def _save_ply_checked(g: Gaussians, path: Path) -> int:
    from ..io import save_ply

    bad = sum(int((~torch.isfinite(getattr(g, f))).sum()) for f in Gaussians.FIELDS)
    if bad:
        raise FitDiverged(f"refusing to write a PLY with {bad} non-finite values")
    save_ply(g.to(device="cpu", dtype=torch.float32), path)
    return os.path.getsize(path)


def _restore(st: FitState, snap: dict) -> None:
    """Copy a snapshot (same layout as the current parameters or not) back into ``st``."""
    device = st.params.device
    params = GaussianParams.from_state_dict(snap["params"], device)
    opt = GaussianOptimizer(params, st.opt.lrs, st.opt.extent, st.opt.decay_steps)
    opt.hooks = st.opt.hooks
    opt.load_state_dict(snap["opt"])
    st.params, st.opt = params, opt
    if st.density is not None and snap.get("density") is not None:
        st.density.load_state_dict(snap["density"])
    st.step, st.order, st.sh_active = snap["step"], list(snap["order"]), snap["sh_active"]
    if st.generator is not None and snap.get("rng") is not None:
        st.generator.set_state(snap["rng"])


def fit_scene(dataset, config: ReconstructConfig | None = None, out_dir=None, gaussians: Gaussians | None = None,
              progress: bool = True, *, resume=None, overwrite: bool = False, callback=None):
    """Fit Gaussians to ``dataset`` (anything with ``.cameras``, ``.names``, ``.image(i)``, ``.points``).

    out_dir: where the run's files go (None: nothing is written, Ctrl-C just stops).
    gaussians: start from these instead of initializing from the dataset's points.
    resume: a run folder (or checkpoint path) to continue from.
    callback: ``fn(step, state)`` after every iteration (tests).
    Returns (Gaussians, metrics)."""
    from tqdm import tqdm

    t_start = time.perf_counter()
    cfg = (config or ReconstructConfig()).validate()
    device = resolve_device(cfg.device)
    cams, names = list(dataset.cameras), list(dataset.names)
    if len(cams) == 0:
        raise InputError("dataset has no images")
    if len(cams) < 2:
        raise InputError(f"dataset has a single view ({names[0] if names else '?'}); fitting needs at least 2")
    out = Path(out_dir) if out_dir is not None else None
    ck = load_checkpoint(resume) if resume is not None else None
    if ck is not None and ck["names"] != names:
        raise InputError("the checkpoint was made on a different dataset (its view names differ)", resume)
    if out is not None:
        runs.start_run_dir(out, overwrite, ck is not None, RUN_FILES, render_dirs=("test", "train"))
        write_text(out / "config.yaml", config_yaml(cfg))

    train_idx, test_idx = split_views(len(cams), cfg.holdout_every)
    targets = _image_list(dataset, device)
    bg_fixed = cfg.background if cfg.background is not None else getattr(
        dataset, "background", (1.0, 1.0, 1.0) if getattr(dataset, "kind", "") == "blender" else (0.0, 0.0, 0.0))
    bg_fixed = tuple(float(v) for v in bg_fixed)

    # --- initial state -----------------------------------------------------------------------------------
    from .init import initialize, scene_extent

    init_note = "given Gaussians"
    if ck is not None:
        ext = float(ck["extent"])
        g0 = None
    elif gaussians is not None:
        ext = scene_extent(cams)
        g0 = gaussians.detach().to(device=device, dtype=torch.float32)
    else:
        g0, ext, init_note = initialize(dataset, cfg.sh_degree, cfg.init_opacity, cfg.init_random_points,
                                        cfg.max_init_points, device, cfg.seed)
    lrs = cfg.learning_rates()
    if ck is not None:
        params = GaussianParams.from_state_dict(ck["params"], device)
    else:
        if g0.num > cfg.max_gaussians:  # the budget holds from the start: keep the most opaque
            keep = torch.topk(g0.opacity_logits, cfg.max_gaussians).indices.sort().values
            g0 = g0.subset(keep)
        params = GaussianParams(g0, max(cfg.sh_degree, g0.sh_degree))
    opt = GaussianOptimizer(params, lrs, ext, lrs.means_steps)
    density = None
    if cfg.densify:
        density = DensityControl(cfg.density_config(len(train_idx)), params.num, device)
        density.generator = torch.Generator(device=device).manual_seed(cfg.seed + 1)
    gen = torch.Generator().manual_seed(cfg.seed)
    st = FitState(params, opt, density, ext, 0, 0, [], gen)
    if ck is not None:
        _restore(st, {"step": ck["iteration"], "params": ck["params"], "opt": ck["optimizer"],
                      "density": ck["density"], "order": ck["order"], "sh_active": ck["sh_active"], "rng": ck["rng"]})
        st.params.frozen = params.frozen
        if density is not None and ck.get("split_rng") is not None:
            density.generator.set_state(ck["split_rng"])
        if density is not None:
            density.config = cfg.density_config(len(train_idx))
        torch.set_rng_state(ck["torch_rng"])
        init_note = f"resumed at iteration {st.step} from {resume}"
    start_step = st.step

    def eval_views(g, which):
        from ..losses import psnr, ssim
        from ..renderer import render

        ps, ss, renders = [], [], []
        with torch.no_grad():
            for i in which:
                img = render(g, cams[i], bg_fixed).color.clamp(0, 1)
                ps.append(psnr(img, targets[i]))
                ss.append(float(ssim(img, targets[i])))
                renders.append(img)
        return ps, ss, renders

    eval_idx = test_idx if test_idx else train_idx
    psnr_init = None
    if start_step == 0:
        pi, _, _ = eval_views(st.params.detached(), eval_idx)
        psnr_init = sum(pi) / len(pi)

    # --- the loop -------------------------------------------------------------------------------------------
    from ..renderer import render

    timer = StageTimer(device, TIMED_STAGES, cfg.timing_every)
    bad = torch.zeros((), dtype=torch.bool, device=device)
    last_good = _snapshot(st)
    history = []
    max_deg = st.params.max_sh_degree
    sh_start = max_deg if (gaussians is not None and ck is None) else 0  # a given scene keeps its SH bands
    pbar = tqdm(total=cfg.iterations, initial=start_step, disable=not progress, dynamic_ncols=True,
                desc="reconstruct", unit="it")
    interrupted = False
    t_loop = last_ck = time.perf_counter()
    last_report = start_step
    with _Interrupt() as intr:
        try:
            while st.step < cfg.iterations:
                step = st.step + 1  # 1-based, as graphdeco's `iteration`
                timer.begin(step)
                st.opt.set_step(step)
                st.sh_active = min(max_deg, sh_start + step // cfg.sh_increase_every)
                if not st.order:
                    st.order = [train_idx[k] for k in torch.randperm(len(train_idx), generator=gen).tolist()]
                vi = st.order.pop()
                cam, gt = cams[vi], targets[vi]
                bg = tuple(torch.rand(3, generator=gen).tolist()) if cfg.random_background else bg_fixed
                want_w = density is not None and density.wants_weights_at(step)
                rout = render(st.params.gaussians(), cam, bg, sh_degree=st.sh_active, return_weights=want_w)
                timer.mark("render")
                loss = _loss(rout.color, gt, cfg.lambda_ssim)
                bad |= ~torch.isfinite(loss)
                timer.mark("loss")
                loss.backward()
                timer.mark("backward")
                st.opt.step()
                st.opt.zero_grad()
                timer.mark("optimizer")
                if density is not None and density.accumulating(step):
                    density.accumulate(rout, cam.width, cam.height)
                    # no structural change at the last iteration: the exported model is the one trained
                    if density.is_densify_step(step) and step < cfg.iterations:
                        density.densify_and_prune(st.opt, st.extent, step)
                    if density.is_reset_step(step) and step < cfg.iterations:
                        density.reset_opacity(st.opt)
                timer.mark("density")
                timer.end()
                st.step = step
                if callback is not None:
                    callback(step, st)
                if step % cfg.progress_every == 0 or step == cfg.iterations or intr.flag:
                    with torch.no_grad():
                        mse = ((rout.color.detach() - gt) ** 2).mean()
                    ok = bool(~bad & torch.isfinite(mse) & st.params.all_finite())
                    if not ok:
                        raise FitDiverged(f"non-finite loss or parameters at or before iteration {step}")
                    lv, mv = float(loss.detach()), float(mse)
                    last_good = _snapshot(st)
                    history.append([step, round(lv, 6)])
                    pbar.update(step - last_report)
                    last_report = step
                    pbar.set_postfix(loss=f"{lv:.4f}", psnr=f"{-10 * math.log10(max(mv, 1e-12)):.2f}",
                                     n=st.params.num, refresh=False)
                if out is not None and ((cfg.checkpoint_every and step % cfg.checkpoint_every == 0) or (
                        cfg.checkpoint_seconds and time.perf_counter() - last_ck >= cfg.checkpoint_seconds)):
                    _save_checkpoint(out / "checkpoint.pt", st, cfg, names, note="periodic")
                    last_ck = time.perf_counter()
                if intr.flag:
                    raise KeyboardInterrupt
        except KeyboardInterrupt:
            interrupted = True
        except FitDiverged as e:
            pbar.close()
            msg = str(e)
            if out is not None:
                _restore(st, last_good)
                _save_checkpoint(out / "checkpoint.pt", st, cfg, names, note="last good state before divergence")
                _save_ply_checked(st.params.detached(), out / "point_cloud.ply")
                msg += (f"; stopped. The last good state (iteration {st.step}) is in {out / 'checkpoint.pt'} and "
                        f"{out / 'point_cloud.ply'}. Lower the learning rates or check the input images")
            raise FitDiverged(msg) from None
    pbar.close()
    train_time = time.perf_counter() - t_loop
    if density is not None and device.type == "cuda":
        torch.cuda.synchronize()

    if interrupted:
        if out is not None:
            if not bool(st.params.all_finite()):
                _restore(st, last_good)
            _save_checkpoint(out / "checkpoint.pt", st, cfg, names, note="interrupted")
            _save_ply_checked(st.params.detached(), out / "point_cloud.ply")
            print(f"interrupted at iteration {st.step}: saved {out / 'checkpoint.pt'} and "
                  f"{out / 'point_cloud.ply'}; continue with --resume {out}")
        raise KeyboardInterrupt

    # --- outputs -----------------------------------------------------------------------------------------------
    final = st.params.detached()
    ps, ss, renders = eval_views(final, eval_idx)
    metrics = {
        "psnr": sum(ps) / len(ps), "ssim": sum(ss) / len(ss),
        "eval_split": "test" if test_idx else "train",
        "views": [names[i] for i in eval_idx], "psnr_per_view": ps, "ssim_per_view": ss,
        "psnr_init": psnr_init, "num_gaussians": final.num, "ply_bytes": None,
        "iterations": st.step, "resumed_from": start_step if start_step else None,
        "train_time_s": train_time, "wall_time_s": None, "it_per_s": (st.step - start_step) / max(train_time, 1e-9),
        "time_split": timer.summary(), "extent": st.extent, "init": init_note,
        "num_train_views": len(train_idx), "num_test_views": len(test_idx), "device": str(device),
        "loss_history": history,
    }
    if out is not None:
        metrics["ply_bytes"] = _save_ply_checked(final, out / "point_cloud.ply")
        write_json(out / "cameras.json", cameras_json(dataset))
        if cfg.save_renders:
            for i, img in zip(eval_idx, renders):
                write_image(out / ("test" if test_idx else "train") / f"{Path(names[i]).stem}.png", img)
        if cfg.final_checkpoint:
            _save_checkpoint(out / "checkpoint.pt", st, cfg, names, note="finished")
    metrics["wall_time_s"] = time.perf_counter() - t_start
    if out is not None:
        write_json(out / "metrics.json", metrics)
    return final, metrics


__all__ = ["ReconstructConfig", "FitDiverged", "FitState", "fit_scene", "load_config", "config_yaml",
           "config_from_dict", "split_views", "cameras_json", "load_checkpoint"]
