"""The one training loop: a run is a list of phases over one set of parameters, one Adam, one
density control and one run state.

    run = Run(params, opt, density, [Fit(...), Stylize(...), Fit(...)], cameras, LoopSettings(...), out=dir)
    train(run)

A ``Phase`` is a named stretch of steps: which parameter groups train, whether density control runs, its
post-step hooks, ``setup(run)`` (idempotent: per-phase targets, made once and kept in its state) and
``terms(run, view) -> {name: loss tensor}`` with ``weights(k) -> {name: float}`` (its weight schedule, as
Python floats). The loss of a view is Σ weight·term in the order the phase returns its terms.

The loop owns everything else, once: the view order (one seeded permutation per epoch, drawn identically on
every rank), rendering, backward, the gradient all-reduce, the optimizer step, timing, progress bars,
Ctrl-C, the log, periodic checkpoints and the divergence check. Per step the host reads nothing: the loss
terms go into a device buffer that is read once per ``log_every`` steps (the log rows, the progress bar,
the non-finite check); there the last good state is snapshotted, and a non-finite loss or parameter
restores it and stops. Checkpoints come at such a flush, with log.jsonl written at the same point, every
``checkpoint_seconds`` of wall time (on by default) and/or every ``checkpoint_every`` steps: a killed run
loses at most that much, and resuming from the checkpoint loses no log row.

The run state has ONE ``state_dict()`` / ``load_state_dict()``: parameters, Adam, density control (its
statistics, tracked tensors, split RNG and events), the step, the view order and its RNG, torch's RNG, the
log, phase times and counts, and (for a checkpoint) each phase's targets. It serves the checkpoint, the
last-good snapshot and resume alike.

Several ranks (``dist``, torch.distributed): a step draws ``views_per_step × world`` views; rank r renders
``dist.rank_slice(batch)``; its loss is the mean over its views; the gradients are averaged over the ranks
before the optimizer step (and its hooks); density statistics are summed before each densify decision.
Every rank then holds the same parameters; only the main rank writes (the others wait at a barrier). A
checkpoint records its views per step (ranks × views_per_step); a run resumed with another number (other ranks,
another views_per_step) continues with its own, after a one-line note on stderr: iterations count steps.
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass

import torch

from ..distributed import Dist
from ..fileio import save_torch, write_text
from ..renderer import render
from ..runs import Interrupt, StageTimer, plain_data
from ..progress import Progress
from .optim import FIELDS, GaussianOptimizer, GaussianParams

STAGES = ("render", "loss", "backward", "optimizer", "density")  # what the loop itself times


class Diverged(RuntimeError):
    """The loss or the parameters became non-finite; the last good state was restored (and saved)."""


@dataclass
class LoopSettings:
    """What every command's config gives the loop (its top-level keys of the same names)."""

    log_every: int = 50  # host reads (log rows, progress bar, non-finite check, last-good snapshot) every N steps
    checkpoint_every: int = 0  # also write checkpoint.pt every N steps (0: by time only)
    checkpoint_seconds: float = 60.0  # ... and at the first log point this long after the last one (0: off)
    views_per_step: int = 1  # views per rank per step (the loss is their mean)
    timing_every: int = 20  # sample the per-stage time split every N steps
    final_checkpoint: bool = True  # write checkpoint.pt at the end (lets --resume extend a run)
    render_headroom: float = 0.0  # > 1, on a GPU: key buffers sized from a view's last count x this (0: exact counts)


@dataclass
class View:
    """One view of a step: its index in the dataset, camera, background and the loop's render of it."""

    index: int
    cam: object  # Camera
    background: tuple
    out: object  # RenderOutput of ``gaussians``
    gaussians: object  # the step's differentiable Gaussians (one for every view of the step)


