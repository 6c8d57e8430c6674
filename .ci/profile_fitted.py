"""GPU profile of one render (+ backward) on a fitted scene, ours against gsplat (development aid, issue 15).

python3 .ci/profile_fitted.py SCENE.ply DATASET [IMAGES]
Prints: the fwd / fwd+bwd medians over every view for both, the per-pixel list lengths (Gaussians binned per
tile, Gaussians walked per pixel until saturation), the intersections per render, and the top CUDA kernels of
each rasterizer (CUPTI via torch.profiler) over every view. `bench raster --scene` reports the same in its tables."""
import statistics
import sys

import torch

from tlvg_warp.eval import bench_raster as br

ply, data = sys.argv[1], sys.argv[2]
images = sys.argv[3] if len(sys.argv) > 3 else "images_4"
dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
case = br.scene_case(f"{ply}:{data}:{images}", dev)
g, cams = case.g, case.cams
print(f"scene {ply}: {g.num:,} Gaussians, SH {g.sh_degree}; {len(cams)} views {cams[0].width}x{cams[0].height}")
ls = br.scene_lists(g, cams)
print(f"intersections per render: mean {ls['intersections']:,.0f}, max {ls['intersections_max']:,}")
print(f"Gaussians binned per tile: mean {ls['tile_mean']:.0f}, max {ls['tile_max']}; "
      f"walked per pixel: mean {ls['px_mean']:.0f}, max {ls['px_max']}")
for peer in ("tlvg_warp", "gsplat"):
    try:
        make = br.PEER_VIEWS[peer](g)
        views = [make(cam) for cam in cams]
        fwds = [br.time_fn(v[0], dev, 10) for v in views]
        fbs = [br.time_fn(v[1], dev, 10) for v in views]
        print(f"{peer}: fwd median {statistics.median(fwds):.3f} ms, fwd+bwd {statistics.median(fbs):.3f} ms "
              f"(over {len(cams)} views, median of 10 each)")
        for name, k in (("fwd", 0), ("fwd+bwd", 1)):
            st = br.gpu_stages([v[k] for v in views], dev)
            if st:
                print(f"  {peer} {name}: GPU kernels+copies {st['gpu total']:.3f} ms/render; by stage: "
                      + ", ".join(f"{s} {st[s]:.3f}" for s in br.STAGE_NAMES))
                for ms, count, key in st["kernels"][:12]:
                    print(f"    {ms:7.3f} ms  x{count:<4g} {key[:90]}")
    except Exception as e:  # noqa: BLE001 - a development aid: report and go on
        print(f"{peer}: failed: {type(e).__name__}: {e}")
