"""Views for a scene that comes without photos (``stylize --scene FILE`` and no ``--data``).

Cameras come from an INRIA ``cameras.json`` when one is given, else from an orbit generated around the scene;
the un-stylized scene rendered into them stands in for the photos (what the content loss and the recolored
pre-process fit then preserve is the scene as it is)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..renderer import render
from ..types import Camera, Gaussians
from .datasets import read_inria_cameras

ORBIT_VIEWS = 24  # one view every 15 degrees
ORBIT_SIZE = (256, 192)  # width, height before config downscale
ORBIT_FOV_DEG = 50.0  # horizontal field of view
ORBIT_ELEVATION_DEG = 20.0  # cameras look slightly down onto the scene
CORE_QUANTILE = 0.9  # the scene's radius: where 90% of the Gaussians lie (stray floaters far out are ignored)
MARGIN = 1.15  # the core sphere fills the view to within this margin
WORLD_UP = (0.0, -1.0, 0.0)  # captures in COLMAP / INRIA / SuperSplat PLY axes (OpenCV: y down) are -y up


@dataclass
class SceneViews:
    cameras: list  # [Camera]
    names: list  # [str]
    source: str  # "orbit" or the cameras.json path


def scene_core(means: torch.Tensor) -> tuple[np.ndarray, float]:
    """(center [3], radius): median position and the CORE_QUANTILE distance from it."""
    m = means.detach().cpu().double().numpy()  # [N, 3]
    sub = m[:: max(1, len(m) // 200_000)]  # a strided sample keeps the quantile cheap on huge scenes
    center = np.median(sub, axis=0)
    radius = float(np.quantile(np.linalg.norm(sub - center, axis=1), CORE_QUANTILE))
    return center, max(radius, 1e-6)


def orbit_cameras(g: Gaussians, n: int = ORBIT_VIEWS, width: int = ORBIT_SIZE[0], height: int = ORBIT_SIZE[1],
                  up=WORLD_UP) -> list:
    """``n`` cameras on a ring around ``up`` through the scene's center, ORBIT_ELEVATION_DEG above it, far
    enough that the core sphere fits the narrower field of view."""
    center, radius = scene_core(g.means)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    fov_x = math.radians(ORBIT_FOV_DEG)
    fov_min = min(fov_x, 2 * math.atan(math.tan(fov_x / 2) * height / width))
    dist = MARGIN * radius / math.sin(fov_min / 2)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)  # (a, b, up) right-handed
    el = math.radians(ORBIT_ELEVATION_DEG)
    cams = []
    for k in range(n):
        t = 2 * math.pi * k / n
        eye = center + dist * (math.cos(el) * (math.cos(t) * a + math.sin(t) * b) + math.sin(el) * up)
        cam = Camera.look_at(eye, center, up=tuple(up), fov_deg=ORBIT_FOV_DEG, width=width, height=height,
                             near=max(1e-3, 0.01 * dist), name=f"orbit_{k:03d}")
        cams.append(cam)
    return cams


def cameras_from_json(path, width: int) -> SceneViews:
    """INRIA cameras.json (the 3DGS trainer's), each camera resized to ``width`` pixels wide."""
    names, cams = read_inria_cameras(path)
    cams = [c.scaled(max(1e-9, c.width / width)) if c.width > width else c for c in cams]
    return SceneViews(cams, names, str(path))


def scene_views(g: Gaussians, cameras_json=None, downscale: float = 1.0) -> SceneViews:
    """The cameras of a photo-less scene: ``cameras_json`` if given, else an orbit."""
    w = max(16, round(ORBIT_SIZE[0] / downscale))
    if cameras_json is not None:
        return cameras_from_json(cameras_json, w)
    h = max(12, round(ORBIT_SIZE[1] / downscale))
    cams = orbit_cameras(g, width=w, height=h)
    return SceneViews(cams, [c.name for c in cams], "orbit")


def render_stand_in_photos(g: Gaussians, cameras: list, background) -> list:
    """The un-stylized scene rendered into each camera: [H, W, 3] float32 in [0, 1] per view."""
    with torch.no_grad():
        return [render(g, c, background).color.clamp(0, 1).detach().cpu().float() for c in cameras]


__all__ = ["SceneViews", "scene_views", "orbit_cameras", "cameras_from_json", "render_stand_in_photos",
           "scene_core"]
