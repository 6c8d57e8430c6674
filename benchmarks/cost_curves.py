"""Cost curves: wall time and peak GPU memory of one stylize step and one fit step against Gaussians and pixels.

    python benchmarks/cost_curves.py --out OUT [--gaussians 100000,300000,1000000,3000000,10000000] \
        [--megapixels 0.1,0.5,1,2,4] [--base-gaussians 1000000] [--base-megapixels 0.76] [--steps 40] [--warm 20] \
        [--steps-of stylize,fit,raster] [--raster-peers tlvg_warp,gsplat] [--resume] [--profile N] [--set K=V]

Each point is a random scene (bench raster's: uniform in a cube, log-scale -4, SH degree 0) stylized by `stylize`
with configs/tlvg.yaml in this process, on orbit views of the point's size (4:3): a stylize step with the stylize
phase alone, a fit step with the pre-process alone (L1 + SSIM against the recoloured views, as `reconstruct` fits,
with density control; reconstruct's own step adds only its SfM-free schedule). Steps
WARM..WARM+STEPS are timed with a synchronize at both ends (the wall per step as the run sees it: host and GPU);
peak memory is torch.cuda.max_memory_allocated over the run (torch's allocations: VGG, the optimizer, the raster's
buffers on torch memory), including what earlier points of the process still hold at its start (``start_mib``).
``raster`` points time the rasterizer alone on the same scene and view size, ours and each of ``--raster-peers``
in this process (bench raster's timing: forward+backward, median of ``--raster-repeats`` after warm-up, one orbit
view; its peak memory). Writes cost_curves.csv and cost_curves.png under OUT after every point;
``--resume`` keeps the points an earlier call wrote there (a curve can take more than one call).
"""
from __future__ import annotations

import argparse
import csv
import gc
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT))  # after an installed package or the GPU scripts' source view

import tlvg_warp.stylize.pipeline as pipeline  # noqa: E402
from tlvg_warp import cli  # noqa: E402
from tlvg_warp.eval.bench_raster import Case, orbit_cameras, random_scene, run_bench  # noqa: E402
from tlvg_warp.io.ply import save_ply  # noqa: E402
from tlvg_warp.io.scene_views import ORBIT_SIZE  # noqa: E402

TIMER = {}


def _sync():
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _top_kernels(prof, steps: int, rows: int = 12) -> str:
    """The GPU kernels of the profiled steps, most time first: ms a step each, and the total."""
    kernels = [e for e in prof.key_averages() if e.device_type == torch.autograd.DeviceType.CUDA
               and not getattr(e, "is_user_annotation", False)]
    kernels.sort(key=lambda e: -e.self_device_time_total)
    total = sum(e.self_device_time_total for e in kernels) / 1e3 / steps
    lines = [f"  {e.self_device_time_total / 1e3 / steps:8.3f} ms  {e.count // steps:4d}x  {e.key[:110]}"
             for e in kernels[:rows]]
    return f"GPU kernel time a step ({steps} steps under the profiler): {total:.2f} ms\n" + "\n".join(lines)


def _timed_train(orig):
    def train(run, callback=None, **kw):
        def both(step, r):
            end = TIMER["warm"] + TIMER["steps"]
            if step == TIMER["warm"]:
                _sync()
                TIMER["t0"] = time.perf_counter()
            elif step == end:
                _sync()
                TIMER["ms"] = (time.perf_counter() - TIMER["t0"]) / TIMER["steps"] * 1e3
                if TIMER["profile"]:  # after the timed steps, so the profiler slows none of them
                    from torch.profiler import ProfilerActivity, profile
                    TIMER["prof"] = profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA])
                    TIMER["prof"].start()
            elif TIMER["profile"] and step == end + TIMER["profile"]:
                _sync()
                TIMER["prof"].stop()
                print(_top_kernels(TIMER["prof"], TIMER["profile"]), flush=True)
            if callback is not None:
                callback(step, r)
        return orig(run, callback=both, **kw)
    return train


def view_size(megapixels: float) -> tuple[float, int, int]:
    """The orbit views' downscale (they are ORBIT_SIZE / downscale) that gives ``megapixels``, and its width, height."""
    downscale = math.sqrt(ORBIT_SIZE[0] * ORBIT_SIZE[1] / (megapixels * 1e6))
    return downscale, round(ORBIT_SIZE[0] / downscale), round(ORBIT_SIZE[1] / downscale)