class Phase:
    """A stretch of ``steps`` optimizer steps. Subclasses give ``terms`` (and usually ``TERMS``, ``setup``,
    ``weights``); the defaults train every group, without density control or hooks."""

    TERMS: tuple = ()  # the names ``terms`` may return (the log's columns; one it leaves out logs 0)
    STAGES: tuple = ()  # stages ``terms`` marks on run.timer (beyond the loop's own)
    render_weights = False  # the terms need Σ αT per Gaussian (RenderOutput.weights)

    def __init__(self, name: str, steps: int, *, trainable=FIELDS, density: bool = False, hooks=(), label=None,
                 fresh_moments: bool = False):
        self.name, self.steps, self.label = name, int(steps), label or name
        self.trainable, self.density, self.hooks = tuple(trainable), bool(density), list(hooks)
        # Adam's state of the trainable groups cleared when the phase starts: the moments of a phase before it,
        # built on other terms, would otherwise set this phase's first steps (their direction and size)
        self.fresh_moments = bool(fresh_moments)

    def setup(self, run: "Run") -> None:
        """Make what the phase needs (idempotent: a resumed run has it from the checkpoint)."""

    def terms(self, run: "Run", view: View) -> dict:
        raise NotImplementedError

    def weights(self, k: int) -> dict:
        """{term: weight} at step ``k`` (0-based) of the phase; a term not named has weight 1."""
        return {}

    def background(self, run: "Run") -> tuple:
        return run.background

    def sh_degree(self, step: int) -> int | None:
        return None  # every stored band

    def row(self, k: int) -> dict:
        """Host values added to the log row of step ``k`` (e.g. a scheduled weight)."""
        return {}

    def flush_extra(self, run: "Run", view: View) -> dict:
        """Values measured at a log flush on its last view (added to the last row and the progress bar)."""
        return {}

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, sd: dict, device=None) -> None:
        pass


