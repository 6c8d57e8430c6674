"""`python -m tlvg_warp bench [raster|sweep]`: measured tables, never timed unit tests."""
from __future__ import annotations

import os
from pathlib import Path

from ..errors import InputError
from ..fileio import write_json, write_text

DEFAULT_DATA = Path(os.environ.get("TLVG_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))


def add_arguments(p):
    p.add_argument("what", nargs="?", default="sweep", choices=["raster", "sweep"],
                   help="sweep (the default): speed against quality of stylization; raster: the rasterizer against gsplat/gswarp")
    p.add_argument("--device", default=None, help="cuda or cpu (default: cuda when available)")
    p.add_argument("--out", default="bench_out", help="folder for the JSON/markdown/CSV/PNG results (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="small sizes for a CPU smoke run")
    p.add_argument("--repeats", type=int, default=20, help="timed repetitions, the median is reported (default: %(default)s)")
    p.add_argument("--sizes", default=None, help="raster: comma-separated Gaussian counts (default 1000000,3000000)")
    p.add_argument("--log-scale", type=float, default=-4.0, help="raster: mean log-scale of the random Gaussians (default: %(default)s)")
    p.add_argument("--sh-degree", type=int, default=3, help="raster: SH degree of the random Gaussians (default: %(default)s)")
    p.add_argument("--peers", default="tlvg_warp,gsplat,gswarp", help="raster: which rasterizers to time (default: %(default)s)")
    p.add_argument("--garden", default=str(DEFAULT_DATA / "bench" / "test_garden.npz"), help="raster: garden points")
    p.add_argument("--scene", default=None, help="sweep: PLY scene (default: the built-in demo)")
    p.add_argument("--data", default=None, help="sweep: dataset the scene was trained from")
    p.add_argument("--style", default=None, help="sweep: painting (default: the built-in one)")
    p.add_argument("--vgg-weights", default=None, help="sweep: VGG-16 weights path or 'random'")
    p.add_argument("--iterations", type=int, default=None, help="sweep: the base point's iterations (default 3000)")


def run(args) -> int:
    if args.what == "sweep":
        from ..eval import bench_sweep

        return bench_sweep.run(args)
    import torch

    from ..eval import bench_raster as br

    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    sizes = [int(s) for s in (args.sizes or ("2000,20000" if args.quick else "1000000,3000000")).split(",")]
    width, height = (252, 189) if args.quick else (1008, 756)
    repeats = 3 if args.quick else args.repeats
    cam = br.bench_camera(width, height)
    cases = [(f"random {n:,} ls{args.log_scale:g}", (br.random_scene(n, args.log_scale, args.sh_degree, device), cam))
             for n in sizes]
    garden = Path(args.garden)
    if garden.is_file():
        g, gcam = br.garden_scene(garden, device, args.sh_degree)
        cases.append((f"garden {g.num:,} pts", (g, gcam)))
    elif args.garden:
        print(f"note: {garden} not found; the garden case is skipped")
    peers = [p.strip() for p in args.peers.split(",") if p.strip()]
    unknown = set(peers) - set(br.PEERS)
    if unknown:
        raise InputError(f"unknown peers {sorted(unknown)}; choose from {sorted(br.PEERS)}")
    rows = br.run_bench(cases, device, repeats, peers, log=lambda r: print(r, flush=True))
    table = br.format_table(rows)
    out = Path(args.out)
    write_json(out / "bench_raster.json", {"device": str(device), "gpu": torch.cuda.get_device_name(device)
                                           if device.type == "cuda" else "cpu", "repeats": repeats, "rows": rows})
    write_text(out / "bench_raster.md", table + "\n")
    print(f"\nrasterizer benchmark on {device} ({'median of %d' % repeats}):\n{table}")
    return 0
