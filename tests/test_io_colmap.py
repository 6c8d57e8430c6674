"""COLMAP binary and text models written by the test itself (struct / plain text), undistortion checked
against OpenCV's own projectPoints / undistortPoints, and the malformed-model cases."""
import numpy as np
import pytest

from _io_helpers import (quat_from_axis_angle, raises_one_line as _raises, rot_from_quat_rodrigues, write_colmap_bin,
                         write_colmap_txt, write_png)
from tlvg_warp import load_dataset
from tlvg_warp.io import colmap

POSE_TOL = 1e-12  # poses go through float64 files and one 4x4 build: only rounding differs
BLOB_TOL_PX = 0.15  # centroid of a bilinearly resampled Gaussian blob (sigma 1.5 px) vs its exact center
CV_TOL_PX = 1e-3  # two OpenCV paths to the same undistorted point (iterative undistortPoints converges)

PINHOLE = (1, "PINHOLE", 80, 60, [70.0, 72.0, 40.5, 29.5])
RADIAL = (2, "SIMPLE_RADIAL", 80, 60, [75.0, 40.0, 30.0, 0.08])


def _scene():
    q = [quat_from_axis_angle(a, ang) for a, ang in (([0, 1, 0], 0.3), ([1, 1, 0], -0.2), ([0, 0, 1], 2.0))]
    t = [np.array([0.1, -0.2, 3.0]), np.array([0.0, 0.3, 2.5]), np.array([-0.4, 0.0, 4.0])]
    xys = [np.array([[10.5, 20.25], [30.0, 40.0]]), np.zeros((0, 2)), np.array([[1.0, 2.0]])]
    p3d = [np.array([7, -1]), np.zeros(0, np.int64), np.array([9])]
    # ids deliberately not in name order: the dataset must sort by image name
    images = [(1, q[0], t[0], 1, "b.png", xys[0], p3d[0]), (2, q[1], t[1], 2, "a.png", xys[1], p3d[1]),
              (5, q[2], t[2], 1, "c.png", xys[2], p3d[2])]
    points = [(7, [0.1, 0.2, 0.3], [255, 0, 10], 0.5, [(1, 0)]),
              (9, [1.0, -2.0, 3.5], [1, 2, 3], 0.25, [(5, 0), (1, 1)])]
    return [PINHOLE, RADIAL], images, points


