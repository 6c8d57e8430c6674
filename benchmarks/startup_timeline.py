"""From the command to the first iteration: a timeline of one `stylize` run, each mark in seconds since the process
was created (Linux: /proc/self/stat's start time against CLOCK_BOOTTIME, 10 ms resolution), so that the
interpreter's own start-up and the imports are counted and the process's exit is not.

    python benchmarks/startup_timeline.py [--no-warmup] [STYLIZE ARGS ...]    e.g. --scene fern.spz --iterations 1

--no-warmup: without the CUDA context made in a thread beside the imports (tlvg_warp/warmup.py).

Marks: the script's first line, `import tlvg_warp.cli`, `import torch`, the VGG loaded, the job resolved (config,
device and VGG), the inputs assembled, Warp's runtime up (wp.init), the painting's targets prepared, the run built,
the first step begun and ended (the GPU synchronized), and the command returned. docs/performance.md quotes it.
"""
from __future__ import annotations

import os
import time


def since_process_start() -> float:
    """Seconds since this process was created."""
    with open("/proc/self/stat") as f:
        start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22: start time in clock ticks since boot
    return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")


MARKS: list[tuple[str, float]] = [("script starts", since_process_start())]


def mark(name: str) -> None:
    MARKS.append((name, since_process_start()))


def wrap(owner, attr: str, before: str | None, after: str | None, sync=None):
    """Replace owner.attr with a version that marks its first call's start and end."""
    fn, seen = getattr(owner, attr), []

    def wrapped(*a, **k):
        first = not seen
        seen.append(1)
        if first and before:
            mark(before)
        out = fn(*a, **k)
        if first and after:
            if sync is not None:
                sync()
            mark(after)
        return out
    setattr(owner, attr, wrapped)


def main(argv: list[str], warmup: bool = True) -> int:
    from tlvg_warp.warmup import start_cuda_warmup

    if warmup:  # as `python -m tlvg_warp` does (tlvg_warp/__main__.py)
        start_cuda_warmup(argv)
    import tlvg_warp.cli as cli
    mark("import tlvg_warp.cli")
    import torch
    mark("import torch")
    # up front, so that their functions can be wrapped: the command imports them inside its run (the time is the
    # same; the marks after this one start later by it)
    import warp as wp

    import tlvg_warp.losses as losses
    import tlvg_warp.stylize.job as job
    import tlvg_warp.stylize.pipeline as pipeline
    import tlvg_warp.train.loop as loop

    def sync():
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            torch.cuda.synchronize()

    wrap(wp, "init", "wp.init begins", "wp.init ends")
    wrap(losses, "load_vgg", "VGG: begins", "VGG loaded", sync=sync)
    wrap(job.StylizeJob, "start", "job resolved: begins", "job resolved (config, device, VGG)")
    wrap(job, "assemble_inputs", None, "inputs assembled")
    wrap(pipeline, "prepare", "targets: begin", "targets prepared", sync=sync)
    wrap(pipeline, "build_run", None, "run built", sync=sync)
    wrap(loop._Loop, "step", "first step begins", "first step ends", sync=sync)
    rc = cli.main(argv)
    mark("command returns")
    width = max(len(n) for n, _ in MARKS)
    prev = 0.0
    print(f"{'mark':<{width}}  since start (s)  since previous (s)")
    for name, t in MARKS:
        print(f"{name:<{width}}  {t:15.2f}  {t - prev:18.2f}")
        prev = t
    return rc


if __name__ == "__main__":
    import sys
    args = sys.argv[1:]
    raise SystemExit(main(["stylize", *(a for a in args if a != "--no-warmup")], warmup="--no-warmup" not in args))
