"""`stylize --scene FILE` without photos: cameras orbit the scene (or come from an INRIA
cameras.json) and the scene's own renders stand in for the photos."""
from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import torch

from tlvg_warp.io.scene_views import (ORBIT_FOV_DEG, WORLD_UP, cameras_from_json, orbit_cameras,
                                      render_stand_in_photos, scene_core, scene_views)
from tlvg_warp.types import Camera, Gaussians

CENTER = np.array([0.5, -1.0, 2.0])


def blob(n=1500, seed=0) -> Gaussians:
    """A ball of Gaussians of radius ~1 around CENTER."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    rgb = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return Gaussians.from_colors(torch.from_numpy(CENTER) + d, rgb, 0.05, opacity=0.8).to(dtype=torch.float32)


def project(cam: Camera, p: np.ndarray) -> np.ndarray:  # [3] -> (u, v, z)
    x = cam.world_to_camera.numpy() @ np.append(p, 1.0)
    return np.array([cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy, x[2]])


def test_orbit_frames_the_scene_upright_from_every_side():
    g = blob()
    center, radius = scene_core(g.means)
    cams = orbit_cameras(g, n=8, width=80, height=60)
    eyes = np.stack([c.center.numpy() for c in cams])
    dist = np.linalg.norm(eyes - center, axis=1)
    assert np.allclose(dist, dist[0])  # one ring
    half_fov_v = math.atan(math.tan(math.radians(ORBIT_FOV_DEG) / 2) * 60 / 80)
    assert np.all(radius / dist <= math.sin(half_fov_v))  # the core sphere fits the narrower field of view
    up = np.array(WORLD_UP)
    for c in cams:
        u, v, z = project(c, center)
        assert z > 0 and abs(u - c.cx) < 1e-6 and abs(v - c.cy) < 1e-6  # looks at the center
        above = project(c, center + 0.1 * radius * up)
        assert above[1] < v  # world up appears up in the image (smaller row)
    azimuth = np.degrees(np.arctan2(*(eyes - center)[:, [0, 2]].T))
    assert np.ptp(np.sort(azimuth)) > 300  # all the way around


def test_stand_in_photos_show_the_scene_centered():
    g = blob()
    views = scene_views(g, downscale=4.0)
    photos = render_stand_in_photos(g, views.cameras[::6], (1.0, 1.0, 1.0))
    for ph, cam in zip(photos, views.cameras[::6]):
        assert tuple(ph.shape) == (cam.height, cam.width, 3)
        ink = (1.0 - ph.mean(-1)).numpy()  # what differs from the white background
        assert ink.mean() > 0.05
        rows, cols = np.mgrid[0:cam.height, 0:cam.width] + 0.5
        cy, cx = (ink * rows).sum() / ink.sum(), (ink * cols).sum() / ink.sum()
        assert abs(cx - cam.cx) < 0.1 * cam.width and abs(cy - cam.cy) < 0.1 * cam.height


def test_cameras_json_round_trip(tmp_path):
    from tlvg_warp.train.reconstruct import cameras_json

    cams = [Camera.look_at(CENTER + [3 * math.cos(t), 0.5, 3 * math.sin(t)], CENTER, up=WORLD_UP, width=640,
                           height=480, name=f"v{k}") for k, t in enumerate(np.linspace(0, 2, 3))]
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps(cameras_json(SimpleNamespace(cameras=cams, names=[c.name for c in cams]))))
    views = cameras_from_json(path, width=160)
    assert views.names == [c.name for c in cams]
    for a, b in zip(cams, views.cameras):
        assert torch.allclose(a.world_to_camera, b.world_to_camera, atol=1e-6)
        assert (b.width, b.height) == (160, 120) and math.isclose(b.fx, a.fx / 4, rel_tol=1e-6)


def test_cameras_flag_without_scene_is_exit_code_2(tmp_path, capsys):
    from tlvg_warp.cli import main

    assert main(["stylize", "--cameras", str(tmp_path / "cameras.json"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "--cameras" in err and err.count("\n") == 1
