"""`python -m tlvg_warp view RUN|FILE`: the scene in the browser (viser).

RUN (a stylization run folder): stylized.ply, a "Scene" dropdown to switch to the un-stylized scene, and the
training cameras of cameras.json as frustums. The run folder does not copy the un-stylized scene; it is found
where evaluate finds it: --original, the "scene" of the run's sources.json (of checkpoint.pt's sources for a run
written before sources.json), reconstruct/point_cloud.ply, or the built-in demo scene when the run's cameras are
the demo's. When none exists the viewer says so and shows the stylized scene alone.
FILE: any scene the project reads (INRIA .ply, .compressed.ply, .spz), with the cameras.json of an INRIA
layout when one lies beside it. Serves on 127.0.0.1 (--host / --port) until Ctrl-C."""
from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

from ..errors import InputError
from ..runs import run_sources
from ..viewer import (DEFAULT_HOST, DEFAULT_PORT, DEFAULT_UP, UP_AXES, SceneViewer, scene_center, scene_radius,
                      up_from_cameras)


def add_arguments(p):
    p.add_argument("path", metavar="RUN|FILE",
                   help="a stylization run folder, or a scene file (INRIA .ply, .compressed.ply, .spz)")
    p.add_argument("--host", default=DEFAULT_HOST,
                   help=f"address to bind (default {DEFAULT_HOST}: this machine only; 0.0.0.0 serves the network)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT,
                   help=f"port (default {DEFAULT_PORT}; a busy port moves to the next free one)")
    p.add_argument("--original", default=None, metavar="PLY",
                   help="with RUN: the un-stylized scene, when the run does not record where it is")
    p.add_argument("--cameras", default=None, metavar="JSON",
                   help="an INRIA cameras.json to draw as frustums (default: the run's, or one beside FILE)")
    p.add_argument("--up", default=None, choices=sorted(UP_AXES),
                   help="world up axis (default: from the cameras; -y without cameras, as COLMAP scenes)")


# --- what a run folder holds ----------------------------------------------------------------------------------
def find_original(run: Path, cams: list):
    """(Gaussians or None, where from / why not)."""
    # lazy: CLI startup
    from ..eval.engine import demo_original
    from ..io.ply import load_ply
    src = run_sources(run)
    for cand in (src.get("scene"), run / "reconstruct" / "point_cloud.ply"):
        if cand and Path(cand).is_file():
            return load_ply(Path(cand)), str(cand)
    if cams and not src.get("data") and not src.get("scene"):
        g = demo_original(run, cams)  # at the density the run started from (its config.yaml downscale)
        if g is not None:
            return g, f"the built-in demo scene ({g.num:,} Gaussians)"
    if src.get("scene"):
        return None, f"the un-stylized scene {src['scene']} no longer exists; pass --original PLY"
    return None, ("this run does not record its un-stylized scene (no sources.json or checkpoint.pt, no "
                  "reconstruct/point_cloud.ply); pass --original PLY to compare")


def cameras_beside(scene: Path):
    for d in (scene.parent, scene.parent.parent, scene.parent.parent.parent):
        if (d / "cameras.json").is_file():
            return d / "cameras.json"
    return None


def load_view(path, original=None, cameras=None) -> dict:
    """What the viewer shows: {"scenes": {name: Gaussians}, "cameras": [Camera], "notes": [str], "title"}."""
    # lazy: CLI startup
    from ..io.datasets import read_inria_cameras
    from ..io.ply import load_ply

    p = Path(path)
    if not p.exists():
        raise InputError("no such run folder or scene file", p)
    notes, cams = [], []
    if p.is_dir():
        ply = p / "stylized.ply"
        if not ply.is_file():
            raise InputError("missing stylized.ply (not a stylization run folder?); pass a scene file instead", p)
        cj = Path(cameras) if cameras else p / "cameras.json"
        if cj.is_file() or cameras:
            _, cams = read_inria_cameras(cj)
        else:
            notes.append("no cameras.json in the run folder: no training cameras to show")
        scenes = {"stylized": load_ply(ply)}
        if original is not None:
            g0, where = load_ply(Path(original)), str(original)
        else:
            g0, where = find_original(p, cams)
        if g0 is not None:
            scenes["un-stylized"] = g0
            notes.append(f"un-stylized: {where}")
        else:
            notes.append(where)
        title = p.resolve().name
    else:
        scenes = {p.name: load_ply(p)}
        cj = Path(cameras) if cameras else cameras_beside(p)
        if cj is not None:
            _, cams = read_inria_cameras(cj)
            notes.append(f"cameras: {cj}")
        title = p.name
    return {"scenes": scenes, "cameras": cams, "notes": notes, "title": title}


def open_viewer(content: dict, host: str, port: int, up=None):
    """A running SceneViewer showing ``content`` (load_view's dict)."""
    v = SceneViewer(host, port, title=f"tlvg_warp: {content['title']}")
    first = next(iter(content["scenes"].values()))
    center = scene_center(first)
    for name, g in content["scenes"].items():
        v.set_scene(name, g)
    cams = content["cameras"]
    if cams:
        v.add_cameras(cams, center)
    for n in content["notes"]:
        v.note(n)
    up_vec = UP_AXES[up] if up else (up_from_cameras(cams) if cams else UP_AXES[DEFAULT_UP])
    v.frame(center, up_vec, cams, scene_radius(first, center))
    return v


def serve_forever(v, quiet=False, lines=()) -> int:
    """Print ``lines``, then wait for Ctrl-C and stop the server. The printing is inside the wait's ``try``: a
    Ctrl-C that arrives while the address is being printed (a caller that reads the address and signals at once)
    must still stop viser, whose threads would otherwise keep the process alive."""
    if threading.current_thread() is threading.main_thread():
        # "press Ctrl-C" must hold whatever the parent left: a SIGINT blocked or ignored in the launching process
        # is inherited, and would leave the server running
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        for line in lines:
            print(line, flush=True)
        if not quiet:
            print("press Ctrl-C to stop", flush=True)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        v.stop()
    return 0


def run(args) -> int:
    content = load_view(args.path, args.original, args.cameras)
    v = open_viewer(content, args.host, args.port, args.up)
    shown = ", ".join(f"{n} ({g.num:,} Gaussians)" for n, g in content["scenes"].items())
    return serve_forever(v, lines=[f"viewer: {v.address}  ({shown}; {len(content['cameras'])} training cameras)"]
                         + [f"  {n}" for n in content["notes"]])
