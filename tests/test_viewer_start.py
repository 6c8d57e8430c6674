"""The viewer's starting viewpoint shows the subject with no training-camera frustum in front of it: checked with
an independent look-at projection (a cone around the view axis, so the result does not depend on the roll)."""
import math

import numpy as np
import torch

from tlvg_warp.types import Camera
from tlvg_warp.viewer import initial_view, scene_center, up_from_cameras


def _centers(cams):
    return [torch.linalg.inv(c.world_to_camera.double())[:3, 3].numpy() for c in cams]


def obstructing(position, look_at, fov_y, aspect, centers, subject) -> list:
    """Indices of the camera centers that lie between the eye and the subject's depth and inside the central half
    of the image (the cone of half-angle atan(0.5 tan(min half-fov))); a center at the eye itself is not one."""
    f = np.asarray(look_at, float) - np.asarray(position, float)
    f /= np.linalg.norm(f)
    half = min(fov_y / 2, math.atan(aspect * math.tan(fov_y / 2)))
    cone = math.atan(0.5 * math.tan(half))
    z_subject = float(np.dot(np.asarray(subject) - position, f))
    out = []
    for i, c in enumerate(centers):
        d = np.asarray(c) - position
        if np.linalg.norm(d) < 1e-9:
            continue
        z = float(np.dot(d, f))
        if 0 < z < z_subject and math.acos(min(1.0, z / np.linalg.norm(d))) < cone:
            out.append(i)
    return out


def _in_view(position, look_at, fov_y, point) -> bool:
    f = np.asarray(look_at, float) - position
    d = np.asarray(point, float) - position
    return math.acos(np.dot(f, d) / np.linalg.norm(f) / np.linalg.norm(d)) < fov_y / 2


def test_demo_starts_unobstructed_at_a_training_camera():
    from tlvg_warp.io.demo import demo_dataset

    ds = demo_dataset(n_views=24, width=80, height=60)
    cams = list(ds.cameras)
    center, up = scene_center(ds.gaussians), up_from_cameras(cams)
    v = initial_view(center, up, cams, 1.0)
    c0 = cams[0]
    aspect, centers = c0.width / c0.height, _centers(cams)
    assert obstructing(v["position"], v["look_at"], v["fov"], aspect, centers, center) == []
    assert _in_view(v["position"], v["look_at"], v["fov"], center)
    assert min(np.linalg.norm(np.asarray(c) - v["position"]) for c in centers) < 1e-9  # a training camera's pose
    # the oracle sees the old start (a step behind the first camera, looking along it): its frustum in the middle
    R = torch.linalg.inv(c0.world_to_camera.double())[:3, :3].numpy()
    pos = centers[0]
    depth = float(np.dot(center - pos, R[:, 2]))
    behind = pos - 0.35 * depth * R[:, 2]
    assert obstructing(behind, pos + depth * R[:, 2], v["fov"], aspect, centers, center) == [0]


def test_cameras_walking_towards_the_subject_start_from_the_front_one():
    """Cameras on a line, each in front of the previous one: from the first, the others stand in the middle of
    the view; the start must be a pose with none in front (the front-most camera)."""
    cams = [Camera.look_at((0.0, 0.0, float(z)), (0.0, 0.0, 10.0), up=(0, -1, 0), fov_deg=50, width=64, height=48)
            for z in range(5)]
    centers, subject = _centers(cams), np.array([0.0, 0.0, 10.0])
    fov = 2 * math.atan(24 / cams[0].fy)
    assert obstructing(centers[0], subject, fov, 64 / 48, centers, subject) == [1, 2, 3, 4]  # the naive start
    v = initial_view(subject, (0, -1, 0), cams)
    assert obstructing(v["position"], v["look_at"], v["fov"], 64 / 48, centers, subject) == []
    assert _in_view(v["position"], v["look_at"], v["fov"], subject)
    assert np.allclose(v["position"], centers[4])


def test_no_cameras_looks_at_the_center_from_outside():
    v = initial_view((1.0, 2.0, 3.0), (0, 0, 1), [], radius=2.0)
    d = np.asarray(v["position"]) - (1.0, 2.0, 3.0)
    assert np.allclose(v["look_at"], (1.0, 2.0, 3.0)) and 1.0 < np.linalg.norm(d) < 2.5
