"""Our scene fit against a minimal gsplat trainer: same photos, same held-out views, same number of iterations.

    python3 benchmarks/gsplat_trainer.py DATA [--images images_4] [--downscale F] [--iterations 7000]
                                         [--raster ours,gsplat] [--warmup 10] [--set KEY=VALUE ...] [--out DIR]

The rasterizers named in --raster fit the scene one after the other in this process. For each it measures:

- training seconds: the optimizer loop alone, torch.cuda.synchronize before both clock reads. Data loading,
  initialization, the held-out evaluation and the one-off kernel compile/load are outside it: a throwaway fit of
  --warmup iterations runs first (its wall time is the table's "warm-up s").
- iterations/s: iterations / training seconds.
- held-out PSNR: the mean over the views `reconstruct` holds out (every 8th view by name, LLFF convention;
  split_views), each rendered with the rasterizer the fit trained with over the scene's background, clamped to
  [0, 1], ``tlvg_warp.losses.psnr``: the way fit_scene computes its metrics.json ``psnr``.
- the final Gaussian count, and the peak CUDA memory of the whole call (torch's allocator high-water mark above
  what was allocated before it, plus the growth of Warp's memory pool, as ``bench raster`` counts it).

The two sides:

- ``ours`` is the product as users run it: ``tlvg_warp.train.reconstruct.fit_scene``, the function
  ``python -m tlvg_warp reconstruct`` calls, on the dataset and config that command builds (its defaults, then
  --images / --downscale / --iterations / --set). Its training seconds and PSNR are the ones it reports itself
  (metrics ``train_time_s`` = its loop time, ``psnr``). That loop also reads the device every ``log_every`` (50)
  steps for its log and its non-finite check, which the minimal trainer does not.
- ``gsplat`` is a minimal trainer on gsplat 1.5.3: ``gsplat.rasterization`` (packed=False) and
  ``gsplat.strategy.DefaultStrategy``, one ``torch.optim.Adam`` per parameter (eps 1e-15), as gsplat's
  examples/simple_trainer.py sets them up. It starts from the very Gaussians fit_scene starts from (``initialize``
  with the config's seed, then the budget), draws the same view at every step (the loop's seeded per-epoch
  permutation, ``ViewOrder``), takes the same loss (our fused (1 - 0.2)·L1 + 0.2·(1 - SSIM), so the loss kernels
  cost the same on both sides), the same learning rates and xyz decay (0.01x over the run), the same SH schedule
  (degree +1 every 1000 steps), the same background and camera (``gsplat_camera``), and our density schedule
  wherever DefaultStrategy has the knob (``gsplat_strategy_kwargs``). Where it cannot follow, ``schedule_notes``
  says so; the notes are printed under the table and written to the JSON.

gsplat is imported only when --raster names it, so ``--raster ours`` runs on a machine without it (and on the CPU).

On the GPU machine (../shared/gpu/README.md stages warp and gsplat 1.5.3 there; gsplat compiles its CUDA
extension on first import, inside the warm-up), from the repository root, with the data under $DATA::

    source /tmp/tlvg-gpu/env.sh && source benchmarks/source_view.sh && \\
    export PYTHONPATH=$(source_view .):$PYTHONPATH TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 && \\
    python3 benchmarks/gsplat_trainer.py $DATA/fern_llff --images images_4 --iterations 7000 \\
        --raster ours,gsplat --out $OUT

It prints the date, the device and the command line, then one markdown table, and writes the table and every
number per rasterizer to DIR/fit_vs_gsplat.json.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import gc
import math
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from tlvg_warp.commands.reconstruct import _load
from tlvg_warp.fileio import write_json
from tlvg_warp.io.datasets import dataset_background
from tlvg_warp.kernels.projection import EWA_BLUR  # the 2D low-pass, 0.3 px² (gsplat's eps2d default too)
from tlvg_warp.runs import resolve_device
from tlvg_warp.train.density import DensityConfig
from tlvg_warp.train.init import initialize
from tlvg_warp.train.loop import photometric_loss
from tlvg_warp.train.optim import exp_decay
from tlvg_warp.train.reconstruct import ReconstructConfig, _image_list, fit_scene, load_config, split_views
from tlvg_warp.train.session import density_control
from tlvg_warp.types import Camera, Gaussians

RASTERS = ("ours", "gsplat")
# gsplat's parameter names -> our fields (whose learning rates LearningRates.for_field gives)
GSPLAT_FIELDS = {"means": "means", "scales": "log_scales", "quats": "quats", "opacities": "opacity_logits",
                 "sh0": "sh_dc", "shN": "sh_rest"}


@dataclass
class Scene:
    """What both fits share: the dataset and config as `reconstruct` builds them, the split, the background."""

    dataset: object
    cfg: ReconstructConfig
    device: torch.device
    train_idx: list  # training views (indices into dataset.cameras)
    eval_idx: list  # the held-out views (the training views when none is held out, as fit_scene)
    held_out: bool  # whether eval_idx are held-out views
    background: tuple  # RGB the scene is rendered over (fit_scene's bg_fixed)


# --- conversions and schedules (no gsplat needed; tests/test_gsplat_trainer_cameras.py checks them) ------------------
def gsplat_camera(cam: Camera, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmat [4,4], K [3,3]) of ``cam`` as gsplat takes them. gsplat's viewmat is world-to-camera with OpenCV axes
    (x right, y down, z forward), as ours; its K is the pinhole matrix with the principal point in pixels where pixel
    (j, i) has its center at (j + 0.5, i + 0.5), as our blend kernel's: no transpose, no half-pixel shift."""
    return cam.world_to_camera.to(dtype), cam.K.to(dtype)


