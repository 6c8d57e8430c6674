"""Independent writers for the io tests: COLMAP binary/text written with struct, images with cv2,
rotations built with cv2.Rodrigues (so the code under test never checks itself)."""
from __future__ import annotations

import os
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from tlvg_warp import InputError

MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "FOV": 7}


def run_cli(argv, capsys):
    """(exit code, stderr) of ``python -m tlvg_warp ARGV`` run in this process (argparse's exit included)."""
    from tlvg_warp.cli import main

    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    return rc, capsys.readouterr().err


def raises_one_line(fn, *words):
    """``fn()`` raises InputError with a one-line message holding every word."""
    with pytest.raises(InputError) as e:
        fn()
    assert "\n" not in str(e.value)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def data_root() -> Path | None:
    p = Path(os.environ.get("TLVG_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    return p if p.is_dir() else None


def quat_from_axis_angle(axis, angle):  # w, x, y, z
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def rot_from_quat_rodrigues(q):
    """Rotation for quaternion q via cv2.Rodrigues (axis-angle), not via the quaternion formula."""
    q = np.asarray(q, float) / np.linalg.norm(q)
    angle = 2 * np.arccos(np.clip(q[0], -1, 1))
    s = np.linalg.norm(q[1:])
    rvec = np.zeros(3) if s < 1e-12 else q[1:] / s * angle
    return cv2.Rodrigues(rvec)[0]


def write_png(path, rgb_u8):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    a = rgb_u8[..., [2, 1, 0, 3]] if rgb_u8.shape[-1] == 4 else rgb_u8[..., ::-1]
    assert cv2.imwrite(str(path), np.ascontiguousarray(a))


def write_colmap_bin(d, cams, images, points):
    """cams: [(id, model, w, h, params)], images: [(id, q, t, cam_id, name, xys [M,2], p3d [M])],
    points: [(id, xyz, rgb, err, [(image_id, p2d_idx)])]."""
    d = Path(d)
    d.mkdir(parents=True, exist_ok=True)
    b = struct.pack("<Q", len(cams))
    for cid, model, w, h, params in cams:
        b += struct.pack("<iiQQ", cid, MODEL_IDS[model], w, h) + struct.pack(f"<{len(params)}d", *params)
    (d / "cameras.bin").write_bytes(b)
    b = struct.pack("<Q", len(images))
    for iid, q, t, cid, name, xys, p3d in images:
        b += struct.pack("<i4d3di", iid, *q, *t, cid) + name.encode() + b"\0" + struct.pack("<Q", len(xys))
        for (x, y), pid in zip(xys, p3d):
            b += struct.pack("<ddq", x, y, pid)
    (d / "images.bin").write_bytes(b)
    b = struct.pack("<Q", len(points))
    for pid, xyz, rgb, err, track in points:
        b += struct.pack("<Q3d3BdQ", pid, *xyz, *rgb, err, len(track))
        for iid, k in track:
            b += struct.pack("<ii", iid, k)
    (d / "points3D.bin").write_bytes(b)


def write_colmap_txt(d, cams, images, points):
    d = Path(d)
    d.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:"]
    lines += [f"{cid} {model} {w} {h} " + " ".join(repr(float(p)) for p in params)
              for cid, model, w, h, params in cams]
    (d / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for iid, q, t, cid, name, xys, p3d in images:
        lines.append(f"{iid} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {cid} {name}")
        lines.append(" ".join(f"{x!r} {y!r} {pid}" for (x, y), pid in zip(xys.tolist(), p3d.tolist())))
    (d / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list"]
    for pid, xyz, rgb, err, track in points:
        lines.append(f"{pid} " + " ".join(repr(float(v)) for v in xyz) + " " + " ".join(str(int(c)) for c in rgb)
                     + f" {err!r} " + " ".join(f"{i} {k}" for i, k in track))
    (d / "points3D.txt").write_text("\n".join(lines) + "\n")