def photometric_loss(img: torch.Tensor, ref: torch.Tensor, lam: float = 0.2) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM) (3DGS; λ 0.2 is SPEC §3's 0.8·L1 + 0.2·(1 − SSIM)): one fused op for λ > 0
    (losses.fit_loss: the L1 and the SSIM in the same Warp kernels)."""
    from ..losses import fit_loss  # lazy: imports Warp

    return (img - ref).abs().mean() if lam == 0 else fit_loss(img, ref, lam)


class Fit(Phase):
    """Fit the renders to per-view target images with ``photometric_loss`` (3DGS's loss).

    targets: [H,W,3] per view on the device, or None: ``make_targets(run)`` makes them at setup (they are then
    part of the phase's state, so a resumed run uses the same ones). sh: (start degree, +1 every N steps, max
    degree) for 3DGS's SH schedule, None for every band. random_background: a random color per view (from the
    view-order RNG). psnr: report the PSNR of the last view at each log flush."""

    TERMS = ("fit",)

    def __init__(self, name: str, steps: int, targets=None, *, make_targets=None, lambda_ssim: float = 0.2,
                 sh=None, random_background: bool = False, psnr: bool = False, **kw):
        super().__init__(name, steps, **kw)
        self.targets, self.make_targets, self.lam = targets, make_targets, float(lambda_ssim)
        self.sh, self.random_background, self.psnr = sh, random_background, psnr

    def setup(self, run: "Run") -> None:
        if self.targets is None:
            self.targets = self.make_targets(run)

    def terms(self, run: "Run", view: View) -> dict:
        return {"fit": photometric_loss(view.out.color, self.targets[view.index], self.lam)}

    def background(self, run: "Run") -> tuple:
        return tuple(torch.rand(3, generator=run.gen).tolist()) if self.random_background else run.background

    def sh_degree(self, step: int) -> int | None:
        if self.sh is None:
            return None
        start, every, top = self.sh
        return min(top, start + step // every)

    def flush_extra(self, run: "Run", view: View) -> dict:
        if not self.psnr:
            return {}
        with torch.no_grad():
            mse = float(((view.out.color.detach() - self.targets[view.index]) ** 2).mean())
        return {"psnr": round(-10.0 * math.log10(max(mse, 1e-12)), 3)}

    def state_dict(self) -> dict:
        made = self.make_targets is not None and self.targets is not None
        return {"targets": [t.detach().cpu() for t in self.targets] if made else None, "sh": self.sh}

    def load_state_dict(self, sd: dict, device=None) -> None:
        if sd.get("targets") is not None and self.make_targets is not None:
            self.targets = [t.to(device=device, dtype=torch.float32) for t in sd["targets"]]
        if sd.get("sh") is not None:
            self.sh = tuple(sd["sh"])


class Run:
    """The run state: parameters, Adam, density control, the phases and their order, the view order, the
    log. ``out``: the run folder (checkpoint.pt, log.jsonl), None to write nothing; ``fmt`` and ``extra``
    (a callable returning a dict) go into every checkpoint."""

    def __init__(self, params, opt, density, phases: list, cams: list, settings: LoopSettings, *, device,
                 seed: int = 0, view_ids=None, background=(0.0, 0.0, 0.0), dist=None, out=None,
                 fmt: str = "tlvg_warp.run.v1", extra=None, log_file: str | None = "log.jsonl"):
        self.params, self.opt, self.density = params, opt, density
        self.phases, self.cams, self.settings = list(phases), list(cams), settings
        self.device, self.background = torch.device(device), tuple(background)
        self.dist = dist if dist is not None else Dist()
        self.out, self.fmt, self.extra, self.log_file = out, fmt, extra, log_file
        self.view_ids = list(range(len(cams))) if view_ids is None else list(view_ids)
        self.gen = torch.Generator().manual_seed(seed)  # the view order (CPU; identical on every rank)
        self.step, self.order, self.log = 0, [], []
        self.phase_time = {p.name: 0.0 for p in self.phases}
        self.counts: dict = {}
        self.columns = ("loss", *dict.fromkeys(t for p in self.phases for t in p.TERMS))
        self.timer = StageTimer(self.device, (*STAGES[:1], *dict.fromkeys(s for p in self.phases for s in p.STAGES),
                                              *STAGES[1:]), settings.timing_every)
        self.loop_time = 0.0  # this process's seconds in the loop
        self.on_phase_end = None  # callable(run, phase) -> {name: number}, kept in counts as "<name>_after_<phase>"
        # render_headroom > 1: on a GPU the training renders size their key buffers from each view's last count (no
        # host wait a step); on the CPU the count costs no wait, and every render counts exactly
        self.budget = None
        if settings.render_headroom and self.device.type == "cuda":
            from ..raster import IntersectionBudget  # lazy: imports Warp, which this module does not need

            self.budget = IntersectionBudget(settings.render_headroom)
        density.views_per_step = settings.views_per_step * self.dist.world

    # --- phases and views --------------------------------------------------------------------------------
    @property
    def total(self) -> int:
        return sum(p.steps for p in self.phases)

    def phase_at(self, step: int) -> tuple[Phase, int]:
        """(phase, 0-based index within it) of the 1-based global ``step``."""
        start = 0
        for p in self.phases:
            if step <= start + p.steps:
                return p, step - start - 1
            start += p.steps
        raise ValueError(step)

    def phase(self, name: str) -> Phase:
        return next(p for p in self.phases if p.name == name)

    def next_batch(self, phase: Phase) -> list[tuple[int, tuple]]:
        """The step's global batch [(view index, background)]: views without replacement per epoch."""
        batch = []
        for _ in range(self.settings.views_per_step * self.dist.world):
            if not self.order:
                self.order = [self.view_ids[k] for k in torch.randperm(len(self.view_ids), generator=self.gen).tolist()]
            batch.append(self.order.pop())
        return [(vi, phase.background(self)) for vi in batch]

    # --- the run state --------------------------------------------------------------------------------------
    def state_dict(self, checkpoint: bool = False) -> dict:
        """Copies of everything that changes during the run. ``checkpoint``: also what a new process needs (the
        log, the phases' targets, ``extra``) — a collective when several ranks run (density statistics)."""
        sd = {"iteration": self.step, "phase": self.phase_at(self.step)[0].name if self.step else None,
              "params": self.params.state_dict(), "optimizer": self.opt.state_dict(),
              "density": self.density.state_dict(global_stats=checkpoint), "order": list(self.order),
              "rng": self.gen.get_state(), "torch_rng": torch.get_rng_state(), "phase_time": dict(self.phase_time),
              "counts": dict(self.counts), "log_len": len(self.log)}
        if checkpoint:
            sd.update({"format": self.fmt, "log": list(self.log), "step_views": self.step_views(),
                       "phases": {p.name: p.state_dict() for p in self.phases}, **(self.extra() if self.extra else {})})
        return sd

    def step_views(self) -> dict:
        """The views of a step: ranks x views_per_step (a checkpoint records them)."""
        return {"ranks": self.dist.world, "per_rank": self.settings.views_per_step}

    def load_state_dict(self, sd: dict) -> None:
        params = GaussianParams.from_state_dict(sd["params"], self.device)
        opt = GaussianOptimizer(params, self.opt.lrs, self.opt.extent, self.opt.decay_steps)
        opt.load_state_dict(sd["optimizer"])
        opt.hooks = self.opt.hooks
        self.params, self.opt = params, opt
        self.density.load_state_dict(sd["density"], from_checkpoint="format" in sd)
        if "format" in sd and sd.get("step_views") and self.dist.is_main:
            _note_views(sd["step_views"], self.step_views())
        self.step, self.order = int(sd["iteration"]), list(sd["order"])
        self.gen.set_state(sd["rng"])
        torch.set_rng_state(sd["torch_rng"])
        self.phase_time.update(sd.get("phase_time", {}))
        self.counts = dict(sd.get("counts", {}))
        if "log" in sd:
            self.log = list(sd["log"])
        else:
            del self.log[sd["log_len"]:]
        for p in self.phases:
            if p.name in sd.get("phases", {}):
                p.load_state_dict(sd["phases"][p.name], self.device)

    # --- files (main rank only) ------------------------------------------------------------------------------
    def save_checkpoint(self, note: str = "") -> None:
        if self.out is None:
            return
        sd = self.state_dict(checkpoint=True)  # every rank: the density statistics are summed
        if self.dist.is_main:
            sd["note"] = note
            save_torch(self.out / "checkpoint.pt", plain_data(sd))  # data only: it loads without unpickling code
        self.dist.barrier()

    def write_log(self) -> None:
        if self.out is not None and self.log_file and self.dist.is_main:
            write_text(self.out / self.log_file, "".join(json.dumps(r) + "\n" for r in self.log))

    def sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def metrics(self, start_step: int) -> dict:
        return {"iterations": self.step, "phase_steps": {p.name: p.steps for p in self.phases},
                "resumed_from": start_step or None,
                "time_per_phase_s": {p: round(t, 3) for p, t in self.phase_time.items()},
                "train_time_s": round(sum(self.phase_time.values()), 3), "stage_split": self.timer.summary(),
                "densify_events": list(self.density.events), "render_counts": self.render_counts(),
                "peak_gpu_mib": peak_gpu_mib(self.device)}

    def render_counts(self) -> dict | None:
        """How this process's training renders sized their key buffers (``IntersectionBudget.counts``); None where
        every render counts exactly (the CPU, or ``render_headroom`` 0)."""
        return self.budget.counts() if self.budget is not None else None


def peak_gpu_mib(device: torch.device) -> float | None:
    """torch's peak allocated memory on ``device`` in this process so far, MiB; None on the CPU."""
    return round(torch.cuda.max_memory_allocated(device) / 2 ** 20, 1) if device.type == "cuda" else None


def _note_views(was: dict, now: dict) -> None:
    """A resumed run continues with its own views per step, also when the checkpoint's differ (another number of
    ranks or views_per_step): one line on stderr says so. (A checkpoint from before they were recorded: none.)"""
    a, b = was["ranks"] * was["per_rank"], now["ranks"] * now["per_rank"]
    if a != b:
        def how(v):
            return f"{v['ranks']} rank{'s' if v['ranks'] != 1 else ''} x views_per_step {v['per_rank']}"
        print(f"note: views per step changed from {a} ({how(was)}, the checkpoint's) to {b} ({how(now)}); "
              "iterations keep counting steps", file=sys.stderr, flush=True)


# --- the loop ---------------------------------------------------------------------------------------------------
class _Stop(Exception):
    def __init__(self, step: int, phase: str):
        self.step, self.phase = step, phase


def train(run: Run, *, progress: bool = True, quiet: bool = False, callback=None, on_flush=None,
          interrupt_at: int | None = None, diverged=Diverged, hint: str = "", on_stop=None) -> None:
    """Run every remaining step of ``run``. ``callback(step, run)`` after each step (tests); ``on_flush(step,
    gaussians)`` at each log flush (the live viewer); ``interrupt_at``: act as if Ctrl-C came after that step;
    ``on_stop(run, note) -> [paths]``: the command's own files at an interruption or divergence (e.g. a PLY).
    Raises KeyboardInterrupt after saving a checkpoint, ``diverged`` (a Diverged subclass) on a non-finite
    loss or parameter, with the last good state restored and saved."""
    loop = _Loop(run, progress and run.dist.is_main, callback, on_flush, interrupt_at)
    with Interrupt() as intr:
        loop.intr = intr
        try:
            loop.run()
        except KeyboardInterrupt:
            loop.close_phase(final=True)
            # the state of the last flush: the one a Ctrl-C flag stops at, and consistent with the log (a second
            # Ctrl-C may have stopped a step half-way, after the optimizer step and before its log row)
            run.load_state_dict(loop.last_good)
            files = _stop_files(run, "interrupted", on_stop)
            if run.out is not None and not quiet and run.dist.is_main:
                print(f"interrupted at iteration {run.step}: saved {' and '.join(map(str, files))}; "
                      f"continue with --resume {run.out}")
            raise
        except _Stop as s:
            loop.close_phase(final=True)
            msg = f"non-finite loss or parameters at or before iteration {s.step} ({s.phase} phase)"
            run.load_state_dict(loop.last_good)
            files = _stop_files(run, "last good state before divergence", on_stop)
            if files:
                msg += f"; stopped. The last good state (iteration {run.step}) is in {' and '.join(map(str, files))}"
                msg += hint.format(out=run.out)
            raise diverged(msg) from None
    loop.close_phase(final=True)
    run.write_log()
    if run.settings.final_checkpoint:
        run.save_checkpoint("finished")


def _stop_files(run: Run, note: str, on_stop) -> list:
    if run.out is None:
        return []
    run.write_log()
    run.save_checkpoint(note)
    extra = on_stop(run, note) if on_stop is not None else []
    return [run.out / "checkpoint.pt", *extra]


class _Loop:
    """The loop's per-run bookkeeping (progress bar, flush buffer, timers); ``run()`` is the loop."""

    def __init__(self, run: Run, progress: bool, callback, on_flush, interrupt_at):
        self.run_, self.progress, self.callback, self.on_flush = run, progress, callback, on_flush
        self.interrupt_at, self.intr = interrupt_at, None
        self.buf: list = []  # (host row info, column indices, device tensor) per step since the last flush
        self.phase = self.t0 = None
        # one progress line for the run, with its ETA across the phases (plain lines when not on a terminal)
        self.pbar = Progress([(p.label, p.steps, type(p).__name__) for p in run.phases], run.step) if progress else None
        self.last_good = run.state_dict()
        self.last_ck = time.perf_counter()
        self.stop_agreed = False  # several ranks: some rank was interrupted (combined at the last flush)
        self.tables: dict = {}  # phase name -> its WeightTable

    def weight_table(self, phase: Phase) -> "WeightTable":
        t = self.tables.get(phase.name)
        if t is None:
            t = self.tables[phase.name] = WeightTable(phase)
        return t

    # phases ---------------------------------------------------------------------------------------------------
    def open_phase(self, phase: Phase, k: int) -> None:
        r = self.run_
        phase.setup(r)
        if k == 0:
            r.counts[f"before_{phase.name}"] = r.params.num
            r.density.begin_phase(r.params.num)
            if phase.fresh_moments:
                r.opt.clear_moments(phase.trainable)
        r.params.set_trainable(phase.trainable)
        r.opt.hooks = list(phase.hooks)
        if self.pbar is not None:
            self.pbar.start_phase(r.phases.index(phase), k)
        self.phase = phase
        r.sync()
        self.t0 = time.perf_counter()

    def close_phase(self, final: bool = False) -> None:
        r = self.run_
        if self.phase is not None and self.t0 is not None:
            r.sync()
            dt = time.perf_counter() - self.t0
            r.phase_time[self.phase.name] += dt
            r.loop_time += dt
            r.counts[f"after_{self.phase.name}"] = r.params.num
        self.t0 = self.phase = None
        if self.pbar is not None:
            self.pbar.end_phase()
            if final:  # the run ends or stops: the progress line is finished
                self.pbar.close()

    # the loop ---------------------------------------------------------------------------------------------------
    def run(self) -> None:
        r = self.run_
        while r.step < r.total:
            step = r.step + 1
            phase, k = r.phase_at(step)
            if phase is not self.phase:
                self.close_phase()
                self.open_phase(phase, k)
            view = self.step(phase, k, step)
            r.step = step
            if self.pbar is not None:
                self.pbar.update(step)  # host-side count only; loss and Gaussian count at the flush
            if self.callback is not None:
                self.callback(step, r)
            if self.interrupt_at is not None and step == self.interrupt_at:
                self.intr.flag = True
            ck_due = self.checkpoint_due(step)
            # one rank alone: stop at once; several: Ctrl-C reaches the ranks at different steps, so they stop
            # together at the next log point, where flush() combines their flags (a rank that flushed alone
            # would enter a collective the others never join)
            stop_now = self.intr.flag and r.dist.world == 1
            if k + 1 == phase.steps and r.on_phase_end is not None:  # e.g. the holes each phase left (stylize)
                r.counts.update({f"{name}_after_{phase.name}": v for name, v in r.on_phase_end(r, phase).items()})
            if step % r.settings.log_every == 0 or k + 1 == phase.steps or stop_now or ck_due:
                self.flush(step, phase, view)
                if k + 1 == phase.steps or step % (r.settings.log_every * 10) == 0 or ck_due:
                    r.write_log()
            if ck_due:
                r.save_checkpoint("periodic")
                self.last_ck = time.perf_counter()
            if stop_now or self.stop_agreed:
                raise KeyboardInterrupt

    def step(self, phase: Phase, k: int, step: int) -> View:
        """One optimizer step: render this rank's views, the phase's terms, backward, all-reduce, Adam, density."""
        r = self.run_
        t = r.timer
        t.begin(step)
        r.opt.set_step(step)
        mine = r.dist.rank_slice(r.next_batch(phase))
        g = r.params.gaussians()  # one differentiable view of the parameters for every view of the step
        dens = phase.density and r.density.accumulating(k + 1)
        want_w = phase.render_weights or (dens and r.density.wants_weights(k + 1))
        n, rows = len(mine), []
        if r.budget is not None:  # a densify step may keep the count and move every view's: count exactly after one
            r.budget.scene = len(r.density.events)
        for vi, bg in mine:
            cam = r.cams[vi]
            view = View(vi, cam, bg, render(g, cam, bg, sh_degree=phase.sh_degree(step), return_weights=want_w,
                                            budget=r.budget, budget_key=vi), g)
            t.mark("render")
            terms = phase.terms(r, view)
            loss = self.weight_table(phase).loss(terms, k)
            t.mark("loss")
            # on this thread: autograd's per-device worker thread costs a handoff per backward (about 40 us of host
            # on the GPU host) and runs the Python backwards of the ops on a core whose caches are cold
            with torch.autograd.set_multithreading_enabled(False):
                (loss if n == 1 else loss / n).backward()
            t.mark("backward")
            if dens:
                r.density.accumulate(view.out, cam.width, cam.height, grad_scale=n)
            rows.append(torch.stack([loss.detach().float(), *(x.detach().float() for x in terms.values())]))
        r.dist.all_reduce_mean_([getattr(r.params, f).grad for f in FIELDS])
        r.opt.step()
        r.opt.zero_grad()
        t.mark("optimizer")
        if dens:
            rare = r.density.acts_at(k + 1, phase.steps)
            t0 = t.timed() if rare else None
            r.density.step(r.opt, k + 1, phase.steps, {"step": step, "phase": phase.name})
            if rare:
                t.done("density", t0)
        t.end()
        info = {"step": step, "phase": phase.name, "view": mine[0][0] if n == 1 else [vi for vi, _ in mine],
                "n": r.params.num, **phase.row(k)}
        self.buf.append((info, tuple(terms), rows[0] if n == 1 else torch.stack(rows).mean(0)))
        return view

    def checkpoint_due(self, step: int) -> bool:
        r = self.run_
        s = r.settings
        if r.out is None:
            return False
        if s.checkpoint_every and step % s.checkpoint_every == 0:
            return True
        if not s.checkpoint_seconds:
            return False
        if r.dist.world == 1:
            return time.perf_counter() - self.last_ck >= s.checkpoint_seconds
        # several ranks: the main rank's clock decides, at log points only (one host broadcast there)
        if step % s.log_every:
            return False
        return bool(r.dist.broadcast_object(time.perf_counter() - self.last_ck >= s.checkpoint_seconds))

    def flush(self, step: int, phase: Phase, view: View) -> None:
        """The one host read of an interval: log rows, the non-finite check, last-good snapshot, progress bar."""
        r = self.run_
        buf, self.buf = self.buf, []
        ok_flag = r.params.all_finite().float().reshape(1)
        flags = [ok_flag]
        if r.dist.world > 1:  # and whether any rank was interrupted (the mean of the flags is > 0)
            flags.append(torch.full((1,), float(self.intr.flag), dtype=ok_flag.dtype, device=ok_flag.device))
        flat = torch.cat([v for _, _, v in buf] + flags)
        r.dist.all_reduce_mean_([flat])  # the log shows the mean over every rank's views
        vals = flat.cpu().tolist()
        if r.dist.world > 1:
            self.stop_agreed = vals.pop() > 0
        ok = vals[-1] == 1.0
        i = 0
        for info, names, _ in buf:
            row = dict(info)
            row.update(dict.fromkeys(r.columns, 0.0))  # a term the phase did not compute logs 0
            for c, x in zip(("loss", *names), vals[i:i + 1 + len(names)]):
                row[c] = round(x, 7)
            ok = ok and math.isfinite(vals[i])  # the loss of that step
            i += 1 + len(names)
            r.log.append(row)
        if not ok:
            raise _Stop(step, phase.name)
        extra = phase.flush_extra(r, view)
        if extra and r.log:
            r.log[-1].update(extra)
        self.last_good = r.state_dict()
        if self.pbar is not None and r.log:
            post = {"loss": f"{r.log[-1]['loss']:.4f}", "n": r.params.num}
            post.update({k: (f"{v:.3f}" if isinstance(v, float) else v) for k, v in extra.items()})
            self.pbar.postfix(post)
        if self.on_flush is not None:
            self.on_flush(step, r.params.detached())


class WeightTable:
    """Σ weight·term of a phase's steps as one dot product. The phase's weights for every one of its steps are put on
    the device once (a copy from the host per step would wait for the GPU), so a step costs two launches (stack, dot)
    instead of a multiply and an add per term, and as many fewer nodes in the backward. Terms whose weight is 0 on
    every step of the phase are left out of the sum (no backward through them), as ``weighted_sum`` drops them."""

    def __init__(self, phase: Phase):
        self.phase = phase
        self.tables: dict = {}  # (term names, dtype, device) -> (indices of the live terms, [steps, live] weights)

    def loss(self, terms: dict, k: int) -> torch.Tensor:
        vals = list(terms.values())
        key = (tuple(terms), vals[0].dtype, vals[0].device)
        entry = self.tables.get(key)
        if entry is None:
            rows = [self.phase.weights(j) for j in range(self.phase.steps)]
            w = [[float(row.get(name, 1.0)) for name in key[0]] for row in rows]
            live = [i for i in range(len(vals)) if any(r[i] != 0 for r in w)]
            table = torch.tensor([[r[i] for i in live] for r in w], dtype=key[1], device=key[2])  # [steps, live]
            alone = len(live) == 1 and all(r[live[0]] == 1.0 for r in w)  # e.g. a Fit phase: the term is the loss
            entry = self.tables[key] = (live, table, alone)
        live, table, alone = entry
        if not live:
            return vals[0] * 0.0
        if alone:
            return vals[live[0]]
        return torch.dot(torch.stack([vals[i].reshape(()) for i in live]), table[k])


def weighted_sum(terms: dict, weights: dict) -> torch.Tensor:
    """Σ weight·term in the order of ``terms`` (weight 1 when not named; a weight of 0 drops the term)."""
    loss = None
    for name, t in terms.items():
        w = weights.get(name, 1.0)
        if w == 0:
            continue
        x = t if w == 1.0 else w * t
        loss = x if loss is None else loss + x
    return loss if loss is not None else next(iter(terms.values())) * 0.0


__all__ = ["Diverged", "LoopSettings", "View", "Phase", "Fit", "Run", "train", "WeightTable", "weighted_sum",
           "photometric_loss", "STAGES"]
