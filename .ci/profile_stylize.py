"""Where a stylization step spends its time on the GPU (development aid, issue 15).

python3 .ci/profile_stylize.py OUT_DIR -- <stylize arguments>
Runs `python -m tlvg_warp stylize <arguments>` in this process under torch.profiler (CPU + CUDA) and prints the
top operators by GPU time and by host time. The profiler slows the host; read the split, not the total."""
import sys

import torch
from torch.profiler import ProfilerActivity, profile

from tlvg_warp.cli import main

out, args = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
    rc = main(["stylize", *args, "--out", out, "--overwrite", "--quiet"])
torch.cuda.synchronize()
print("stylize exit", rc)
avg = prof.key_averages()
gpu_us = sum(e.self_device_time_total for e in avg)
cpu_us = sum(e.self_cpu_time_total for e in avg)
launches = sum(e.count for e in avg if e.key in ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx"))
print(f"totals: GPU kernels {gpu_us / 1e3:.1f} ms, host (self CPU) {cpu_us / 1e3:.1f} ms, kernel launches {launches}")
print(avg.table(sort_by="device_time_total", row_limit=30, max_name_column_width=70))
print(avg.table(sort_by="self_cpu_time_total", row_limit=20, max_name_column_width=70))
