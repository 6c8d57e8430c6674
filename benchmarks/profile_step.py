"""Is a training step host-bound or GPU-bound? (development aid)

python3 benchmarks/profile_step.py stylize|reconstruct -- <command arguments>
Runs the command in this process; its training loop gets a callback that (1) times steps WARM..WARM+TIMED
with a synchronize at both ends and nothing in between (the wall per step, as the run sees it), then (2) runs
torch.profiler (CPU + CUDA) over the next ACTIVE steps: GPU kernel time per step (the sum of kernel durations:
one stream), host launches per step, the top kernels and host operators. GPU time per step well below the wall
per step means the host bounds the step. Then (3) cProfile over the next CPROF steps: the Python functions that
take the host's time (self time and cumulative), to see which ones a host-bound step should lose. During (1) the
host's own time per stage of the loop is taken too (perf_counter at the loop's timer marks, no sync): where a
stage's host time exceeds what its work should cost, the host waited there for the GPU (a read back)."""
import cProfile
import io
import os
import pstats
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile, schedule

import tlvg_warp.stylize.pipeline as pipeline
import tlvg_warp.train.reconstruct as reconstruct
from tlvg_warp.cli import main

WARM, TIMED, ACTIVE = int(os.environ.get("WARM", 300)), int(os.environ.get("TIMED", 600)), 40
CPROF = int(os.environ.get("CPROF", 200))
TIMELINE = int(os.environ.get("TIMELINE", 0))  # > 0: also ms a step over each stretch of this many steps
cprof = cProfile.Profile()
cmd, args = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
state = {}
prof = profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA],
               schedule=schedule(wait=0, warmup=5, active=ACTIVE, repeat=1))


def host_split(timer) -> dict:
    """Patch ``timer`` (the run's StageTimer) to also sum the host's perf_counter time per stage, every step."""
    host, last = {}, [0.0]  # stage -> seconds; the time of the last mark
    begin, mark = timer.begin, timer.mark

    def begin_(step):
        last[0] = time.perf_counter()
        begin(step)

    def mark_(stage):
        now = time.perf_counter()
        host[stage] = host.get(stage, 0.0) + now - last[0]
        last[0] = now
        mark(stage)
    timer.begin, timer.mark = begin_, mark_
    return host


def callback_(step, run):
    state.setdefault("stamps", []).append((step, time.perf_counter()))  # every step: the run's timeline
    if step == WARM:
        torch.cuda.synchronize()
        state["host"] = host_split(run.timer)
        state["t0"] = time.perf_counter()
    elif step == WARM + TIMED:
        torch.cuda.synchronize()
        state["wall_ms"] = (time.perf_counter() - state["t0"]) / TIMED * 1e3
        del run.timer.begin, run.timer.mark  # the class's own again
        prof.start()
        state["prof"] = True
    elif state.get("prof"):
        prof.step()
        if step == WARM + TIMED + 5 + ACTIVE + 1:
            torch.cuda.synchronize()
            prof.stop()
            state["prof"] = False
            state["cp_end"] = step + CPROF
            cprof.enable()
    elif state.get("cp_end") == step:
        cprof.disable()
        state["cp_steps"] = CPROF


def wrap(mod):
    orig = mod.train

    def train(run, callback=None, **kw):
        def both(step, r):
            callback_(step, r)
            if callback is not None:
                callback(step, r)
        return orig(run, callback=both, **kw)
    mod.train = train


wrap(pipeline)
wrap(reconstruct)
rc = main([cmd, *args])
print(f"{cmd} exit {rc}")
avg = prof.key_averages()
# GPU-side events, less the user annotations (ProfilerStep#'s GPU range spans whole steps, idle time included)
kernels = [e for e in avg if e.device_type == torch.autograd.DeviceType.CUDA and not getattr(e, "is_user_annotation", False)]
gpu_us = sum(e.self_device_time_total for e in kernels)  # the kernels' own time (a graph's kernels among them)
launch_names = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx", "cudaMemsetAsync",
                "cudaMemcpyAsync")
api = {e.key: e.count for e in avg if e.key in launch_names}
print(f"wall per step (no profiler, steps {WARM}..{WARM + TIMED}): {state.get('wall_ms', float('nan')):.2f} ms")
stamps = state.get("stamps", [])
if TIMELINE and len(stamps) > 1:  # ms a step per stretch of TIMELINE steps (host clock, no sync: the host runs a
    # few steps ahead at most), and the slowest single steps (the profiled and cProfiled steps after WARM + TIMED are
    # slow by their profilers)
    step_of = {s: t for s, t in stamps}
    rows = []
    for a in range(stamps[0][0], stamps[-1][0] - TIMELINE + 1, TIMELINE):
        if a in step_of and a + TIMELINE in step_of:
            rows.append(f"{a}-{a + TIMELINE} {(step_of[a + TIMELINE] - step_of[a]) / TIMELINE * 1e3:.2f}")
    print("timeline, ms a step per stretch: " + ", ".join(rows))
    d = sorted(((t1 - t0) * 1e3, s1) for (s0, t0), (s1, t1) in zip(stamps, stamps[1:]))[::-1][:12]
    print("slowest steps (ms, step): " + ", ".join(f"{ms:.1f} @{s}" for ms, s in d))
print("host time per step by stage (no profiler, same steps): " + ", ".join(
    f"{k} {v / TIMED * 1e3:.2f} ms" for k, v in state.get("host", {}).items()))
print(f"GPU kernel time per step (profiler, {ACTIVE} steps): {gpu_us / 1e3 / ACTIVE:.2f} ms; API calls per step: "
      + ", ".join(f"{k} {v / ACTIVE:.0f}" for k, v in api.items()))
print(avg.table(sort_by="self_device_time_total", row_limit=25, max_name_column_width=60))
print(avg.table(sort_by="self_cpu_time_total", row_limit=25, max_name_column_width=60))
if state.get("cp_steps"):
    for key in ("tottime", "cumulative"):
        buf = io.StringIO()
        st = pstats.Stats(cprof, stream=buf)
        st.sort_stats(key).print_stats(35)
        print(f"cProfile over {CPROF} steps, by {key} (seconds over the steps; divide by {CPROF} for a step):")
        print("\n".join(buf.getvalue().splitlines()[4:]))
