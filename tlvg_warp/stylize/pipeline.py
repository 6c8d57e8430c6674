"""The stylization loop (SPEC §3): pre-process, stylize, post-process with one Adam across the phases.

    inp = StylizeInputs(gaussians, cameras, names, photos, style, background)
    result = run_stylize(inp, StylizeConfig(), out_dir)

Every iteration renders ONE training view, drawn at random without replacement per epoch.
1. pre-process: the photos recolored to the painting's palette (ARF color transfer, once), fit with
   0.8·L1 + 0.2·(1−SSIM), density control on (``density_in_pre``).
2. stylize: style (FAST on luminance by default) + content + inverse depth + TV + opacity/scale anchors
   + Lab chroma (0.2 → 0.05) + flow alignment + anisotropy; xyz unlocked with its exponential decay, the
   tangential hook after every Adam step of this phase (and of no other), density control under the budget.
3. post-process: every view rendered and recolored once more; colors and rotations fit to them
   (xyz, scales, opacities keep their values: their gradients are dropped, Adam skips them).

Per-view targets are computed once: recolored photos, VGG features of the photos, the un-stylized scene's
inverse depth (at the start), the target stroke fields (at the start of stylize, from the "matched" or
"canvas" mapping), the post-process targets (at the start of post). The host reads values only every
``log_every`` iterations (log flush, progress bar, NaN check, last-good snapshot) and at densify steps.

Decisions (beyond the spec, documented):
- keep_sh False (default): the whole run works at SH degree 0 (the input's view-dependent bands are
  dropped at the start), so stylized.ply is exactly what was optimized.
- The content loss compares RGB VGG features of the render with those of the original photo, also when the
  style loss is luminance-only (SPEC §3, as ARF-Plus: only the style term is decoupled); that costs a second
  VGG pass per iteration when luminance_only. The RGB-loss ablation changes the style term's input only.
- The "matched" target field of a view is built from the FAST/NNFM cell match of that view's render at the
  start of stylize and then held fixed (a target that moved with the render would chase itself). The match
  is on luminance features whatever the style term's input, so the RGB-loss ablation keeps the same fields.
- The opacity / scale anchors are tensors tracked by density control: a clone or split child is anchored at its own
  value when it is born.
- lock_xyz locks positions during stylize only (the pre-process is a photometric fit).
"""
from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .. import runs
from ..errors import InputError
from ..runs import Interrupt as _Interrupt, StageTimer, resolve_device
from ..fileio import atomic_path, write_text
from ..types import Camera, Gaussians
from .config import StylizeConfig, config_yaml

CHECKPOINT_FORMAT = "tlvg_warp.stylize.v1"
PHASES = ("pre", "stylize", "post")
LOG_TERMS = ("loss", "fit", "style", "content", "depth", "tv", "opacity_reg", "scale_reg", "lab", "align", "aniso")
STAGES = ("render", "vgg", "style", "losses", "flow", "backward", "optimizer", "density")
NORM_EPS = 1e-24  # inside sqrt of the anchor norms: a finite (zero) gradient when nothing has moved yet
POST_FROZEN = ("means", "log_scales", "opacity_logits")  # the post-process fits colors and rotations only
RUN_FILES = ("checkpoint.pt", "stylized.ply", "metrics.json", "log.jsonl", "config.yaml")


SCREEN_SIZE_REFERENCE = 1000  # pixels: the image size 3DGS's max_screen_size was chosen for


class StylizeDiverged(RuntimeError):
    """The loss or the parameters became non-finite; the last good state was saved."""


