"""Is a training step host-bound or GPU-bound? (development aid)

python3 benchmarks/profile_step.py stylize|reconstruct -- <command arguments>
Runs the command in this process; its training loop gets a callback that (1) times steps WARM..WARM+TIMED
with a synchronize at both ends and nothing in between (the wall per step, as the run sees it), then (2) runs
torch.profiler (CPU + CUDA) over the next ACTIVE steps: GPU kernel time per step (the sum of kernel durations:
one stream), host launches per step, the top kernels and host operators. GPU time per step well below the wall
per step means the host bounds the step."""
import os
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile, schedule

import tlvg_warp.stylize.pipeline as pipeline
import tlvg_warp.train.reconstruct as reconstruct
from tlvg_warp.cli import main

WARM, TIMED, ACTIVE = int(os.environ.get("WARM", 300)), int(os.environ.get("TIMED", 600)), 40
cmd, args = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
state = {}
prof = profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA],
               schedule=schedule(wait=0, warmup=5, active=ACTIVE, repeat=1))


def callback_(step, run):
    if step == WARM:
        torch.cuda.synchronize()
        state["t0"] = time.perf_counter()
    elif step == WARM + TIMED:
        torch.cuda.synchronize()
        state["wall_ms"] = (time.perf_counter() - state["t0"]) / TIMED * 1e3
        prof.start()
        state["prof"] = True
    elif state.get("prof"):
        prof.step()
        if step == WARM + TIMED + 5 + ACTIVE + 1:
            torch.cuda.synchronize()
            prof.stop()
            state["prof"] = False


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
kernels = [e for e in avg if e.device_type == torch.autograd.DeviceType.CUDA]
gpu_us = sum(e.self_device_time_total for e in avg if not e.key.startswith("ProfilerStep"))
launch_names = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx", "cudaMemsetAsync",
                "cudaMemcpyAsync")
api = {e.key: e.count for e in avg if e.key in launch_names}
print(f"wall per step (no profiler, steps {WARM}..{WARM + TIMED}): {state.get('wall_ms', float('nan')):.2f} ms")
print(f"GPU kernel time per step (profiler, {ACTIVE} steps): {gpu_us / 1e3 / ACTIVE:.2f} ms; API calls per step: "
      + ", ".join(f"{k} {v / ACTIVE:.0f}" for k, v in api.items()))
print(avg.table(sort_by="self_device_time_total", row_limit=25, max_name_column_width=60))
print(avg.table(sort_by="self_cpu_time_total", row_limit=25, max_name_column_width=60))
