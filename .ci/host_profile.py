"""Where the host spends one synchronized render + backward on the GPU (development aid): cProfile over the
bench's step, top functions by own time. Time inside a sync (Tensor.__int__, synchronize) is the host waiting
for the GPU; the rest is Python and launch overhead that the GPU may wait for."""
import cProfile
import pstats
import sys

import torch

from tlvg_warp.eval.bench_raster import PEERS, bench_camera, random_scene

n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
which = sys.argv[2] if len(sys.argv) > 2 else "tlvg_warp"
g = random_scene(n, -4.0, 3, torch.device("cuda"))
_, step, _ = PEERS[which](g, bench_camera(1008, 756))
for _ in range(5):
    step()
torch.cuda.synchronize()
pr = cProfile.Profile()
pr.enable()
for _ in range(50):
    step()
    torch.cuda.synchronize()
pr.disable()
print(f"== {which} N={n:,}: 50 synchronized steps")
st = pstats.Stats(pr)
st.sort_stats("tottime").print_stats(22)
st.sort_stats("cumtime").print_stats(30)