@dataclass
class StylizeInputs:
    gaussians: Gaussians  # the un-stylized scene
    cameras: list  # Camera per view, at the working resolution
    names: list  # view names
    photos: list  # [H,W,3] float32 in [0,1] per view
    style: torch.Tensor  # the painting [h,w,3] float32 in [0,1]
    background: tuple = (0.0, 0.0, 0.0)  # render background
    sources: dict = field(default_factory=dict)  # where the inputs came from (recorded for --resume)

    def check(self) -> None:
        if len(self.cameras) < 1:
            raise InputError("the dataset has no views")
        if len(self.cameras) != len(self.photos) or len(self.names) != len(self.cameras):
            raise InputError(f"{len(self.cameras)} cameras but {len(self.photos)} photos")
        for cam, ph, nm in zip(self.cameras, self.photos, self.names):
            if tuple(ph.shape) != (cam.height, cam.width, 3):
                raise InputError(f"photo {nm} is {tuple(ph.shape)}, its camera says {cam.height}x{cam.width}")
        if self.gaussians.num == 0:
            raise InputError("the scene has no Gaussians")
        g = self.gaussians
        finite = torch.ones(g.num, dtype=torch.bool, device=g.device)
        for f in g.FIELDS:
            finite &= torch.isfinite(getattr(g, f)).reshape(g.num, -1).all(1)
        bad = int((~finite).sum())
        if bad == g.num:
            raise InputError(f"all {bad} Gaussians of the scene have non-finite parameters")
        if bad:  # a few broken splats (a bad export, an upstream NaN) are dropped rather than poisoning the run
            warnings.warn(f"dropping {bad} of {g.num} Gaussians with non-finite parameters")
            self.gaussians = g.subset(finite)


# --- small utilities -------------------------------------------------------------------------------------------