def _write(root, fmt):
    cams, images, points = _scene()
    (write_colmap_bin if fmt == "bin" else write_colmap_txt)(root / "sparse" / "0", cams, images, points)
    rng = np.random.default_rng(0)
    for im in images:
        write_png(root / "images" / im[4], rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    return cams, images, points


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_model_read_back(tmp_path, fmt):
    cams, images, points = _write(tmp_path, fmt)
    d = tmp_path / "sparse" / "0"
    c = colmap.read_cameras(d / f"cameras.{fmt}")
    assert c[2].model == "SIMPLE_RADIAL" and np.array_equal(c[2].params, RADIAL[4]) and c[1].width == 80
    ims = colmap.read_images(d / f"images.{fmt}")
    assert sorted(ims) == [1, 2, 5] and ims[1].name == "b.png" and ims[5].camera_id == 1
    assert np.array_equal(ims[1].xys, images[0][5]) and np.array_equal(ims[1].point3d_ids, [7, -1])
    assert ims[2].xys.shape == (0, 2)
    p = colmap.read_points3d(d / f"points3D.{fmt}")
    assert np.array_equal(p.ids, [7, 9]) and np.array_equal(p.xyz, [pt[1] for pt in points])
    assert np.array_equal(p.rgb, [[255, 0, 10], [1, 2, 3]]) and np.array_equal(p.error, [0.5, 0.25])
    assert np.array_equal(p.track_offsets, [0, 1, 3])
    assert np.array_equal(p.track_image_ids, [1, 5, 1]) and np.array_equal(p.track_point2d_idx, [0, 0, 1])


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_dataset(tmp_path, fmt):
    cams, images, points = _write(tmp_path, fmt)
    ds = load_dataset(tmp_path)
    assert ds.names == ["a.png", "b.png", "c.png"] and len(ds) == 3 and ds.kind == "colmap"
    by_name = {im[4]: im for im in images}
    for cam, name in zip(ds.cameras, ds.names):
        _, q, t, cid, *_ = by_name[name]
        expect = np.eye(4)
        expect[:3, :3], expect[:3, 3] = rot_from_quat_rodrigues(q), t
        assert np.abs(cam.world_to_camera.numpy() - expect).max() < POSE_TOL
        assert (cam.width, cam.height) == (80, 60) and ds.image(ds.names.index(name)).shape == (60, 80, 3)
    b = ds.cameras[1]  # PINHOLE: intrinsics untouched
    assert (b.fx, b.fy, b.cx, b.cy) == (70.0, 72.0, 40.5, 29.5)
    assert np.array_equal(ds.image(1).numpy(), _read_png(tmp_path / "images" / "b.png"))
    xyz, rgb = ds.points
    assert np.allclose(xyz.numpy(), [pt[1] for pt in points]) and np.allclose(rgb[0].numpy(), [1, 0, 10 / 255])


def _read_png(path):
    import cv2

    return cv2.imread(str(path))[:, :, ::-1].astype(np.float32) / 255


def test_binary_and_text_agree(tmp_path):
    _write(tmp_path / "b", "bin")
    _write(tmp_path / "t", "txt")
    a, b = load_dataset(tmp_path / "b"), load_dataset(tmp_path / "t")
    for ca, cb in zip(a.cameras, b.cameras):
        assert np.array_equal(ca.world_to_camera.numpy(), cb.world_to_camera.numpy())
        assert (ca.fx, ca.fy, ca.cx, ca.cy) == (cb.fx, cb.fy, cb.cx, cb.cy)


def test_undistortion_matches_opencv(tmp_path):
    """An OPENCV-model photo of known 3D points: after load_dataset's undistortion each blob sits where
    the returned pinhole camera projects its 3D point, and where cv2.undistortPoints sends it."""
    import cv2

    W, H = 200, 150
    params = [160.0, 155.0, 101.0, 74.0, -0.12, 0.03, 0.002, -0.001]
    K = np.array([[160.0, 0, 101.0], [0, 155.0, 74.0], [0, 0, 1]])
    dist = np.array(params[4:])
    half = np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])  # COLMAP pixel centers at +0.5, OpenCV at 0
    gx, gy = np.meshgrid(np.linspace(-0.4, 0.4, 5), np.linspace(-0.3, 0.3, 4))
    X = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], 1)  # [20, 3] in front of an identity camera
    dpx = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K - half, dist)[0].reshape(-1, 2) + 0.5  # distorted
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    img = np.zeros((H, W))
    for u, v in dpx:  # a loop over 20 blobs, each a whole-image array expression
        img += np.exp(-((jj - u) ** 2 + (ii - v) ** 2) / (2 * 1.5 ** 2))
    png = np.repeat((np.clip(img, 0, 1) * 65535 + 0.5).astype(np.uint16)[:, :, None], 3, 2)
    (tmp_path / "images").mkdir()
    assert cv2.imwrite(str(tmp_path / "images" / "x.png"), png)  # 16-bit: blob centroids stay sub-pixel exact
    write_colmap_bin(tmp_path / "sparse" / "0", [(1, "OPENCV", W, H, params)],
                     [(1, [1, 0, 0, 0], [0, 0, 0], 1, "x.png", np.zeros((0, 2)), np.zeros(0, np.int64))], [])
    ds = load_dataset(tmp_path)
    cam, out = ds.cameras[0], ds.image(0).numpy()[:, :, 0]
    assert (cam.width, cam.height) == (W, H) and cam.fx != 160.0  # a new pinhole, not the input K
    proj = np.stack([cam.fx * X[:, 0] / X[:, 2] + cam.cx, cam.fy * X[:, 1] / X[:, 2] + cam.cy], 1)
    und = cv2.undistortPoints(dpx.reshape(-1, 1, 2) - 0.5, K - half, dist, P=cam.K.numpy() - half)
    assert np.abs(und.reshape(-1, 2) + 0.5 - proj).max() < CV_TOL_PX
    for u, v in proj:
        i0, j0 = int(v), int(u)
        win = out[i0 - 5:i0 + 6, j0 - 5:j0 + 6]
        wi, wj = np.meshgrid(np.arange(i0 - 5, i0 + 6) + 0.5, np.arange(j0 - 5, j0 + 6) + 0.5, indexing="ij")
        c = np.array([(win * wj).sum(), (win * wi).sum()]) / win.sum()
        assert np.abs(c - [u, v]).max() < BLOB_TOL_PX, (c, u, v)


# --- bad input ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_unknown_camera_model(tmp_path, fmt):
    _write(tmp_path, fmt)
    (write_colmap_bin if fmt == "bin" else write_colmap_txt)(
        tmp_path / "sparse" / "0", [(1, "FOV", 80, 60, [70.0, 70.0, 40.0, 30.0, 0.1]), RADIAL], *_scene()[1:])
    _raises(lambda: load_dataset(tmp_path), f"cameras.{fmt}", "FOV", "unsupported")


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_binary(tmp_path, name):
    _write(tmp_path, "bin")
    f = tmp_path / "sparse" / "0" / name
    f.write_bytes(f.read_bytes()[:-7])
    _raises(lambda: load_dataset(tmp_path), name)


def test_corrupt_text(tmp_path):
    _write(tmp_path, "txt")
    f = tmp_path / "sparse" / "0" / "images.txt"
    f.write_text(f.read_text().replace("b.png", "").replace(" 1 \n", " one \n", 1))
    _raises(lambda: load_dataset(tmp_path), "images.txt")


def test_missing_image_file(tmp_path):
    _write(tmp_path, "bin")
    (tmp_path / "images" / "c.png").unlink()
    _raises(lambda: load_dataset(tmp_path), "c.png", "missing")


def test_unknown_camera_id(tmp_path):
    _, images, points = _write(tmp_path, "bin")
    write_colmap_bin(tmp_path / "sparse" / "0", [PINHOLE], images, points)  # camera 2 absent
    _raises(lambda: load_dataset(tmp_path), "images.bin", "camera 2")
