"""`python -m tlvg_warp bench [raster|sweep]`: measured tables, never timed unit tests."""
from __future__ import annotations

import os
from pathlib import Path

import torch

from ..errors import InputError
from ..fileio import write_json, write_text

DEFAULT_DATA = Path(os.environ.get("TLVG_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))


def _size(text: str) -> tuple[int, int]:
    """'WxH' as (width, height); argparse turns the ValueError into a one-line usage error (exit code 2)."""
    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
        raise ValueError(text)
    return int(w), int(h)


_size.__name__ = "size (WxH, e.g. 3840x2160)"  # argparse names the type in its error


def add_arguments(p):
    p.add_argument("what", nargs="?", default="sweep", choices=["raster", "sweep"],
                   help="sweep (the default): speed against quality of stylization; raster: the rasterizer against gsplat/gswarp")
    p.add_argument("--device", default=None, help="cuda or cpu (default: cuda when available)")
    p.add_argument("--out", default="bench_out", help="folder for the JSON/markdown/CSV/PNG results (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="small sizes for a CPU smoke run")
    p.add_argument("--repeats", type=int, default=20, help="timed repetitions, the median is reported (default: %(default)s)")
    p.add_argument("--sizes", default=None, help="raster: comma-separated Gaussian counts of the random scenes "
                   "(default 1000000,3000000; 'none' for none)")
    p.add_argument("--size", type=_size, default=None, metavar="WxH",
                   help="raster: image size of the random scenes and of orbit views, e.g. 3840x2160 for a 4K stress "
                        "case (default 1008x756)")
    p.add_argument("--log-scale", type=float, default=-4.0, help="raster: mean log-scale of the random Gaussians (default: %(default)s)")
    p.add_argument("--sh-degree", type=int, default=3, help="raster: SH degree of the random Gaussians (default: %(default)s)")
    p.add_argument("--peers", default="tlvg_warp,gsplat,gswarp", help="raster: which rasterizers to time (default: %(default)s)")
    p.add_argument("--garden", default=str(DEFAULT_DATA / "bench" / "test_garden.npz"), help="raster: garden points")
    p.add_argument("--scene", action="append", default=None,
                   help="sweep: PLY scene (default: the built-in demo). raster: PLY[:DATASET[:IMAGES]], a fitted scene "
                        "timed over every view of DATASET (IMAGES: its photo folder, e.g. images_4), or over orbit "
                        "views without one; repeatable")
    p.add_argument("--views", type=int, default=None, help="raster: at most this many views per --scene (default all)")
    p.add_argument("--depth", action="store_true", help="raster: our renders also blend the expected depth (default "
                   "off, as gsplat's RGB mode)")
    p.add_argument("--profile-reps", type=int, default=2, help="raster: renders per view in the GPU stage profile")
    p.add_argument("--data", default=None, help="sweep: dataset the scene was trained from")
    p.add_argument("--style", default=None, help="sweep: painting (default: the built-in one)")
    p.add_argument("--vgg-weights", default=None, metavar="PATH|hed|random",
                   help="sweep: VGG-16 weights, a path, 'hed' or 'random' (as stylize)")
    p.add_argument("--iterations", type=int, default=None, help="sweep: the base point's iterations (default 3000)")


def run(args) -> int:
    if args.what == "sweep":
        # lazy: CLI startup
        from ..eval import bench_sweep

        args.scene = args.scene[-1] if args.scene else None
        return bench_sweep.run(args)
    # lazy: CLI startup
    from ..eval import bench_raster as br

    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    sizes_arg = args.sizes or ("2000,20000" if args.quick else "1000000,3000000")
    sizes = [] if sizes_arg.strip().lower() in ("none", "0", "") else [int(s) for s in sizes_arg.split(",")]
    width, height = args.size or ((252, 189) if args.quick else (1008, 756))
    repeats = 3 if args.quick else args.repeats
    cam = br.bench_camera(width, height)
    cases = [br.Case(f"random {n:,} ls{args.log_scale:g}", br.random_scene(n, args.log_scale, args.sh_degree, device),
                     [cam]) for n in sizes]
    garden = Path(args.garden) if args.garden else None
    if garden is not None and garden.is_file():
        g, gcam = br.garden_scene(garden, device, args.sh_degree)
        cases.append(br.Case(f"garden {g.num:,} pts", g, [gcam]))
    elif garden is not None:
        print(f"note: {garden} not found; the garden case is skipped")
    for spec in args.scene or []:
        cases.append(br.scene_case(spec, device, args.views, orbit_size=(width, height)))
    peers = [p.strip() for p in args.peers.split(",") if p.strip()]
    unknown = set(peers) - set(br.PEERS)
    if unknown:
        raise InputError(f"unknown peers {sorted(unknown)}; choose from {sorted(br.PEERS)}")
    rows = br.run_bench(cases, device, repeats, peers, log=lambda r: print(r, flush=True), ours_depth=args.depth,
                        profile_reps=args.profile_reps)
    table, stages, kernels = br.format_table(rows), br.format_stages(rows), br.format_kernels(rows)
    out = Path(args.out)
    write_json(out / "bench_raster.json", {"device": str(device), "gpu": torch.cuda.get_device_name(device)
                                           if device.type == "cuda" else "cpu", "repeats": repeats,
                                           "ours_depth": args.depth, "rows": rows})
    write_text(out / "bench_raster.md", "\n\n".join(x for x in (stages, table) if x) + "\n")  # the table last
    if kernels:
        print(f"\ntop kernels per render (CUPTI):\n{kernels}")
    if stages:
        print(f"\nGPU kernel time per render by stage (ms; wall = the timed median):\n{stages}")
    print(f"\nrasterizer benchmark on {device} (median over views of each view's median of {repeats}; ratio = peer "
          f"time / ours; ours {'with' if args.depth else 'without'} expected depth):\n{table}")
    return 0