def tv_loss(img: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of horizontal plus vertical neighbours of an [H,W,3] image."""
    return ((img[1:] - img[:-1]) ** 2).mean() + ((img[:, 1:] - img[:, :-1]) ** 2).mean()


def inverse_depth(depth: torch.Tensor) -> torch.Tensor:
    """1/z where something was rendered (depth > 0), 0 elsewhere."""
    return torch.where(depth > 0, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))


def anchor_norm(x: torch.Tensor, anchor: torch.Tensor) -> torch.Tensor:
    """‖x − anchor‖₂ with a zero (not NaN) gradient at x = anchor."""
    return torch.sqrt(((x - anchor) ** 2).sum() + NORM_EPS)


def phase_of(step: int, steps: tuple) -> tuple[str, int, int]:
    """(phase, 0-based index within it, its length) of the 1-based global ``step``."""
    start = 0
    for name, n in zip(PHASES, steps):
        if step <= start + n:
            return name, step - start - 1, n
        start += n
    raise ValueError(step)


def flow_field_tensor(doubled: torch.Tensor) -> torch.Tensor:
    """[H,W,2] doubled-angle field -> [H,W,3] (c·cos2θ, c·sin2θ, c), the layout flow_terms takes."""
    return torch.cat([doubled, doubled.norm(dim=-1, keepdim=True)], -1).contiguous()


def flow_terms(g, cam, fld, weights):
    """The flow energies (paper eq. 1 + anisotropy), the Warp kernel of tlvg_warp.flow."""
    from ..flow import flow_terms as _flow_terms

    return _flow_terms(g, cam, fld, weights)


# --- the run ---------------------------------------------------------------------------------------------------
@dataclass
class StylizeResult:
    gaussians: Gaussians  # the stylized scene (SH degree 0 unless keep_sh)
    inputs: StylizeInputs
    config: StylizeConfig
    style_work: torch.Tensor  # the painting at its working size [hs,ws,3] (CPU)
    style_field: tuple  # (θ, coherence, doubled) numpy at the working size
    fields: list  # per-view target field [H,W,3] (CPU)
    log: list  # one dict per iteration
    metrics: dict  # timings, counts, VGG flag, ...
    vgg_random: bool = False
    vgg_source: str = ""
    originals: list = field(default_factory=list)  # renders of the un-stylized scene per view [H,W,3] (CPU)


class _State:
    def __init__(self):
        self.step = 0
        self.order: list = []
        self.fields = None  # list of [H,W,3] on device (stylize targets)
        self.post_targets = None  # list of [H,W,3] on device
        self.phase_time = dict.fromkeys(PHASES, 0.0)
        self.counts = {}
        self.log: list = []
        self.densify_events: list = []


def load_checkpoint(path) -> dict:
    return runs.read_checkpoint(path, CHECKPOINT_FORMAT, "stylize")


def run_stylize(inp: StylizeInputs, cfg: StylizeConfig, out_dir=None, *, resume=None, overwrite=False,
                progress=True, vgg=None, interrupt_at: int | None = None, quiet=False,
                on_progress=None) -> StylizeResult:
    """Run the three phases. ``resume``: a run folder / checkpoint to continue. ``vgg``: a loaded feature
    network (default: load_vgg(cfg.vgg_weights)). ``interrupt_at``: behave as if Ctrl-C came after that
    step (tests). ``on_progress(step, gaussians)``: called at every log flush (every ``log_every`` steps and
    at the end of each phase) with the current Gaussians, detached (the live viewer, ``stylize --view``).
    Raises KeyboardInterrupt after saving a checkpoint, StylizeDiverged on NaN."""
    from tqdm import tqdm

    from ..losses import (color_transfer, content_loss, fast_loss, field_at_cells, fit_loss,
                          flatten_feats, flow_alignment_score_torch, gram_loss, lab_chroma_loss, load_vgg, luminance,
                          map_field_canvas, map_field_matched, match_style_cells, nnfm_loss, recolor_sh, resize_style,
                          stroke_field)
    from ..renderer import render
    from ..train.density import DensityConfig, DensityControl
    from ..train.init import scene_extent
    from ..train.optim import GaussianOptimizer, GaussianParams, LearningRates, tangential_hook

    t_start = time.perf_counter()
    cfg = cfg.validate()
    inp.check()
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    out = Path(out_dir) if out_dir is not None else None
    ck = load_checkpoint(resume) if resume is not None else None
    if ck is not None and ck["names"] != list(inp.names):
        raise InputError("the checkpoint was made on a different dataset (its view names differ)", resume)
    if cfg.background is None:  # record the resolved background (evaluation re-renders with it)
        cfg = dataclasses.replace(cfg, background=[float(v) for v in inp.background])
    if out is not None:
        runs.start_run_dir(out, overwrite, ck is not None, RUN_FILES)
        write_text(out / "config.yaml", config_yaml(cfg))

    # --- the feature network and the painting (once) ----------------------------------------------------------
    announce = vgg is None  # a caller that passes the network has already said where it came from
    if vgg is None:
        vgg = load_vgg(cfg.vgg_weights, device)
    vgg = vgg.to(device)
    style_in = luminance if cfg.luminance_only else (lambda x: x)  # the style term's input (and nothing else)
    style_np = inp.style.detach().cpu().numpy().astype(np.float32)
    style_work = torch.from_numpy(resize_style(style_np, cfg.style_height)).contiguous()  # [hs,ws,3]
    with torch.no_grad():
        sf_lum = vgg(luminance(style_work.to(device)), scale=1.0)  # [1,768,fh,fw]: the field match
        sf = sf_lum if cfg.luminance_only else vgg(style_work.to(device), scale=1.0)
    style_cells = tuple(sf_lum.shape[-2:])
    style_feats = flatten_feats(sf).contiguous()  # [768, Ns]: the style term's target
    match_feats = flatten_feats(sf_lum).contiguous()
    s_theta, s_coh, s_doubled = stroke_field(style_work.numpy())
    style_doubled_cells = torch.from_numpy(field_at_cells(s_doubled, style_cells)).to(device)

    # --- per-view targets (once) ---------------------------------------------------------------------------------
    cams: list[Camera] = list(inp.cameras)
    n_views = len(cams)
    bg = tuple(float(v) for v in (cfg.background if cfg.background is not None else inp.background))
    photos = [p.to(device=device, dtype=torch.float32).contiguous() for p in inp.photos]
    recolored, pal_m, pal_t = color_transfer(photos, style_work.to(device))  # palette-matched photos (pre + Lab)
    g_in = inp.gaussians.detach().to(device=device, dtype=torch.float32)
    inv_depth, photo_feats, originals = [], [], []
    with torch.no_grad():
        for i, cam in enumerate(cams):
            ro = render(g_in, cam, bg)
            inv_depth.append(inverse_depth(ro.depth))
            originals.append(ro.color.clamp(0, 1).cpu())
            photo_feats.append(flatten_feats(vgg(photos[i], scale=cfg.vgg_scale)))  # content: RGB
    extent = scene_extent(cams)

    # --- parameters, one Adam across the phases ---------------------------------------------------------------------
    n_pre, n_sty, n_post = steps = cfg.phase_steps()
    g_work = g_in if cfg.keep_sh else g_in.with_sh_degree(0)
    if cfg.palette_init:  # the same colour map the pre-process targets went through, applied in closed form
        g_work = dataclasses.replace(g_work, sh=recolor_sh(g_work.sh, pal_m, pal_t))
    lrs = LearningRates(cfg.lr_means, cfg.lr_means_final, cfg.lr_means_steps, cfg.lr_sh_dc, cfg.lr_sh_rest,
                        cfg.lr_opacity, cfg.lr_scales, cfg.lr_quats)
    budget = cfg.gaussian_budget or max(g_in.num, int(math.ceil(cfg.budget_factor * g_in.num)))
    if not cfg.use_budget:
        budget = 1 << 62
    st = _State()
    gen = torch.Generator().manual_seed(cfg.seed)
    params = GaussianParams(g_work, g_work.sh_degree)  # a resumed run replaces it (load_state_dict below)
    opt = GaussianOptimizer(params, lrs, extent, lrs.means_steps)
    # the tangential hook acts in the Stylize phase only (SPEC §3); the loop installs it per step
    stylize_hooks = [(tangential_hook(cfg.tangential_lambda), ("means",))] if cfg.tangential_lambda > 0 else []
    # 3DGS's screen-size rule was set for ~1000-pixel images; larger renders scale it so that a sharper view
    # of the same scene does not prune every splat as "too big on screen" (seen in the stability suite)
    longest = max(max(c.width, c.height) for c in cams)
    screen_limit = cfg.max_screen_size * max(1.0, longest / SCREEN_SIZE_REFERENCE)
    dcfg = DensityConfig(grad_threshold=cfg.densify_grad_threshold, percent_dense=cfg.percent_dense,
                         min_opacity=cfg.min_opacity, max_screen_size=screen_limit,
                         max_world_size=cfg.max_world_size, interval=cfg.densify_interval, start=0, until=1 << 62,
                         opacity_reset_interval=0, max_gaussians=budget, prune_unseen=cfg.prune_unseen,
                         contribution_window=2 * n_views - 1, split_mode=cfg.split_mode)  # any 2n-1 consecutive views hold an epoch
    density = DensityControl(dcfg, params.num, device)
    density.generator = torch.Generator(device=device).manual_seed(cfg.seed + 1)
    start_counts = {"input": g_in.num}

    # --- the run state: one state_dict / load_state_dict for the checkpoint, the last-good snapshot and resume ---
    def state_dict(checkpoint: bool = False) -> dict:
        sd = {"iteration": st.step, "params": opt.params.state_dict(), "optimizer": opt.state_dict(),
              "density": density.state_dict(), "split_rng": density.generator.get_state(),
              "order": list(st.order), "rng": gen.get_state(), "torch_rng": torch.get_rng_state(),
              "phase_time": dict(st.phase_time), "counts": dict(st.counts),
              "densify_events": list(st.densify_events), "log_len": len(st.log)}
        if checkpoint:  # what a new process needs besides (the per-view targets are fixed once made)
            sd.update({"format": CHECKPOINT_FORMAT, "log": st.log,
                       "fields": [f.cpu() for f in st.fields] if st.fields is not None else None,
                       "post_targets": ([(t.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu() for t in st.post_targets]
                                        if st.post_targets is not None else None),
                       "config": dataclasses.asdict(cfg), "names": list(inp.names), "sources": inp.sources})
        return sd

    def load_state_dict(sd: dict) -> None:
        nonlocal opt
        o = GaussianOptimizer(GaussianParams.from_state_dict(sd["params"], device), lrs, extent, lrs.means_steps)
        o.load_state_dict(sd["optimizer"])
        opt = o
        if sd.get("density") is not None:
            density.load_state_dict(sd["density"])
        if sd.get("anchors") is not None:  # checkpoints before the anchors moved into density control's state
            density.tracked = {k: v.to(device) for k, v in sd["anchors"].items()}
        if sd.get("split_rng") is not None:
            density.generator.set_state(sd["split_rng"])
        st.step, st.order = int(sd["iteration"]), list(sd["order"])
        gen.set_state(sd["rng"])
        torch.set_rng_state(sd["torch_rng"])
        st.phase_time, st.counts = dict(sd["phase_time"]), dict(sd["counts"])
        st.densify_events = list(sd.get("densify_events", []))
        if "log" in sd:
            st.log = list(sd["log"])
        else:
            del st.log[sd["log_len"]:]
        if sd.get("fields") is not None:
            st.fields = [f.to(device) for f in sd["fields"]]
        if sd.get("post_targets") is not None:
            st.post_targets = [t.to(device=device, dtype=torch.float32) / 255.0 for t in sd["post_targets"]]

    if ck is not None:
        load_state_dict(ck)
    start_step = st.step

    def save_checkpoint(note=""):
        if out is None:
            return
        ckpt = state_dict(checkpoint=True)
        ckpt["note"] = note
        with atomic_path(out / "checkpoint.pt") as tmp, open(tmp, "wb") as f:
            torch.save(ckpt, f)  # to a file object: a full disk raises OSError (a path gives a RuntimeError)

    def write_log():
        if out is not None:
            import json
            write_text(out / "log.jsonl", "".join(json.dumps(r) + "\n" for r in st.log))

    # --- phase set-up (idempotent: a resumed run restores these from the checkpoint) ----------------------------
    def features(img):
        return flatten_feats(vgg(img, scale=cfg.vgg_scale))

    def ensure_stylize_targets():
        if not density.tracked:  # the regularizer anchors: density control keeps them aligned
            density.tracked = {"opacity_logits": opt.params.opacity_logits.detach().clone(),
                               "log_scales": opt.params.log_scales.detach().clone()}
        if st.fields is not None:
            return
        fl = []
        with torch.no_grad():
            g = opt.params.gaussians()
            for cam in cams:
                if cfg.field_mapping == "canvas":
                    _, _, d = map_field_canvas(torch.from_numpy(s_doubled).to(device), cam.height, cam.width)
                else:
                    f = vgg(luminance(render(g, cam, bg).color), scale=cfg.vgg_scale)  # [1,768,hc,wc]
                    idx, w = match_style_cells(flatten_feats(f), match_feats)
                    _, _, d = map_field_matched(style_doubled_cells, idx, w, cam.height, cam.width,
                                                tuple(f.shape[-2:]))
                fl.append(flow_field_tensor(d.to(device=device, dtype=torch.float32)))
        st.fields = fl

    def ensure_post_targets():
        if st.post_targets is not None:
            return
        with torch.no_grad():
            g = opt.params.gaussians()
            rs = [render(g, cam, bg).color.clamp(0, 1) for cam in cams]
        st.post_targets, _, _ = color_transfer(rs, style_work.to(device))

    # --- the loop --------------------------------------------------------------------------------------------------
    timer = StageTimer(device, STAGES)
    bad = torch.zeros((), dtype=torch.bool, device=device)
    zero = torch.zeros((), device=device)
    last_good = None
    buf: list = []  # (host info dict, device tensor of LOG_TERMS)
    pbar = None
    phase_t0, cur_phase = None, None
    interrupted = False

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    def close_phase():
        nonlocal phase_t0, pbar
        if cur_phase is not None and phase_t0 is not None:
            sync()
            st.phase_time[cur_phase] += time.perf_counter() - phase_t0
            st.counts[f"after_{cur_phase}"] = opt.params.num
        phase_t0 = None
        if pbar is not None:
            pbar.close()
            pbar = None

    def flush(step, phase, k, rout_color, fld):
        """The one host sync of an interval: log rows, NaN check, progress bar, last-good snapshot."""
        nonlocal buf, last_good
        extra = {}
        if phase == "stylize" and fld is not None:
            with torch.no_grad():
                extra["flow_score"] = flow_alignment_score_torch(rout_color.detach(), fld[..., :2])
        vals = torch.stack([v for _, v in buf]).cpu().tolist() if buf else []
        ok = bool(~bad & opt.params.all_finite())
        for (info, _), row in zip(buf, vals):
            r = dict(info)
            r.update({n: round(float(x), 7) for n, x in zip(LOG_TERMS, row)})
            st.log.append(r)
        if extra and st.log:
            st.log[-1]["flow_score"] = round(float(extra["flow_score"]), 5)
        buf = []
        if not ok:
            raise StylizeDiverged(f"non-finite loss or parameters at or before iteration {step} ({phase} phase)")
        last_good = state_dict()
        if pbar is not None and st.log:
            post = {"loss": f"{st.log[-1]['loss']:.4f}", "n": opt.params.num}
            if "flow_score" in st.log[-1]:
                post["flow"] = f"{st.log[-1]['flow_score']:.3f}"
            pbar.set_postfix(post, refresh=True)

    last_good = state_dict()
    last_ck = [time.perf_counter()]
    if not quiet and announce and vgg.is_random:
        print("WARNING: VGG-16 is RANDOMLY initialized (not pretrained): the style/content losses are not "
              "meaningful; a smoke run only")
    total = sum(steps)
    with _Interrupt() as intr:
        try:
            while st.step < total:
                step = st.step + 1
                phase, k, n_phase = phase_of(step, steps)
                if phase != cur_phase:
                    close_phase()
                    cur_phase = phase
                    if phase == "stylize":
                        ensure_stylize_targets()
                        if k == 0:
                            st.counts["before_stylize"] = opt.params.num
                    elif phase == "post":
                        ensure_post_targets()
                    if k == 0:  # a resumed run keeps the statistics it accumulated (from the checkpoint)
                        density.reset_stats(opt.params.num)
                    pbar = tqdm(total=n_phase, initial=k, disable=not progress, dynamic_ncols=True,
                                desc=f"{phase:>7}", unit="it", leave=True)
                    sync()
                    phase_t0 = time.perf_counter()
                timer.begin(step)
                opt.set_step(step)
                opt.hooks = stylize_hooks if phase == "stylize" else []
                if not st.order:
                    st.order = torch.randperm(n_views, generator=gen).tolist()
                vi = st.order.pop()
                cam = cams[vi]
                use_density = (phase == "pre" and cfg.density_in_pre) or (phase == "stylize" and cfg.density_in_stylize)
                flow_on = phase == "stylize" and (cfg.w_align > 0 or cfg.w_aniso > 0)
                g = opt.params.gaussians()
                rout = render(g, cam, bg, return_weights=use_density or flow_on)
                img = rout.color
                timer.mark("render")
                terms = {}
                fld = None
                if phase == "stylize":
                    fld = st.fields[vi]
                    a = features(style_in(img))  # the style term's features
                    a_rgb = features(img) if cfg.luminance_only else a  # the content term's (RGB)
                    timer.mark("vgg")
                    if cfg.style_loss == "fast":
                        terms["style"] = fast_loss(a, style_feats)
                    elif cfg.style_loss == "nnfm":
                        terms["style"] = nnfm_loss(a, style_feats)
                    else:
                        terms["style"] = gram_loss(a, style_feats)
                    timer.mark("style")
                    terms["content"] = content_loss(a_rgb, photo_feats[vi])
                    terms["depth"] = ((inverse_depth(rout.depth) - inv_depth[vi]) ** 2).mean()
                    terms["tv"] = tv_loss(img)
                    terms["opacity_reg"] = anchor_norm(opt.params.opacity_logits, density.tracked["opacity_logits"])
                    terms["scale_reg"] = anchor_norm(opt.params.log_scales, density.tracked["log_scales"])
                    terms["lab"] = lab_chroma_loss(img, recolored[vi])
                    w_lab = cfg.lab_weight(k, n_phase)
                    loss = (cfg.w_style * terms["style"] + cfg.w_content * terms["content"]
                            + cfg.w_depth * terms["depth"] + cfg.w_tv * terms["tv"]
                            + cfg.w_opacity_reg * terms["opacity_reg"] + cfg.w_scale_reg * terms["scale_reg"]
                            + w_lab * terms["lab"])
                    timer.mark("losses")
                    if flow_on:
                        terms["align"], terms["aniso"] = flow_terms(g, cam, fld, rout.weights)
                        loss = loss + cfg.w_align * terms["align"] + cfg.w_aniso * terms["aniso"]
                    timer.mark("flow")
                else:
                    w_lab = 0.0
                    target = recolored[vi] if phase == "pre" else st.post_targets[vi]
                    terms["fit"] = fit_loss(img, target)
                    loss = terms["fit"]
                    timer.mark("losses")
                terms["loss"] = loss
                bad |= ~torch.isfinite(loss.detach())
                loss.backward()
                timer.mark("backward")
                frozen = POST_FROZEN if phase == "post" else (("means",) if (phase == "stylize" and cfg.lock_xyz) else ())
                for f in frozen:
                    getattr(opt.params, f).grad = None  # Adam skips a parameter without a gradient
                if use_density:
                    density.accumulate(rout, cam.width, cam.height)
                opt.step()
                opt.zero_grad()
                timer.mark("optimizer")
                if use_density and (k + 1) % cfg.densify_interval == 0 and k + 1 < n_phase:
                    ev = density.densify_and_prune(opt, extent, step)
                    ev.update(step=step, phase=phase)
                    st.densify_events.append(ev)
                    timer.mark("density")
                timer.end()
                st.step = step
                if pbar is not None:
                    pbar.update(1)  # host-side count only; loss and Gaussian count at the flush
                buf.append(({"step": step, "phase": phase, "view": vi, "n": opt.params.num, "w_lab": round(w_lab, 6)},
                            torch.stack([terms[t].detach().float().reshape(()) if t in terms else zero
                                         for t in LOG_TERMS])))
                if interrupt_at is not None and step == interrupt_at:
                    intr.flag = True
                # periodic checkpoints come at a flush, with the log written: a killed run resumes from a
                # consistent (parameters, log) pair
                ck_due = out is not None and ((cfg.checkpoint_every and step % cfg.checkpoint_every == 0) or (
                    cfg.checkpoint_seconds and time.perf_counter() - last_ck[0] >= cfg.checkpoint_seconds))
                if step % cfg.log_every == 0 or k + 1 == n_phase or intr.flag or ck_due:
                    flush(step, phase, k, img, fld)
                    if on_progress is not None:
                        on_progress(step, opt.params.detached())
                    if k + 1 == n_phase or step % (cfg.log_every * 10) == 0 or ck_due:
                        write_log()
                if ck_due:
                    save_checkpoint("periodic")
                    last_ck[0] = time.perf_counter()
                if intr.flag:
                    raise KeyboardInterrupt
        except KeyboardInterrupt:
            interrupted = True
        except StylizeDiverged as e:
            close_phase()
            msg = str(e)
            load_state_dict(last_good)
            if out is not None:
                write_log()
                save_checkpoint("last good state before divergence")
                msg += (f"; stopped. The last good state (iteration {st.step}) is in {out / 'checkpoint.pt'} "
                        f"(continue with --resume {out} after lowering the learning rates or loss weights)")
            raise StylizeDiverged(msg) from None
    close_phase()
    if st.fields is None and not interrupted:  # no stylize phase ran: the targets are still needed for the score
        ensure_stylize_targets()
    if interrupted:
        if not bool(opt.params.all_finite()):
            load_state_dict(last_good)
        write_log()
        save_checkpoint("interrupted")
        if out is not None and not quiet:
            print(f"interrupted at iteration {st.step}: saved {out / 'checkpoint.pt'}; continue with --resume {out}")
        raise KeyboardInterrupt
    write_log()
    save_checkpoint("finished")

    final = opt.params.detached()
    final = final if cfg.keep_sh else final.with_sh_degree(0)
    st.counts.setdefault("before_stylize", st.counts.get("after_pre", g_in.num))
    metrics = {
        "iterations": st.step, "phase_steps": dict(zip(PHASES, steps)), "resumed_from": start_step or None,
        "time_per_phase_s": {p: round(t, 3) for p, t in st.phase_time.items()},
        "train_time_s": round(sum(st.phase_time.values()), 3),
        "setup_time_s": None, "stage_split": timer.summary(), "device": str(device),
        "gaussians_input": start_counts["input"], "gaussians_before_stylize": st.counts["before_stylize"],
        "gaussians_after_stylize": st.counts.get("after_stylize", st.counts["before_stylize"]),
        "gaussians_final": final.num, "gaussian_budget": budget if cfg.use_budget else None, "densify_events": st.densify_events,
        "extent": extent, "flow_terms": "warp kernel",
        "vgg_random": bool(vgg.is_random), "vgg_source": vgg.source,
    }
    metrics["setup_time_s"] = round(time.perf_counter() - t_start - metrics["train_time_s"], 3)
    return StylizeResult(final, inp, cfg, style_work, (s_theta, s_coh, s_doubled),
                         [f.cpu() for f in st.fields] if st.fields is not None else [], st.log, metrics,
                         bool(vgg.is_random), vgg.source, originals)


__all__ = ["StylizeInputs", "StylizeResult", "StylizeDiverged", "run_stylize", "load_checkpoint", "phase_of",
           "tv_loss", "inverse_depth", "anchor_norm", "flow_field_tensor", "LOG_TERMS", "PHASES"]
