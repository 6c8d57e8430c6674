"""Host microseconds per call of the operations a render is made of, on CUDA (perf_counter over many calls, the
GPU drained between blocks): what each host step costs, to choose what to remove. `python3 .ci/host_costs.py`"""
import statistics, time
import torch
from tlvg_warp import ops
from tlvg_warp.eval import bench_raster as br
from tlvg_warp.renderer import check_inputs, _zero_pair
from tlvg_warp.types import Gaussians

dev = torch.device("cuda", 0)  # a tensor's device (always indexed)
N = 159035


def cost(name, fn, reps=2000):
    for _ in range(20):
        fn()
    torch.cuda.synchronize()
    ts = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(reps // 5):
            fn()
        ts.append((time.perf_counter() - t0) / (reps // 5) * 1e6)
        torch.cuda.synchronize()
    print(f"{name:55s} {statistics.median(ts):8.2f} us")


g = br.random_scene(N, -4, 3, dev)
gp = Gaussians(*br._leaf_params(g))
cam = br.bench_camera(1280, 720)
K = ops.kernels_for(torch.float32)
x = torch.zeros(N, 3, device=dev)
cost("torch.empty(N, 3)", lambda: torch.empty(N, 3, device=dev))
cost("torch.zeros(5N)", lambda: torch.zeros(5 * N, device=dev))
cost("x.view(N, 3) (view op)", lambda: x.view(N, 3))
cost("torch.cuda.current_device()", torch.cuda.current_device)
cost("torch._C._cuda_getCurrentRawStream(0)", lambda: torch._C._cuda_getCurrentRawStream(0))
w = ops.warp_on(dev)
def enter_exit(w=w):
    with w:
        pass
cost("warp_on(cuda:0) enter+exit", enter_exit)
cost("ct(x, vec3)", lambda: ops.ct(x, K.vec3))
cost("input_ct(gp.means, vec3) (cached)", lambda: ops.input_ct(gp.means, K.vec3))
cost("check_inputs", lambda: check_inputs(gp, cam, None))
cost("probe", lambda: _zero_pair(gp.dtype, gp.device).expand(gp.num, 2).detach().requires_grad_(True))
cost("camera_values", lambda: ops.camera_values(cam))
vals = ops.camera_values(cam)
cost("camera_args (kept)", lambda: ops.camera_args(cam, K, vals))
colors = torch.empty(N, 3, device=dev)
center = ops.camera_center(K, vals)
wdev = ops.wdevice(dev)
def launch_sh():
    ops.fast_launch(K.sh_color, 3 * N, [ops.input_ct(gp.means, K.vec3), ops.input_ct(gp.sh, None), center, 16,
                                        ops.ct(colors.view(-1))], wdev)
with w:
    cost("fast_launch sh_color (5 args, inside warp_on)", launch_sh)
    rt = ops._runtime()
    site = [s for k, s in ops._sites.items() if k[0] is K.sh_color][0]
    L = site.launch
    sh_args = [ops.input_ct(gp.means, K.vec3), ops.input_ct(gp.sh, None), center, 16, ops.ct(colors.view(-1))]
    cost("  of which _set_args (5 args)", lambda: ops._set_args(site, sh_args, True))  # slots now point at sh_args
    def raw():
        rt.core.wp_cuda_launch_kernel(wdev.context, site.hook, L.bounds.size, L.max_blocks, L.block_dim,
                                      int(L.grid_stride), L.cluster_dim, site.smem, L.params_addr,
                                      wdev.stream.cuda_stream, None)
    cost("  of which wp_cuda_launch_kernel alone", raw)
    cost("  of which wdev.context + stream.cuda_stream", lambda: (wdev.context, wdev.stream.cuda_stream))
    keys = torch.rand(2 * N, device=dev)
    vals_ = torch.zeros(2 * N, dtype=torch.int32, device=dev)
    cost("sort_pairs_at float32 N (depth sort)", lambda: ops.sort_pairs_at(torch.float32, dev, keys.data_ptr(),
                                                                          vals_.data_ptr(), N), reps=500)
    ik = torch.randint(0, 3600, (2 * 600000,), dtype=torch.int32, device=dev)
    cost("sort_pairs_at int32 600k, 12 bits (tile sort)", lambda: ops.sort_pairs_at(
        torch.int32, dev, ik.data_ptr(), vals_.data_ptr(), 150000, 0, 12), reps=500)
    src = torch.ones(N, dtype=torch.int32, device=dev)
    dst = torch.empty(N, dtype=torch.int32, device=dev)
    cost("inclusive_scan_at N", lambda: ops.inclusive_scan_at(src.data_ptr(), dst.data_ptr(), N, dev), reps=500)
    cost("dst[-1].item() (GPU idle)", lambda: dst[N - 1].item())
    cost("torch.cumsum(src) int64 + item", lambda: torch.cumsum(src, 0, dtype=torch.int64)[-1].item(), reps=500)


class Mark(torch.autograd.Function):
    t = []

    @staticmethod
    def forward(ctx, a):
        return a * 1

    @staticmethod
    def backward(ctx, g):
        Mark.t.append(time.perf_counter())
        return g


leaf = torch.zeros(N, 3, device=dev, requires_grad=True)
up = torch.rand(N, 3, device=dev)
cost("Function.apply, trivial forward (one mul)", lambda: Mark.apply(leaf), reps=1000)
cost("mul alone", lambda: leaf.detach() * 1, reps=1000)
for mt in (True, False):
    gaps, totals = [], []
    with torch.autograd.set_multithreading_enabled(mt):
        for _ in range(300):
            loss = (Mark.apply(leaf) * up).sum()
            torch.cuda.synchronize()
            Mark.t.clear()
            t0 = time.perf_counter()
            loss.backward()
            t1 = time.perf_counter()
            gaps.append((Mark.t[0] - t0) * 1e6); totals.append((t1 - t0) * 1e6)
            torch.cuda.synchronize()
    print(f"{'backward(): call -> Function.backward entry, mt=' + str(mt):55s} {statistics.median(gaps):8.2f} us"
          f" (whole backward() {statistics.median(totals):.1f})")
