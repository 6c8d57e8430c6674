"""`python -m tlvg_warp stability [--quick]`: drive the pipeline into the places where stylization breaks."""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..fileio import write_json, write_text


def add_arguments(p):
    p.add_argument("--quick", action="store_true",
                   help="the fast subset on CPU: 32x24 views, ~4.7k Gaussians, 6 iterations, random VGG")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--out", default="stability_out", help="folder for stability.json and stability.md")
    p.add_argument("--only", default=None, help="comma-separated scenario names (default: all)")
    p.add_argument("--vgg-weights", default=None, metavar="PATH|hed|random",
                   help="VGG-16 weights: a path, 'hed' or 'random' (default: random with --quick, else the usual "
                        "lookup, as stylize)")
    p.add_argument("--long-iters", type=int, default=10000, help="iterations of the long_run scenario (GPU only)")


def run(args) -> int:
    # lazy: CLI startup
    from ..eval import stability as S

    names = [s.name for s in S.scenarios(6, args.long_iters)]
    only = [s.strip() for s in args.only.split(",") if s.strip()] if args.only else None
    if only and set(only) - set(names):
        raise InputError(f"unknown scenarios {sorted(set(only) - set(names))}; choose from {', '.join(names)}")
    if args.long_iters < 1:
        raise InputError(f"--long-iters must be >= 1, got {args.long_iters}")
    vgg = args.vgg_weights or ("random" if args.quick else None)
    res = S.run_suite(args.quick, args.device, only, vgg, log=lambda r: print(r, flush=True),
                      long_iters=args.long_iters)
    table = S.format_table(res["rows"])
    out = Path(args.out)
    write_json(out / "stability.json", res)
    write_text(out / "stability.md", table + "\n")
    print(f"\nstability suite on {res['device']} ({'quick' if args.quick else 'full'}; "
          f"{res['views']} views {res['size'][0]}x{res['size'][1]}, {res['iterations']} iterations; "
          f"VGG {res['vgg']}):\n{table}\nwrote {out / 'stability.json'}")
    failed = [r["scenario"] for r in res["rows"] if r.get("finished") is False or (r.get("nan") or 0) > 0]
    if failed:
        print(f"not finished or NaN: {', '.join(failed)}")
    return 1 if failed else 0