def gsplat_cameras(cams, device) -> tuple[torch.Tensor, torch.Tensor]:
    vm, ks = zip(*(gsplat_camera(c) for c in cams))
    return torch.stack(vm).to(device), torch.stack(ks).to(device)  # [V,4,4], [V,3,3]


class ViewOrder:
    """The training loop's view order (train/loop.py, ``Run.next_batch`` with one view per step): a permutation of
    the training views per epoch, from a CPU generator seeded with the config's seed, taken from its end."""

    def __init__(self, view_ids, seed: int):
        self.ids, self.order = list(view_ids), []
        self.gen = torch.Generator().manual_seed(int(seed))

    def next(self) -> int:
        if not self.order:
            self.order = [self.ids[k] for k in torch.randperm(len(self.ids), generator=self.gen).tolist()]
        return self.order.pop()


def sh_degree_at(step: int, cfg: ReconstructConfig) -> int:
    """The active SH degree at 1-based ``step`` of a fit from scratch (loop.Fit.sh_degree with sh=(0, every, max))."""
    return min(cfg.sh_degree, step // cfg.sh_increase_every)


def means_lr(cfg: ReconstructConfig, extent: float, iterations: int):
    """step -> the xyz learning rate (GaussianOptimizer.set_step: 3DGS's log-linear decay over the run)."""
    steps = cfg.lr.means_steps or iterations
    return lambda step: exp_decay(step, cfg.lr.means * extent, cfg.lr.means_final * extent, steps)


def gsplat_strategy_kwargs(d: DensityConfig, iterations: int) -> dict:
    """DefaultStrategy settings that follow our density schedule, for a trainer that passes 1-based steps (ours).
    gsplat refines when step > refine_start_iter, step % refine_every == 0 and step < refine_stop_iter; we densify
    when s >= start, s % interval == 0, s < until and s < iterations (no change at the last step)."""
    never = iterations + 1  # a step the fit does not reach
    return {
        "refine_start_iter": d.start - 1, "refine_every": d.interval,
        "refine_stop_iter": min(d.until, iterations) if d.until > 0 else iterations,
        # reset_every also gates gsplat's 3D-size pruning (step > reset_every), as the first reset gates our size
        # rules (size_rules after_reset): without resets (reconstruct's default) neither side prunes by size
        "reset_every": d.opacity_reset_interval or never,
        "prune_opa": d.min_opacity, "grow_grad2d": d.grad_threshold, "grow_scale3d": d.percent_dense,
        "prune_scale3d": d.max_world_size if d.max_world_size > 0 else math.inf,  # 0: our world rule is off
        "refine_scale2d_stop_iter": 0,  # gsplat's screen-size split/prune off: ours only after a reset
        "pause_refine_after_reset": 0, "absgrad": False, "revised_opacity": False, "verbose": False,
    }


def schedule_notes(d: DensityConfig, iterations: int, num_start: int) -> list[str]:
    """Where the gsplat fit cannot follow our density schedule (for this config)."""
    notes = [
        "split: ours samples the 2 children from N(mu, Sigma) truncated to +-3 sigma, gsplat untruncated (both: scales "
        "/1.6, opacity kept)",
        "order: ours decides pruning before densifying and never densifies a pruned Gaussian; gsplat grows first, "
        "then prunes (the clone of a low-opacity Gaussian goes with it)",
        "threshold: ours densifies at mean gradient >= grad_threshold, gsplat at > grow_grad2d",
    ]
    if d.use_budget:
        notes.append(f"budget: ours caps the count at {d.budget(num_start):,} (the most opaque kept, the largest "
                     "gradients densified first); DefaultStrategy has no cap")
    if d.prune_unseen:
        notes.append(f"unseen: ours also prunes Gaussians whose sum of alpha*T stays under {d.min_contribution} "
                     "pixel over 2 epochs of views; DefaultStrategy has no such rule")
    if d.opacity_reset_interval and d.opacity_reset_interval < iterations:
        notes.append("opacity reset: DefaultStrategy 1.5.3 never resets (`step % reset_every == 0 & step > 0` is a "
                     "chained comparison that is always false; fixed after 1.5.3), though its 3D-size pruning starts "
                     f"after step {d.opacity_reset_interval}; our screen-size rule ({d.max_screen_size} px) has no "
                     "gsplat counterpart here")
        if abs(d.reset_opacity - 2 * d.min_opacity) > 1e-12:
            notes.append("reset value: gsplat resets to 2 x prune_opa, ours to reset_opacity")
    if d.size_rules != "after_reset":
        notes.append(f"size_rules={d.size_rules}: DefaultStrategy only prunes by size after a reset")
    if d.split_mode != "3dgs":
        notes.append(f"split_mode={d.split_mode}: DefaultStrategy splits as 3DGS")
    return notes


# --- the scene -------------------------------------------------------------------------------------------------
def load_scene(args) -> Scene:
    """The dataset and config exactly as `python -m tlvg_warp reconstruct` builds them from the same arguments."""
    overrides = list(args.set) + [f"{k}={v}" for k, v in (("iterations", args.iterations), ("images", args.images),
                                                          ("downscale", args.downscale)) if v is not None]
    cfg = load_config(None, overrides)
    dataset = _load(args.data, cfg)
    train_idx, test_idx = split_views(len(dataset.cameras), cfg.holdout_every)
    bg = tuple(float(v) for v in cfg.background) if cfg.background is not None else dataset_background(dataset)
    return Scene(dataset, cfg, resolve_device(cfg.device), train_idx, test_idx or train_idx, bool(test_idx), bg)


def initial_gaussians(scene: Scene) -> tuple[Gaussians, float]:
    """fit_scene's starting point: initialize() with the config's seed, within the budget; and the extent."""
    cfg, cams = scene.cfg, scene.dataset.cameras
    g0, ext, _ = initialize(scene.dataset, cfg.sh_degree, cfg.init_opacity, cfg.init_random_points,
                            cfg.max_init_points, scene.device, cfg.seed)
    density = density_control(cfg, g0.num, scene.device, cams, extent=ext, n_views=len(scene.train_idx))
    return density.fit_budget(g0), ext


# --- ours: the product ----------------------------------------------------------------------------------------------
def ours_fit(scene: Scene, iterations: int) -> dict:
    """fit_scene as `reconstruct` runs it (no output folder); its own training time and held-out metrics."""
    cfg = dataclasses.replace(scene.cfg, iterations=iterations)
    _, m = fit_scene(scene.dataset, cfg, None, progress=False)
    return {"train_s": m["train_time_s"], "psnr": m["psnr"], "ssim": m["ssim"], "psnr_per_view": m["psnr_per_view"],
            "num_gaussians": m["num_gaussians"], "densify_steps": len(m["densify_events"])}


# --- gsplat: the minimal trainer --------------------------------------------------------------------------------------
@dataclass
class GsplatFit:
    params: torch.nn.ParameterDict  # means [N,3], scales [N,3] (log), quats [N,4] (wxyz), opacities [N] (logit),
    # sh0 [N,1,3], shN [N,K-1,3]
    optimizers: dict  # one Adam per key of params
    strategy: object  # gsplat.strategy.DefaultStrategy, or None without density control
    state: dict  # the strategy's running state
    viewmats: torch.Tensor  # [V,4,4]
    Ks: torch.Tensor  # [V,3,3]
    targets: list  # [H,W,3] per view
    background: torch.Tensor  # [3]
    lr: object  # step -> xyz learning rate
    rasterization: object  # gsplat.rasterization


def gsplat_params(g: Gaussians) -> torch.nn.ParameterDict:
    """gsplat's layout of ``g`` (copies): activations applied at render time, SH DC and rest apart."""
    t = {"means": g.means, "scales": g.log_scales, "quats": g.quats, "opacities": g.opacity_logits,
         "sh0": g.sh[:, :1], "shN": g.sh[:, 1:]}
    return torch.nn.ParameterDict({k: torch.nn.Parameter(v.detach().clone().contiguous()) for k, v in t.items()})


def gsplat_setup(scene: Scene, iterations: int) -> GsplatFit:
    from gsplat import rasterization  # lazy: only --raster gsplat needs it (and CUDA)
    from gsplat.strategy import DefaultStrategy

    cfg, dev = scene.cfg, scene.device
    g0, ext = initial_gaussians(scene)
    params = gsplat_params(g0)
    opts = {k: torch.optim.Adam([params[k]], lr=cfg.lr.for_field(f, ext), eps=1e-15) for k, f in GSPLAT_FIELDS.items()}
    strategy, state = None, {}
    if "fit" in cfg.density.phases:
        strategy = DefaultStrategy(**gsplat_strategy_kwargs(cfg.density, iterations))
        strategy.check_sanity(params, opts)
        state = strategy.initialize_state(scene_scale=ext)  # 3DGS's extent, as ours (1.1 x camera spread)
    viewmats, Ks = gsplat_cameras(scene.dataset.cameras, dev)
    bg = torch.tensor(scene.background, dtype=torch.float32, device=dev)
    return GsplatFit(params, opts, strategy, state, viewmats, Ks, _image_list(scene.dataset, dev), bg,
                     means_lr(cfg, ext, iterations), rasterization)


def gsplat_render(fit: GsplatFit, cam: Camera, vi: int, sh_degree: int) -> tuple[torch.Tensor, dict]:
    """View ``vi`` through gsplat.rasterization: the image [H,W,3] and its meta (means2d, radii for the strategy)."""
    p = fit.params
    img, _, meta = fit.rasterization(
        means=p["means"], quats=p["quats"], scales=torch.exp(p["scales"]), opacities=torch.sigmoid(p["opacities"]),
        colors=torch.cat([p["sh0"], p["shN"]], 1), viewmats=fit.viewmats[vi:vi + 1], Ks=fit.Ks[vi:vi + 1],
        width=cam.width, height=cam.height, near_plane=cam.near, far_plane=cam.far, eps2d=EWA_BLUR,
        sh_degree=sh_degree, packed=False, backgrounds=fit.background[None])
    return img[0], meta  # [H,W,3]


def gsplat_step(fit: GsplatFit, scene: Scene, step: int, vi: int) -> None:
    """One optimizer step on view ``vi`` (1-based ``step``), in simple_trainer's order: render, strategy pre-backward,
    loss, backward, Adam, strategy post-backward (our loop also densifies after the optimizer step)."""
    fit.optimizers["means"].param_groups[0]["lr"] = fit.lr(step)
    img, meta = gsplat_render(fit, scene.dataset.cameras[vi], vi, sh_degree_at(step, scene.cfg))
    if fit.strategy is not None:
        fit.strategy.step_pre_backward(fit.params, fit.optimizers, fit.state, step, meta)
    photometric_loss(img, fit.targets[vi], scene.cfg.loss.lambda_ssim).backward()
    for opt in fit.optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    if fit.strategy is not None:
        fit.strategy.step_post_backward(fit.params, fit.optimizers, fit.state, step, meta, packed=False)


@torch.no_grad()
def gsplat_eval(fit: GsplatFit, scene: Scene) -> tuple[list, list]:
    """PSNR and SSIM per held-out view, every stored SH band (fit_scene's eval renders without sh_degree)."""
    from tlvg_warp.losses import psnr, ssim  # lazy: imports Warp

    ps, ss = [], []
    for i in scene.eval_idx:
        img = gsplat_render(fit, scene.dataset.cameras[i], i, scene.cfg.sh_degree)[0].clamp(0, 1)
        ps.append(psnr(img, fit.targets[i]))
        ss.append(float(ssim(img, fit.targets[i])))
    return ps, ss


def gsplat_fit(scene: Scene, iterations: int) -> dict:
    fit = gsplat_setup(scene, iterations)
    order = ViewOrder(scene.train_idx, scene.cfg.seed)
    sync(scene.device)
    t0 = time.perf_counter()
    for step in range(1, iterations + 1):
        gsplat_step(fit, scene, step, order.next())
    sync(scene.device)
    train_s = time.perf_counter() - t0
    ps, ss = gsplat_eval(fit, scene)
    return {"train_s": train_s, "psnr": sum(ps) / len(ps), "ssim": sum(ss) / len(ss), "psnr_per_view": ps,
            "num_gaussians": int(fit.params["means"].shape[0])}


# --- measuring ------------------------------------------------------------------------------------------------------
FITS = {"ours": ours_fit, "gsplat": gsplat_fit}


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _warp_pool_high(device: torch.device) -> int:
    import warp as wp

    from tlvg_warp.launch import init_warp

    init_warp()
    return wp.get_mempool_used_mem_high(f"cuda:{device.index or 0}")


def measured(name: str, scene: Scene, iterations: int, warmup: int) -> dict:
    """FITS[name] after a throwaway warm-up fit: its numbers, the call's wall time and peak CUDA memory (MiB)."""
    fn, dev = FITS[name], scene.device
    t0 = time.perf_counter()
    if warmup:
        fn(scene, warmup)  # compiles / loads every kernel of a step and of the evaluation
    warm_s = time.perf_counter() - t0
    gc.collect()
    if dev.type == "cuda":
        sync(dev)
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(dev)
        base, wp0 = torch.cuda.memory_allocated(dev), _warp_pool_high(dev)
    t1 = time.perf_counter()
    r = fn(scene, iterations)
    sync(dev)
    r.update(iterations=iterations, it_per_s=iterations / max(r["train_s"], 1e-9), warmup_s=warm_s,
             warmup_iterations=warmup, wall_s=time.perf_counter() - t1, peak_mib=None)
    if dev.type == "cuda":
        grown = max(_warp_pool_high(dev) - wp0, 0)
        r["peak_mib"] = (torch.cuda.max_memory_allocated(dev) - base + grown) / 2**20
    return r


# --- reporting ------------------------------------------------------------------------------------------------------
COLUMNS = ("rasterizer", "iterations", "train s", "it/s", "held-out PSNR dB", "Gaussians", "peak MiB", "warm-up s")


def table(results: dict) -> str:
    rows = ["| " + " | ".join(COLUMNS) + " |", "|" + " --- |" * len(COLUMNS)]
    for name, r in results.items():
        peak = "n/a (cpu)" if r["peak_mib"] is None else f"{r['peak_mib']:.0f}"
        cells = (name, r["iterations"], f"{r['train_s']:.1f}", f"{r['it_per_s']:.1f}", f"{r['psnr']:.2f}",
                 f"{r['num_gaussians']:,}", peak, f"{r['warmup_s']:.1f}")
        rows.append("| " + " | ".join(map(str, cells)) + " |")
    return "\n".join(rows)


def header(scene: Scene, names: list) -> list[str]:
    dev = scene.device
    device = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"
    cam = scene.dataset.cameras[scene.train_idx[0]]
    held = "held-out" if scene.held_out else "training (none held out)"
    lines = [f"date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}", f"device: {device}",
             "command: " + " ".join(shlex.quote(a) for a in ["python3", *sys.argv]),
             f"scene: {len(scene.train_idx)} training views, PSNR over {len(scene.eval_idx)} {held} views, "
             f"{cam.width}x{cam.height}, torch {torch.__version__}"]
    if "gsplat" in names:
        import gsplat

        lines[-1] += f", gsplat {gsplat.__version__}"
    return lines


def report(scene: Scene, names: list, results: dict, out: Path) -> None:
    cfg, iters = scene.cfg, next(iter(results.values()))["iterations"]
    start = initial_gaussians(scene)[0].num
    notes = schedule_notes(cfg.density, iters, start) if "gsplat" in names else []
    lines, tab = header(scene, names), table(results)
    print("\n".join(lines) + "\n\n" + tab)
    for n in notes:
        print(f"- {n}")
    kw = {k: ("inf" if v == math.inf else v) for k, v in gsplat_strategy_kwargs(cfg.density, iters).items()}
    write_json(out / "fit_vs_gsplat.json", {
        "header": lines, "table": tab, "results": results, "schedule_notes": notes, "gsplat_strategy": kw,
        "config": dataclasses.asdict(cfg), "initial_gaussians": start,
        "views": {"train": scene.train_idx, "eval": scene.eval_idx}})
    print(f"wrote {out / 'fit_vs_gsplat.json'}")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("data", metavar="DATA", help="dataset folder, as for `python -m tlvg_warp reconstruct`")
    p.add_argument("--images", default=None, help="image sub-folder, e.g. images_4 (as reconstruct)")
    p.add_argument("--downscale", type=float, default=None, help="image downscale factor (as reconstruct)")
    p.add_argument("--iterations", type=int, default=7000, help="optimizer steps of every fit (default 7000)")
    p.add_argument("--raster", default="ours,gsplat", help="comma-separated: ours, gsplat (default both)")
    p.add_argument("--warmup", type=int, default=10, help="iterations of the throwaway warm-up fit (0: none)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="reconstruct config override")
    p.add_argument("--out", default="/tmp/tlvg-out", help="folder for fit_vs_gsplat.json (default /tmp/tlvg-out)")
    args = p.parse_args(argv)
    args.names = [n.strip() for n in args.raster.split(",") if n.strip()]
    bad = [n for n in args.names if n not in RASTERS]
    if bad or not args.names:
        p.error(f"--raster takes a comma-separated list of {', '.join(RASTERS)}; got {args.raster!r}")
    return args


def check_gsplat_side(scene: Scene) -> None:
    cfg = scene.cfg
    if scene.device.type != "cuda":
        raise SystemExit("error: --raster gsplat needs CUDA (gsplat has no CPU path); use --raster ours here")
    if cfg.views_per_step != 1 or cfg.random_background:
        raise SystemExit("error: the gsplat trainer takes one view per step over a fixed background "
                         "(views_per_step=1, random_background=false)")


def main(argv=None) -> int:
    args = parse_args(argv)
    scene = load_scene(args)
    if "gsplat" in args.names:
        check_gsplat_side(scene)
    results = {n: measured(n, scene, args.iterations, args.warmup) for n in args.names}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report(scene, args.names, results, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