def raster_points(n: int, megapixels: float, args) -> list[dict]:
    """The rasterizer alone on the point's random scene at the point's view size: one row per peer (ms =
    forward+backward, peak MiB of that call; an error where a peer failed, e.g. out of memory)."""
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    _, w, h = view_size(megapixels)
    g = random_scene(n, -4.0, 0, device)
    rows = run_bench([Case(f"random {n}", g, orbit_cameras(g, 1, w, h))], device, args.raster_repeats,
                     peers=tuple(args.raster_peers.split(",")), log=lambda *_: None, profile_reps=1)
    del g
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return [{"step": f"raster {r['peer']}", "gaussians": n, "width": w, "height": h,
             "megapixels": round(w * h / 1e6, 3), "rc": 0 if "fwd_bwd_ms" in r else r.get("error", "failed"),
             "ms_per_step": round(r.get("fwd_bwd_ms", float("nan")), 3),
             "peak_mib": round(r.get("peak_mb", float("nan")), 1)} for r in rows]


def point(work: Path, n: int, megapixels: float, kind: str, args) -> dict:
    """One run of a random scene of ``n`` Gaussians on views of ``megapixels``, ``kind`` stylize or fit steps only:
    ms per step, peak MiB. Scenes and runs go to ``work``."""
    scene = work / f"scene_{n}.ply"
    if not scene.is_file():
        save_ply(random_scene(n, -4.0, 0, "cpu"), scene)
    downscale, w, h = view_size(megapixels)
    TIMER.update(warm=args.warm, steps=args.steps, ms=float("nan"), profile=getattr(args, "profile", 0))
    start = held = float("nan")
    if torch.cuda.is_available():  # what earlier points of this process left allocated counts in the peak: what
        gc.collect()  # garbage collection frees goes first, the rest is reported as start_mib
        torch.cuda.empty_cache()
        held = torch.cuda.memory_allocated() / 2 ** 20
        clear = getattr(torch._C, "_cuda_clearCublasWorkspaces", None)  # cuBLAS keeps a workspace per stream it
        if clear is not None:  # ran on (CUDA graphs capture on side streams): held_mib counts them, start_mib not
            clear()
            torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        start = torch.cuda.memory_allocated() / 2 ** 20
    argv = ["stylize", "--scene", str(scene), "--out", str(work / f"run_{kind}_{n}_{megapixels}"), "--overwrite",
            "--quiet",
            "--iterations", str(args.warm + args.steps + TIMER["profile"] + 1), "--downscale", f"{downscale:.6f}",
            "--set", "phases=" + ("[0,1,0]" if kind == "stylize" else "[1,0,0]"), "--set", "orbit_frames=0",
            "--set", "web_formats=false", *[a for kv in args.set for a in ("--set", kv)],
            *(["--vgg-weights", args.vgg_weights] if args.vgg_weights else []),
            *(["--device", args.device] if args.device else [])]
    rc = cli.main(argv)
    peak = torch.cuda.max_memory_allocated() / 2 ** 20 if torch.cuda.is_available() else float("nan")
    return {"step": kind, "gaussians": n, "width": w, "height": h, "megapixels": round(w * h / 1e6, 3), "rc": rc,
            "ms_per_step": round(TIMER["ms"], 3), "peak_mib": round(peak, 1), "start_mib": round(start, 1),
            "held_mib": round(held, 1), "settings": " ".join(args.set)}


