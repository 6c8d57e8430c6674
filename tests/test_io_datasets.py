"""LLFF, Blender and INRIA cameras.json datasets written by the tests, folder/downscale/split choices,
and the bad-input cases (each a one-line InputError naming the file)."""
import json

import cv2
import numpy as np
from plyfile import PlyData, PlyElement

from _io_helpers import raises_one_line as _raises, write_png
from tlvg_warp import load_dataset

POSE_TOL = 1e-9  # a 4x4 inverse of well-conditioned rigid transforms in float64
PROJ_TOL_PX = 1e-6  # projecting a point with exact intrinsics: only rounding


def _rigid(seed):
    r = np.random.default_rng(seed)
    c2w = np.eye(4)
    c2w[:3, :3] = cv2.Rodrigues(r.normal(size=3) * 0.5)[0]
    c2w[:3, 3] = r.normal(size=3)
    return c2w


def _project(cam, X):
    p = cam.world_to_camera.numpy() @ np.append(X, 1.0)
    return np.array([cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy]), p[2]


# --- LLFF ---------------------------------------------------------------------------------------------------
def _llff(root, n=10, folder="images_2", size=(80, 60), full=(160, 120), focal=150.0):
    c2ws = [_rigid(i) for i in range(n)]
    rows = []
    for c2w in c2ws:  # OpenCV columns [right, down, forward] -> LLFF [down, right, backwards]
        m = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], [full[1], full[0], focal]], 1)  # [3, 5]
        rows.append(np.concatenate([m.ravel(), [1.0, 10.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    rng = np.random.default_rng(1)
    for i in range(n):
        write_png(root / folder / f"img{i:03d}.png", rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    return c2ws


def test_llff_axes_intrinsics_and_split(tmp_path):
    c2ws = _llff(tmp_path)
    ds = load_dataset(tmp_path)  # only images_2 exists: chosen automatically
    assert len(ds) == 10 and ds.kind == "llff" and ds.points is None and ds.bounds.shape == (10, 2)
    for cam, c2w in zip(ds.cameras, c2ws):
        assert np.abs(cam.world_to_camera.numpy() - np.linalg.inv(c2w)).max() < POSE_TOL
        assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (80, 60, 75.0, 75.0, 40.0, 30.0)
        # semantic check of the axes: 2 units along the OpenCV forward axis lands on the principal point,
        # a step along the camera's "down" column lands lower in the image
        uv, z = _project(cam, c2w[:3, 3] + 2 * c2w[:3, 2])
        assert z > 0 and np.abs(uv - [40, 30]).max() < PROJ_TOL_PX
        uv2, _ = _project(cam, c2w[:3, 3] + 2 * c2w[:3, 2] + 0.1 * c2w[:3, 1])
        assert uv2[1] > uv[1] + 1
    test = load_dataset(tmp_path, split="test")
    train = load_dataset(tmp_path, split="train")
    assert test.names == ["img000.png", "img008.png"] and len(train) == 8 and "img000.png" not in train.names
    assert np.array_equal(test.cameras[1].world_to_camera.numpy(), ds.cameras[8].world_to_camera.numpy())


def test_downscale_resizes_with_inter_area(tmp_path):
    _llff(tmp_path, n=3, folder="images", size=(64, 48), full=(64, 48), focal=50.0)
    ds = load_dataset(tmp_path, downscale=2)
    cam = ds.cameras[0]
    assert (cam.width, cam.height, cam.fx, cam.cx) == (32, 24, 25.0, 16.0)
    src = cv2.imread(str(tmp_path / "images" / "img000.png"))[:, :, ::-1].astype(np.float32) / 255
    assert np.allclose(ds.image(0).numpy(), cv2.resize(src, (32, 24), interpolation=cv2.INTER_AREA), atol=1e-6)
    # an images_2 folder, when present, is used as is
    _llff(tmp_path, n=3, folder="images_2", size=(32, 24), full=(64, 48), focal=50.0)
    ds2 = load_dataset(tmp_path, downscale=2)
    src2 = cv2.imread(str(tmp_path / "images_2" / "img000.png"))[:, :, ::-1].astype(np.float32) / 255
    assert np.array_equal(ds2.image(0).numpy(), src2)
    assert load_dataset(tmp_path, images="images").cameras[0].width == 64


# --- Blender ------------------------------------------------------------------------------------------------
def _gl_look_at(eye, target=(0, 0, 0), up=(0, 0, 1)):
    """OpenGL camera-to-world: columns right, up, backwards (built here independently of the code)."""
    eye = np.asarray(eye, float)
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, :3] = np.stack([right, np.cross(back, right), back], 1)
    m[:3, 3] = eye
    return m


def _blender(root):
    rng = np.random.default_rng(2)
    eyes = {"train": [(3, 0, 1), (0, 3, 1), (-3, 0, 1)], "test": [(0, -3, 1), (2, 2, 2)]}
    rgba = {}
    for split, es in eyes.items():
        frames = []
        for k, e in enumerate(es):
            img = rng.integers(0, 255, (30, 40, 4), dtype=np.uint8)
            img[0, 0, 3], img[0, 1, 3] = 0, 255
            write_png(root / split / f"r_{k}.png", img)
            rgba[f"{split}/r_{k}.png"] = img
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": _gl_look_at(e).tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    return rgba



def test_images_in_threads_equal_opencv_in_view_order(tmp_path):
    """``images()`` (decoded in a thread pool) returns every view in order, each equal to OpenCV's own decode of
    its file, and fills the cache ``image(i)`` returns. Catches results gathered in completion order."""
    _llff(tmp_path, n=7, folder="images", size=(40, 30), full=(40, 30), focal=30.0)
    ds = load_dataset(tmp_path)
    got = ds.images()
    assert len(got) == 7
    for i, img in enumerate(got):
        src = cv2.imread(str(tmp_path / "images" / f"img{i:03d}.png"))[:, :, ::-1].astype(np.float32) / 255
        assert np.array_equal(img.numpy(), src) and ds.image(i) is img

def test_blender(tmp_path):
    rgba = _blender(tmp_path)
    ds = load_dataset(tmp_path)
    assert ds.names == sorted(rgba) and len(ds) == 5 and ds.points is None
    assert len(load_dataset(tmp_path, split="train")) == 3 and len(load_dataset(tmp_path, split="test")) == 2
    f = 0.5 * 40 / np.tan(0.4)
    for cam in ds.cameras:
        assert (cam.width, cam.height, cam.cx, cam.cy) == (40, 30, 20.0, 15.0) and abs(cam.fx - f) < 1e-9
        uv, z = _project(cam, np.zeros(3))  # every camera looks at the origin
        assert z > 0 and np.abs(uv - [20, 15]).max() < PROJ_TOL_PX
        up, _ = _project(cam, np.array([0, 0, 0.2]))  # world up appears higher in the image (smaller row)
        assert up[1] < uv[1] - 1
    # RGBA over the background: straight alpha, computed here from the PNG bytes
    for bg in ((1.0, 1.0, 1.0), (0.0, 0.25, 0.5)):
        d = load_dataset(tmp_path, background=bg)
        src = rgba[d.names[0]].astype(np.float32) / 255
        expect = src[:, :, :3] * src[:, :, 3:] + np.array(bg, np.float32) * (1 - src[:, :, 3:])
        got = d.image(0).numpy()
        assert np.allclose(got, expect, atol=1e-6) and np.allclose(got[0, 0], bg)



def test_dataset_background_white_for_blender_black_for_photos_else_the_datasets_own(tmp_path):
    """One rule for reconstruct and stylize: a Blender scene renders over white, real photos over black, a dataset
    with its own background (the demo) over that."""
    from tlvg_warp.io.datasets import dataset_background
    from tlvg_warp.io.demo import DEMO_BACKGROUND, demo_dataset

    _blender(tmp_path / "blender")
    (tmp_path / "llff").mkdir()
    _llff(tmp_path / "llff")
    assert dataset_background(load_dataset(tmp_path / "blender")) == (1.0, 1.0, 1.0)
    assert dataset_background(load_dataset(tmp_path / "llff")) == (0.0, 0.0, 0.0)
    demo = demo_dataset(n_views=2, width=16, height=12)
    assert dataset_background(demo) == tuple(DEMO_BACKGROUND)
    demo.background = (0.0, 0.25, 0.5)
    assert dataset_background(demo) == (0.0, 0.25, 0.5)

# --- INRIA cameras.json ------------------------------------------------------------------------------------
def test_inria_cameras_json(tmp_path):
    cams = []
    for i in range(3):
        c2w = _rigid(10 + i)
        cams.append({"id": i, "img_name": f"v{i}", "width": 40, "height": 30, "position": c2w[:3, 3].tolist(),
                     "rotation": c2w[:3, :3].tolist(), "fx": 33.0, "fy": 34.0})
        write_png(tmp_path / "images" / f"v{i}.jpg" if i else tmp_path / "images" / "v0.png",
                  np.full((30, 40, 3), 50 * i, np.uint8))
    (tmp_path / "cameras.json").write_text(json.dumps(cams))
    v = np.zeros(4, [(c, "f4") for c in "xyz"] + [(c, "u1") for c in ("red", "green", "blue")])
    v["x"], v["red"] = [1, 2, 3, 4], [0, 255, 51, 0]
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "input.ply"))
    ds = load_dataset(tmp_path)
    assert ds.names == ["v0", "v1", "v2"] and ds.kind == "inria"
    for cam, c in zip(ds.cameras, cams):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = c["rotation"], c["position"]
        assert np.abs(cam.world_to_camera.numpy() - np.linalg.inv(c2w)).max() < POSE_TOL
        assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width) == (33.0, 34.0, 20.0, 15.0, 40)
    assert abs(ds.image(1).mean().item() - 50 / 255) < 2 / 255  # JPEG: within its quantization
    assert np.allclose(ds.points[0][:, 0].numpy(), [1, 2, 3, 4]) and np.allclose(ds.points[1][2, 0].item(), 0.2)


# --- bad input ----------------------------------------------------------------------------------------------
def test_nonexistent_path(tmp_path):
    _raises(lambda: load_dataset(tmp_path / "no_scene"), "no_scene", "does not exist")
    (tmp_path / "f.txt").write_text("x")
    _raises(lambda: load_dataset(tmp_path / "f.txt"), "f.txt")
    (tmp_path / "empty").mkdir()
    _raises(lambda: load_dataset(tmp_path / "empty"), "empty", "no dataset found")


def test_camera_count_mismatch(tmp_path):
    _llff(tmp_path, n=4)
    (tmp_path / "images_2" / "img003.png").unlink()
    _raises(lambda: load_dataset(tmp_path), "poses_bounds.npy", "4 poses but 3 images")


def test_unreadable_image_header(tmp_path):
    _llff(tmp_path, n=3)
    (tmp_path / "images_2" / "img001.png").write_bytes(b"not an image at all, just text" * 4)
    _raises(lambda: load_dataset(tmp_path), "img001.png", "unreadable")


def test_unreadable_image_body(tmp_path):
    _llff(tmp_path, n=3)
    f = tmp_path / "images_2" / "img002.png"
    f.write_bytes(f.read_bytes()[:40])  # valid header, body cut off: found with the headers, before any decoding
    _raises(lambda: load_dataset(tmp_path), "img002.png", "truncated")


def test_inconsistent_sizes(tmp_path):
    _llff(tmp_path, n=3)
    write_png(tmp_path / "images_2" / "img001.png", np.zeros((60, 70, 3), np.uint8))
    _raises(lambda: load_dataset(tmp_path), "img001.png", "70x60", "inconsistent")


def test_bad_poses_bounds(tmp_path):
    _llff(tmp_path, n=2)
    a = np.load(tmp_path / "poses_bounds.npy")
    a[1, 3] = np.nan
    np.save(tmp_path / "poses_bounds.npy", a)
    _raises(lambda: load_dataset(tmp_path), "poses_bounds.npy", "1 NaN")
    np.save(tmp_path / "poses_bounds.npy", a[:, :15])
    _raises(lambda: load_dataset(tmp_path), "poses_bounds.npy", "N x 17")
    (tmp_path / "poses_bounds.npy").write_bytes(b"\x93NUMPY garbage")
    _raises(lambda: load_dataset(tmp_path), "poses_bounds.npy", "unreadable")


def test_blender_bad_json_and_missing_frame(tmp_path):
    _blender(tmp_path)
    (tmp_path / "test" / "r_1.png").unlink()
    _raises(lambda: load_dataset(tmp_path), "r_1.png", "missing")
    _raises(lambda: load_dataset(tmp_path, images="images_4"), "NeRF/Blender")
    (tmp_path / "transforms_train.json").write_text("{not json")
    _raises(lambda: load_dataset(tmp_path), "transforms_train.json", "corrupt JSON")


def test_missing_image_folder(tmp_path):
    _llff(tmp_path, n=2)
    _raises(lambda: load_dataset(tmp_path, images="images_8"), "images_8", "does not exist")


def test_non_finite_blender_pose_names_json(tmp_path):
    _blender(tmp_path)
    meta = json.loads((tmp_path / "transforms_test.json").read_text())
    meta["camera_angle_x"] = 0.0  # focal = 0.5 W / tan(0) -> infinite
    (tmp_path / "transforms_test.json").write_text(json.dumps(meta))
    _raises(lambda: load_dataset(tmp_path), "transforms_test.json")
