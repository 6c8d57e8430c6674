"""Where a stylize run's outputs spend their time: the renders of the orbit video and the views (what
`write_outputs` does in its own thread) alone, then beside the scene-file writers it runs in its pool, and the
writers alone. Each arrangement is timed ``--repeats`` times on one scene.

    python benchmarks/profile_outputs.py SCENE [--views 20] [--frames 96] [--repeats 3] [--downscale 1]

The views are the scene's own orbit (as `stylize --scene` without photos); the scene is rendered at SH degree 0.
docs/performance.md quotes it.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

from tlvg_warp.io import load_ply, save_ply
from tlvg_warp.io.scene_views import scene_views
from tlvg_warp.io.splat_formats import save_compressed_ply, save_spz
from tlvg_warp.renderer import render
from tlvg_warp.stylize.outputs import OUTPUT_WORKERS, orbit_path, to_u8, write_orbit, write_view


def render_all(g, cams, frames: int, per_frame_copy: bool = True) -> float:
    """Seconds to render the orbit's ``frames`` and every view, each copied to the host as write_outputs does
    (``per_frame_copy``), or kept on the device and copied once at the end."""
    t = time.perf_counter()
    with torch.no_grad():
        path = orbit_path(cams, frames)
        if per_frame_copy:
            _ = [to_u8(render(g, c, (1.0, 1.0, 1.0)).color) for c in path]
            _ = [render(g, c, (1.0, 1.0, 1.0)).color.clamp(0, 1).cpu() for c in cams]
        else:
            imgs = [render(g, c, (1.0, 1.0, 1.0)).color for c in path + list(cams)]
            _ = [i.cpu() for i in imgs]
    if g.means.is_cuda:
        torch.cuda.synchronize()
    return time.perf_counter() - t


def renders_with_view_jobs(g, cams, frames: int, folder: Path, renders_first: bool = False) -> tuple:
    """(seconds of the renders, seconds until every job is done): write_outputs's loop, the orbit's encoding and
    each view's files and flow scores (against a constant field) in a pool of OUTPUT_WORKERS beside the renders;
    ``renders_first``: every render done (and copied) before the first job starts."""
    t = time.perf_counter()
    with ThreadPoolExecutor(max_workers=OUTPUT_WORKERS) as pool, torch.no_grad():
        jobs, held = [], []  # held: the jobs kept back until every render is done (renders_first)

        def submit(*job):
            if renders_first:
                held.append(job)
            else:
                jobs.append(pool.submit(*job))

        fr = [to_u8(render(g, c, (1.0, 1.0, 1.0)).color) for c in orbit_path(cams, frames)]
        submit(write_orbit, folder, fr, 24)
        for i, c in enumerate(cams):
            sty = render(g, c, (1.0, 1.0, 1.0)).color.clamp(0, 1).cpu()
            fld = torch.stack([torch.ones(c.height, c.width), torch.zeros(c.height, c.width)], -1).numpy()
            submit(write_view, folder, i, sty, sty, sty, fld, i < 4)
        t_render = time.perf_counter() - t
        jobs += [pool.submit(*job) for job in held]
        for j in jobs:
            j.result()
    return t_render, time.perf_counter() - t


def writers(g_cpu, folder: Path) -> list:
    return [(save_ply, g_cpu, folder / "s.ply"), (save_compressed_ply, g_cpu, folder / "s.compressed.ply"),
            (save_spz, g_cpu, folder / "s.spz")]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--downscale", type=float, default=1.0)
    args = ap.parse_args()
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    g = load_ply(args.scene).with_sh_degree(0)
    views = scene_views(g, None, args.downscale)
    cams = list(views.cameras)[: args.views]
    g = g.to(device=dev)
    g_cpu = g.to(device="cpu", dtype=torch.float32)
    print(f"{args.scene}: {g.num:,} Gaussians, {len(cams)} views at {cams[0].width}x{cams[0].height}, "
          f"{args.frames} orbit frames, on {torch.cuda.get_device_name() if dev == 'cuda' else 'cpu'}")
    render_all(g, cams, 4)  # warm-up: kernels loaded, buffers allocated
    rows = {"renders alone, a copy per frame": [], "renders alone, one copy at the end": [],
            "writers alone (PLY, compressed PLY, SPZ in a pool)": [], "renders beside the writers": [],
            "renders beside the view and video jobs (write_outputs's loop)": [],
            "the same, until every job is done": [], "renders first, then the view and video jobs": [],
            "renders first: until every job is done": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeats):
            rows["renders alone, a copy per frame"].append(render_all(g, cams, args.frames))
            rows["renders alone, one copy at the end"].append(render_all(g, cams, args.frames, per_frame_copy=False))
            with ThreadPoolExecutor(max_workers=3) as pool:
                t = time.perf_counter()
                for f in [pool.submit(*w) for w in writers(g_cpu, Path(tmp))]:
                    f.result()
                rows["writers alone (PLY, compressed PLY, SPZ in a pool)"].append(time.perf_counter() - t)
            with ThreadPoolExecutor(max_workers=3) as pool:
                jobs = [pool.submit(*w) for w in writers(g_cpu, Path(tmp))]
                rows["renders beside the writers"].append(render_all(g, cams, args.frames))
                for f in jobs:
                    f.result()
            t_render, t_all = renders_with_view_jobs(g, cams, args.frames, Path(tmp))
            rows["renders beside the view and video jobs (write_outputs's loop)"].append(t_render)
            rows["the same, until every job is done"].append(t_all)
            t_render, t_all = renders_with_view_jobs(g, cams, args.frames, Path(tmp), renders_first=True)
            rows["renders first, then the view and video jobs"].append(t_render)
            rows["renders first: until every job is done"].append(t_all)
    print("| arrangement | seconds (each repeat) |\n| --- | --- |")
    for k, v in rows.items():
        print(f"| {k} | {', '.join(f'{x:.3f}' for x in v)} |")


if __name__ == "__main__":
    main()
