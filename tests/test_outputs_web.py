"""Outputs others can use: orbit.mp4 in H.264 that browsers play, and files as readable as the
umask allows (not mkstemp's private 0600)."""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from tlvg_warp.fileio import write_json, write_text
from tlvg_warp.stylize.outputs import write_video

VIDEO_MEAN_ERR = 4 / 255  # CRF 18 x264 on smooth frames: mean |decoded - sent| well under 2 gray levels


def _frames(n: int, h: int, w: int) -> list:
    """A smooth gradient sliding sideways: [H, W, 3] floats in [0, 1]."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return [np.stack([(x + 3 * k) / (w + 3 * n), y / h, np.full_like(x, 0.5)], -1) for k in range(n)]


@pytest.mark.parametrize("size", [(48, 64), (45, 61)])
def test_orbit_video_is_h264_that_browsers_play(tmp_path, size):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="imageio-ffmpeg is not installed")
    h, w = size
    frames = _frames(12, h, w)
    path = tmp_path / "orbit.mp4"
    assert write_video(path, frames, 24) is None  # None: H.264 written, no fallback note
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    decoded = [np.frombuffer(b, np.uint8).reshape(meta["size"][1], meta["size"][0], 3) for b in reader]
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert meta["size"] == (w + w % 2, h + h % 2)  # yuv420p: odd sizes get one repeated row / column
    assert len(decoded) == len(frames) and meta["fps"] == 24
    err = np.mean([np.abs(d[:h, :w] / 255.0 - f).mean() for d, f in zip(decoded, frames)])
    assert err < VIDEO_MEAN_ERR
    data = path.read_bytes()
    assert data.index(b"moov") < data.index(b"mdat")  # +faststart: a browser can start before the download ends
    # frames already in uint8 (the stylization converts its renders on the GPU) encode to the same file; the
    # oracle is numpy's own rounding of the float frames. Catches a second scaling (x255 twice) or a lost rounding.
    u8 = [np.clip(f * 255.0 + 0.5, 0, 255).astype(np.uint8) for f in frames]
    assert write_video(tmp_path / "u8.mp4", u8, 24) is None and (tmp_path / "u8.mp4").read_bytes() == data


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o002])
def test_outputs_get_the_mode_the_umask_allows(tmp_path, mask):
    old = os.umask(mask)
    try:
        with open(tmp_path / "plain.txt", "w") as f:  # the oracle: what an ordinary open() creates
            f.write("x")
        write_text(tmp_path / "atomic.txt", "x")
        write_json(tmp_path / "sub" / "m.json", {"a": 1})
    finally:
        os.umask(old)
    plain = os.stat(tmp_path / "plain.txt").st_mode & 0o777
    assert plain == 0o666 & ~mask
    assert os.stat(tmp_path / "atomic.txt").st_mode & 0o777 == plain
    assert os.stat(tmp_path / "sub" / "m.json").st_mode & 0o777 == plain


def test_u8_of_a_tensor_equals_numpys_rounding():
    """Renders are converted to uint8 where they are (torch); the oracle is the numpy path on the same values,
    NaN, out-of-range and exact halves included. Catches a missing +0.5 (truncation) or a clamp after scaling."""
    import torch

    from tlvg_warp.stylize.outputs import to_u8

    g = torch.Generator().manual_seed(0)
    x = torch.rand(17, 23, 3, generator=g) * 1.4 - 0.2
    x[0, 0, 0], x[0, 1, 0], x[1, 0, 1] = float("nan"), 0.5 / 255.0, 254.5 / 255.0
    assert to_u8(x).dtype == np.uint8 and np.array_equal(to_u8(x), to_u8(x.numpy()))


def test_orbit_slerp_matches_scipy():
    """The orbit's rotations: our quaternion conversion and slerp against scipy's Rotation and Slerp (the oracle;
    the stylize run no longer imports scipy), over random keys, including neighbours more than 180 degrees apart
    as quaternions (the shorter arc) and repeated keys (the small-angle branch)."""
    from scipy.spatial.transform import Rotation, Slerp

    from tlvg_warp.stylize.outputs import slerp_rotations
    from tlvg_warp.train.optim import quat_to_rotmat, rotmat_to_quat

    keys = Rotation.random(12, random_state=3).as_matrix()
    keys[5] = keys[4]  # equal neighbours
    keys[8] = Rotation.from_rotvec([0, 0, 3.1]).as_matrix()
    keys[9] = Rotation.from_rotvec([0, 0, -3.1]).as_matrix()  # 0.08 rad apart across the pi boundary
    q = rotmat_to_quat(keys)
    assert np.allclose(quat_to_rotmat(torch.from_numpy(q)).numpy(), keys, atol=1e-12)
    ref_q = Rotation.from_matrix(keys).as_quat()[:, [3, 0, 1, 2]]  # scipy: x, y, z, w
    assert np.allclose(np.abs((q * ref_q).sum(1)), 1.0, atol=1e-12)  # the same rotation (q or -q)
    ts = np.concatenate([np.linspace(0, 11, 97), [0.0, 4.5, 8.5, 11.0]])
    ours = slerp_rotations(keys, ts)
    ref = Slerp(np.arange(12.0), Rotation.from_matrix(keys))(ts).as_matrix()
    assert np.allclose(ours, ref, atol=1e-9)
    # the 8 -> 9 step goes the short way: halfway is the identity's neighbourhood around z = pi, not z = 0
    assert abs(abs(Rotation.from_matrix(ours[-2]).as_rotvec()[2]) - np.pi) < 1e-6