def chart(rows: list[dict], path: Path, base_n: int, base_mp: float, settings: str = "") -> None:
    """Both curves of the rows measured with ``settings`` (a call's --set, space-joined; other rows are left out);
    a curve without a point is an empty panel."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # lazy: only the figure needs it
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4))
    FigureCanvasAgg(fig)
    rows = [r for r in rows if (r.get("settings") or "") == settings and r["rc"] in (0, "0")]
    for k, (key, label, keep) in enumerate((("gaussians", "Gaussians", lambda r: r["megapixels_asked"] == base_mp),
                                            ("megapixels", "megapixels", lambda r: r["gaussians"] == base_n))):
        ax = fig.add_subplot(1, 2, k + 1)
        if not any(keep(r) for r in rows):  # a call that measured the other curve only: log axes need data
            ax.set_axis_off()
            ax.set_title(f"against {label}: no points", fontsize=9)
            continue
        ax2 = ax.twinx()
        kinds = sorted({r["step"] for r in rows}, key=lambda k: (k.startswith("raster"), k))
        for kind, color in zip(kinds, ("tab:blue", "tab:green", "tab:orange", "tab:red", "tab:purple")):
            pts = sorted((r for r in rows if keep(r) and r["step"] == kind),
                         key=lambda r: r[key])
            name = kind.replace("raster tlvg_warp", "raster ours (fwd+bwd)").replace("raster gsplat",
                                                                                     "raster gsplat (fwd+bwd)")
            ax.plot([r[key] for r in pts], [r["ms_per_step"] for r in pts], "o-", color=color, label=f"{name} ms")
            ax2.plot([r[key] for r in pts], [r["peak_mib"] for r in pts], "s--", color=color, alpha=0.5)
        ax.legend(loc="upper left", fontsize=8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("ms per step")
        ax2.set_ylabel("peak MiB (dashed)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="cost_curves.csv and cost_curves.png, rewritten after each point")
    ap.add_argument("--work", default="/tmp/tlvg-cost", help="the random scenes and the runs (large)")
    ap.add_argument("--gaussians", default="100000,300000,1000000,3000000,10000000")
    ap.add_argument("--megapixels", default="0.1,0.5,1,2,4")
    ap.add_argument("--base-gaussians", type=int, default=1_000_000, help="the Gaussians of the pixel curve")
    ap.add_argument("--base-megapixels", type=float, default=0.76, help="the pixels of the Gaussian curve (1008x756)")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--warm", type=int, default=20)
    ap.add_argument("--vgg-weights", default=None)
    ap.add_argument("--device", default=None)
    ap.add_argument("--steps-of", default="stylize,fit,raster", help="which to time: stylize, fit, raster")
    ap.add_argument("--raster-peers", default="tlvg_warp,gsplat", help="the rasterizers of the raster points")
    ap.add_argument("--raster-repeats", type=int, default=10)
    ap.add_argument("--resume", action="store_true", help="keep the points already in OUT/cost_curves.csv")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="after the timed steps, N more under torch's profiler: the top GPU kernels a step")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a stylize setting for every point (repeatable; the CSV's settings column names them)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    pipeline.train = _timed_train(pipeline.train)
    todo = [(int(float(n)), args.base_megapixels) for n in args.gaussians.split(",") if n]
    todo += [(args.base_gaussians, float(m)) for m in args.megapixels.split(",")
             if m and (args.base_gaussians, float(m)) not in todo]
    rows = read(out / "cost_curves.csv") if args.resume else []
    done = {(r["step"].split()[0], r["gaussians"], r["megapixels_asked"], r.get("settings") or "") for r in rows}
    print("| step | Gaussians | view | ms per step | peak MiB |\n| --- | --- | --- | --- | --- |")
    for kind in args.steps_of.split(","):
        for n, mp in todo:
            if (kind, n, mp, " ".join(args.set)) in done:
                continue
            new = raster_points(n, mp, args) if kind == "raster" else [point(work, n, mp, kind, args)]
            for r in new:
                rows.append(r | {"megapixels_asked": mp})
                print(f"| {r['step']} | {n:,} | {r['width']}x{r['height']} | {r['ms_per_step']} | {r['peak_mib']} |"
                      + ("" if r["rc"] in (0, "0") else f" {r['rc']}"), flush=True)
            write(rows, out, args)  # after every point: a run cut short keeps what it measured


def read(path: Path) -> list[dict]:
    """The rows an earlier call wrote (numbers back as numbers); none where there is no file."""
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k in ("gaussians", "width", "height"):
            r[k] = int(r[k])
        for k in ("megapixels", "ms_per_step", "peak_mib", "megapixels_asked"):
            r[k] = float(r[k])
    return rows


def write(rows: list[dict], out: Path, args) -> None:
    with open(out / "cost_curves.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))  # rows of earlier calls
        # may lack a later column (start_mib): left empty there
        wr.writeheader()
        wr.writerows(rows)
    chart(rows, out / "cost_curves.png", args.base_gaussians, args.base_megapixels, " ".join(getattr(args, "set", [])))


if __name__ == "__main__":
    main()
