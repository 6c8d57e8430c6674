"""GPU profile of one render (+ backward) on a fitted scene, ours against gsplat (development aid, issue 15).

python3 .ci/profile_fitted.py SCENE.ply DATASET [IMAGES]
Prints: the fwd / fwd+bwd medians over every view for both, the per-pixel list lengths (Gaussians binned per
tile, Gaussians walked per pixel until saturation), the intersections per render, and the top CUDA kernels of
each rasterizer (CUPTI via torch.profiler) on view 0."""
import statistics
import sys

import torch
from torch.profiler import ProfilerActivity, profile

from tlvg_warp import load_dataset, ops
from tlvg_warp.eval.bench_raster import PEERS, _sync, time_fn
from tlvg_warp.io.ply import load_ply

ply, data = sys.argv[1], sys.argv[2]
images = sys.argv[3] if len(sys.argv) > 3 else "images_4"
dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
g = load_ply(ply).to(device=dev)
ds = load_dataset(data, images=images)
cams = list(ds.cameras)
print(f"scene {ply}: {g.num:,} Gaussians, SH {g.sh_degree}; {len(cams)} views {cams[0].width}x{cams[0].height}")

# per-pixel list lengths of ours: capture the binning state of one forward per view
seen = {}
orig_blend = ops.blend


def spy(K, proj, pouts, counts, total, geometry, cam, settings):
    out = orig_blend(K, proj, pouts, counts, total, geometry, cam, settings)
    seen["total"] = total
    seen["state"] = out[4]
    return out


ops.blend = spy
lens, walked, totals = [], [], []
from tlvg_warp import render
for cam in cams:
    with torch.no_grad():
        render(g, cam)
    st = seen["state"]
    ranges, last = st["args"][0]._ref, st["saved"][2]._ref  # [tiles, 2], [H, W]
    totals.append(seen["total"])
    per_tile = (ranges[:, 1] - ranges[:, 0]).float()
    H, W = last.shape
    ys, xs = torch.meshgrid(torch.arange(H, device=dev), torch.arange(W, device=dev), indexing="ij")
    tiles_x = (W + 15) // 16
    start = ranges[(ys // 16) * tiles_x + xs // 16, 0]
    per_px = (last - start).float()
    lens.append((per_tile.mean().item(), per_tile.max().item(), per_px.mean().item(), per_px.max().item()))
ops.blend = orig_blend
print(f"intersections per render: mean {statistics.mean(totals):,.0f}, max {max(totals):,}")
if lens:
    print(f"Gaussians binned per tile: mean {statistics.mean(l[0] for l in lens):.0f}, max {max(l[1] for l in lens):.0f}; "
          f"walked per pixel: mean {statistics.mean(l[2] for l in lens):.0f}, max {max(l[3] for l in lens):.0f}")

for peer in ("tlvg_warp", "gsplat"):
    try:
        fwds, fbs = [], []
        for cam in cams:
            fwd, fb, _ = PEERS[peer](g, cam)
            fwds.append(time_fn(fwd, dev, 10))
            fbs.append(time_fn(fb, dev, 10))
        print(f"{peer}: fwd median {statistics.median(fwds):.3f} ms, fwd+bwd {statistics.median(fbs):.3f} ms "
              f"(over {len(cams)} views, median of 10 each)")
        fwd, fb, _ = PEERS[peer](g, cams[0])
        for name, fn in (("fwd", fwd), ("fwd+bwd", fb)):
            for _ in range(3):
                fn()
            _sync(dev)
            with profile(activities=[ProfilerActivity.CUDA]) as prof:
                for _ in range(10):
                    fn()
                _sync(dev)
            evs = [e for e in prof.key_averages() if e.device_time_total > 0]
            tot = sum(e.device_time_total for e in evs) / 10 / 1e3
            print(f"  {peer} {name}: GPU kernels+copies {tot:.3f} ms/it")
            for e in sorted(evs, key=lambda e: -e.device_time_total)[:12]:
                print(f"    {e.device_time_total / 10 / 1e3:7.3f} ms  x{e.count // 10:<3d} {e.key[:90]}")
    except Exception as e:  # noqa: BLE001 - a development aid: report and go on
        print(f"{peer}: failed: {type(e).__name__}: {e}")
