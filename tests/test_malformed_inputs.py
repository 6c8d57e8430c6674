"""A corpus of malformed inputs for every format the CLI reads: each must end in exactly one line on stderr
that names the culprit (file, flag or endpoint) and the problem, exit 2, no traceback, nothing left in --out, and the
input files untouched (hashed before and after).

All cases run in this one process through ``cli.main(argv)`` and share one fixture of valid inputs: a small scene
(the demo scene, subsampled) with 4 views written in every dataset layout, photos, paintings, a config and a weights
file. Each malformed input is a valid file written another way (the test's own writers, not the code under test)
and then corrupted."""
from __future__ import annotations

import hashlib
import json
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from _io_helpers import write_colmap_bin, write_colmap_txt
from tlvg_warp.cli import main
from tlvg_warp.io import load_dataset, load_ply, save_ply
from tlvg_warp.io.demo import builtin_painting, demo_dataset

W, H, VIEWS = 32, 24, 4
REPO_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "tlvg.yaml"


# ----------------------------------------------------------------------------------------- valid inputs
def _u8(img):
    return (np.clip(np.asarray(img), 0, 1) * 255 + 0.5).astype(np.uint8)


def _imwrite(path, rgb_u8):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb_u8[..., ::-1]))


def _colmap(root, cams, photos, text=False, ext=".png"):
    """COLMAP model written with struct (tests/_io_helpers), photos with cv2."""
    images = []
    for i, c in enumerate(cams):
        m = c.world_to_camera.double().numpy()
        x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
        images.append((i + 1, [w, x, y, z], m[:3, 3].tolist(), 1, f"view{i}{ext}", np.zeros((0, 2)),
                       np.zeros(0, np.int64)))
        _imwrite(root / "images" / f"view{i}{ext}", photos[i])
    c = cams[0]
    cam = [(1, "PINHOLE", c.width, c.height, [c.fx, c.fy, c.cx, c.cy])]
    pts = [(1, [0.0, 0.0, 0.0], [128, 128, 128], 0.5, [(1, 0)])]
    (write_colmap_txt if text else write_colmap_bin)(root / "sparse" / "0", cam, images, pts)


def _llff(root, cams, photos):
    rows = []
    for i, c in enumerate(cams):
        c2w = np.linalg.inv(c.world_to_camera.double().numpy())
        R = c2w[:3, :3]
        llff = np.stack([R[:, 1], R[:, 0], -R[:, 2], c2w[:3, 3], [c.height, c.width, c.fx]], 1)  # [3, 5]
        rows.append(np.concatenate([llff.reshape(-1), [0.5, 20.0]]))
        _imwrite(root / "images" / f"img{i:03d}.png", photos[i])
    np.save(root / "poses_bounds.npy", np.array(rows))


def _blender(root, cams, photos):
    frames = []
    for i, c in enumerate(cams):
        c2w = np.linalg.inv(c.world_to_camera.double().numpy())
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w.tolist()})
        _imwrite(root / "train" / f"r_{i}.png", photos[i])
    angle = 2 * np.arctan(cams[0].width / (2 * cams[0].fx))
    (root / "transforms.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))


def _inria(root, cams, photos):
    entries = []
    for i, c in enumerate(cams):
        c2w = np.linalg.inv(c.world_to_camera.double().numpy())
        entries.append({"id": i, "img_name": f"v{i}", "width": c.width, "height": c.height, "fx": c.fx,
                        "fy": c.fy, "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist()})
        _imwrite(root / "images" / f"v{i}.png", photos[i])
    (root / "cameras.json").write_text(json.dumps(entries))


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    root = tmp_path_factory.mktemp("valid")
    ds = demo_dataset(n_views=VIEWS, width=W, height=H)
    cams = list(ds.cameras)
    photos = [_u8(ds.image(i)) for i in range(VIEWS)]
    g = ds.gaussians.subset(torch.arange(0, ds.gaussians.num, 40))
    save_ply(g, root / "scene" / "scene.ply")
    _colmap(root / "colmap_bin", cams, photos)
    _colmap(root / "colmap_txt", cams, photos, text=True)
    _colmap(root / "colmap_jpg", cams, photos, ext=".jpg")
    _llff(root / "llff", cams, photos)
    _blender(root / "blender", cams, photos)
    _inria(root / "inria", cams, photos)
    paint = _u8(cv2.resize(builtin_painting().numpy(), (128, 96), interpolation=cv2.INTER_AREA))
    _imwrite(root / "paint" / "painting.jpg", paint)
    _imwrite(root / "paint" / "painting.png", paint)
    shutil.copy(REPO_CONFIG, root / "config.yaml")
    torch.save({"features.0.weight": torch.zeros(64, 3, 3, 3), "features.0.bias": torch.zeros(64)},
               root / "weights.pth")
    # the valid inputs are valid: every layout loads, with the same cameras
    for layout in ("colmap_bin", "colmap_txt", "colmap_jpg", "llff", "blender", "inria"):
        d = load_dataset(root / layout)
        assert len(d) == VIEWS and (d.cameras[0].width, d.cameras[0].height) == (W, H), layout
        assert d.image(0).shape == (H, W, 3)
    assert load_ply(root / "scene" / "scene.ply").num == g.num > 0
    return root


# ----------------------------------------------------------------------------------------- corruptions
def _cut(f: Path, keep: float | int):
    b = f.read_bytes()
    f.write_bytes(b[: keep if isinstance(keep, int) else int(len(b) * keep)])


def _sub(f: Path, old: bytes, new: bytes, count=1):
    b = f.read_bytes()
    assert old in b, (f, old)
    f.write_bytes(b.replace(old, new, count))


def _ply_table_nan(f: Path):
    b = bytearray(f.read_bytes())
    start = b.index(b"end_header\n") + len(b"end_header\n")
    b[start + 4 * 6:start + 4 * 7] = struct.pack("<f", float("nan"))  # f_dc_0 of the first Gaussian
    f.write_bytes(bytes(b))


def _png_size(f: Path, w, h):
    b = bytearray(f.read_bytes())
    b[16:24] = struct.pack(">II", w, h)
    f.write_bytes(bytes(b))


def _jpeg_size(f: Path, w, h):
    b = bytearray(f.read_bytes())
    i = b.index(b"\xff\xc0")
    b[i + 5:i + 9] = struct.pack(">HH", h, w)
    f.write_bytes(bytes(b))


def _json_edit(f: Path, fn):
    d = json.loads(f.read_text())
    fn(d)
    f.write_text(json.dumps(d))


def _npy_edit(f: Path, fn):
    np.save(f, fn(np.load(f)))


def _resize_photo(f: Path, w, h):
    _imwrite(f, np.zeros((h, w, 3), np.uint8) + 90)


def _cameras_bin_model(f: Path, model_id):
    b = bytearray(f.read_bytes())
    b[12:16] = struct.pack("<i", model_id)
    f.write_bytes(bytes(b))


def _images_bin_camera(f: Path, cam_id):
    b = bytearray(f.read_bytes())
    b[8 + 4 + 56:8 + 4 + 56 + 4] = struct.pack("<i", cam_id)  # first record: id, 7 doubles, camera id
    f.write_bytes(bytes(b))


def _images_bin_unterminated(f: Path):
    b = f.read_bytes()
    f.write_bytes(b[: b.index(b"view0.png") + 4])


# Each case: (layout copied into the case folder, how to corrupt it, command, culprit that the line names, problem
# words). Commands: "data" = reconstruct LAYOUT; "scene" = stylize --scene scene/scene.ply --data colmap_bin;
# "style" = stylize --style ...; "config" = stylize --config; "weights" = stylize --vgg-weights; "judge".
S = "scene/scene.ply"
CB, CT, CJ = "colmap_bin/sparse/0", "colmap_txt/sparse/0", "colmap_jpg/images"
CASES = {
    # PLY scenes
    "ply_not_ply": (S, lambda f: f.write_bytes(b"solid cube\n" + f.read_bytes()[4:]), "scene", S, "not a PLY"),
    "ply_no_end_header": (S, lambda f: _sub(f, b"end_header\n", b"end_headr\n"), "scene", S, "header"),
    "ply_truncated": (S, lambda f: _cut(f, 0.7), "scene", S, "truncated"),
    "ply_missing_opacity": (S, lambda f: _sub(f, b"property float opacity\n", b"property float opacitx\n"),
                            "scene", S, "missing required"),
    "ply_nan": (S, _ply_table_nan, "scene", S, "NaN"),
    "ply_f_rest_gap": (S, lambda f: _sub(f, b"property float opacity\n",
                                         b"property float f_rest_7\nproperty float opacity\n"), "scene", S, "f_rest"),
    "ply_no_format": (S, lambda f: _sub(f, b"format binary_little_endian 1.0\n", b""), "scene", S, "format"),
    "ply_list_property": (S, lambda f: _sub(f, b"property float x\n", b"property list uchar int x\n"), "scene", S,
                          "list"),
    "ply_duplicate_property": (S, lambda f: _sub(f, b"property float y\n", b"property float x\n"), "scene", S,
                               "duplicate"),
    "ply_empty_scene": (S, lambda f: f.write_bytes(f.read_bytes()[:f.read_bytes().index(b"end_header\n") + 11]
                                                   .replace(b"element vertex ", b"element vertex 0\ncomment ")),
                        "scene", S, "no Gaussians"),
    "ply_missing": (S, lambda f: f.unlink(), "scene", S, "does not exist"),
    "ply_is_folder": (S, lambda f: (f.unlink(), f.mkdir()), "scene", S, "not a file"),
    "ply_bad_header_line": (S, lambda f: _sub(f, b"element vertex", b"element vertex 3 4\nelement vert"), "scene", S,
                            "corrupt PLY header"),
    # COLMAP binary
    "cameras_bin_truncated": (CB, lambda d: _cut(d / "cameras.bin", 20), "data", f"{CB}/cameras.bin", "truncated"),
    "images_bin_truncated": (CB, lambda d: _cut(d / "images.bin", 0.5), "data", f"{CB}/images.bin", "truncated"),
    "points_bin_truncated": (CB, lambda d: _cut(d / "points3D.bin", 0.6), "data", f"{CB}/points3D.bin", "truncated"),
    "cameras_bin_trailing": (CB, lambda d: (d / "cameras.bin").write_bytes((d / "cameras.bin").read_bytes() + b"xx"),
                             "data", f"{CB}/cameras.bin", "trailing"),
    "cameras_bin_fisheye": (CB, lambda d: _cameras_bin_model(d / "cameras.bin", 5), "data", f"{CB}/cameras.bin",
                            "OPENCV_FISHEYE"),
    "images_bin_missing": (CB, lambda d: (d / "images.bin").unlink(), "data", f"{CB}/images.bin", "missing file"),
    "images_bin_unknown_camera": (CB, lambda d: _images_bin_camera(d / "images.bin", 7), "data",
                                  f"{CB}/images.bin", "camera 7"),
    "images_bin_name_cut": (CB, lambda d: _images_bin_unterminated(d / "images.bin"), "data", f"{CB}/images.bin",
                            "truncated"),
    "colmap_photo_missing": ("colmap_bin/images", lambda d: (d / "view2.png").unlink(), "data",
                             "colmap_bin/images/view2.png", "missing"),
    # COLMAP text
    "cameras_txt_bad_number": (CT, lambda d: _sub(d / "cameras.txt", b" 32 24 ", b" 32 twentyfour "), "data",
                               f"{CT}/cameras.txt", "line 2"),
    "cameras_txt_param_count": (CT, lambda d: _sub(d / "cameras.txt", b"PINHOLE", b"SIMPLE_PINHOLE"), "data",
                                f"{CT}/cameras.txt", "needs 3 params"),
    "cameras_txt_unknown_model": (CT, lambda d: _sub(d / "cameras.txt", b"PINHOLE", b"FOV"), "data",
                                  f"{CT}/cameras.txt", "unsupported camera model"),
    "images_txt_bad_quaternion": (CT, lambda d: _sub(d / "images.txt", b"\n1 ", b"\n1 w"), "data",
                                  f"{CT}/images.txt", "corrupt COLMAP text"),
    "points_txt_bad_row": (CT, lambda d: _sub(d / "points3D.txt", b"\n1 ", b"\n1 x "), "data",
                           f"{CT}/points3D.txt", "corrupt COLMAP text"),
    "cameras_txt_missing": (CT, lambda d: (d / "cameras.txt").unlink(), "data", f"{CT}/cameras.txt", "missing file"),
    # LLFF
    "llff_not_npy": ("llff", lambda d: (d / "poses_bounds.npy").write_bytes(b"poses, bounds\n1,2,3\n"), "data",
                     "llff/poses_bounds.npy", "unreadable"),
    "llff_wrong_shape": ("llff", lambda d: _npy_edit(d / "poses_bounds.npy", lambda a: a[:, :15]), "data",
                         "llff/poses_bounds.npy", "N x 17"),
    "llff_nan": ("llff", lambda d: _npy_edit(d / "poses_bounds.npy", lambda a: np.where(a == a[0, 3], np.nan, a)),
                 "data", "llff/poses_bounds.npy", "NaN"),
    "llff_extra_photo": ("llff", lambda d: shutil.copy(d / "images" / "img000.png", d / "images" / "img009.png"),
                         "data", "llff/poses_bounds.npy", "camera count mismatch"),
    "llff_truncated_npy": ("llff", lambda d: _cut(d / "poses_bounds.npy", 0.5), "data", "llff/poses_bounds.npy",
                           "unreadable"),
    # Blender transforms
    "blender_bad_json": ("blender", lambda d: _cut(d / "transforms.json", 0.5), "data", "blender/transforms.json",
                         "corrupt JSON"),
    "blender_no_frames": ("blender", lambda d: _json_edit(d / "transforms.json", lambda j: j.pop("frames")), "data",
                          "blender/transforms.json", "frames"),
    "blender_no_matrix": ("blender", lambda d: _json_edit(d / "transforms.json",
                                                          lambda j: j["frames"][1].pop("transform_matrix")),
                          "data", "blender/transforms.json", "frame 1"),
    "blender_matrix_3x3": ("blender", lambda d: _json_edit(
        d / "transforms.json", lambda j: j["frames"][0].update(transform_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
        "data", "blender/transforms.json", "4x4"),
    "blender_negative_fov": ("blender", lambda d: _json_edit(d / "transforms.json",
                                                             lambda j: j.update(camera_angle_x=-0.5)),
                             "data", "blender/transforms.json", "camera_angle_x"),
    "blender_no_intrinsics": ("blender", lambda d: _json_edit(d / "transforms.json",
                                                              lambda j: j.pop("camera_angle_x")),
                              "data", "blender/transforms.json", "intrinsics"),
    "blender_photo_missing": ("blender", lambda d: (d / "train" / "r_3.png").unlink(), "data",
                              "blender/train/r_3.png", "missing"),
    # INRIA cameras.json
    "inria_bad_json": ("inria", lambda d: _sub(d / "cameras.json", b"[", b"{"), "data", "inria/cameras.json",
                       "corrupt JSON"),
    "inria_not_list": ("inria", lambda d: (d / "cameras.json").write_text('{"cameras": []}'), "data",
                       "inria/cameras.json", "list"),
    "inria_no_fx": ("inria", lambda d: _json_edit(d / "cameras.json", lambda j: j[2].pop("fx")), "data",
                    "inria/cameras.json", "camera 2"),
    "inria_rotation_shape": ("inria", lambda d: _json_edit(d / "cameras.json",
                                                           lambda j: j[0].update(rotation=[1, 0, 0])),
                             "data", "inria/cameras.json", "3x3"),
    # photos
    "photo_truncated_jpeg": (CJ, lambda d: _cut(d / "view1.jpg", 0.6), "data", f"{CJ}/view1.jpg", "truncated"),
    "photo_truncated_png": ("colmap_bin/images", lambda d: _cut(d / "view1.png", 0.8), "data",
                            "colmap_bin/images/view1.png", "truncated"),
    "photo_other_scale": ("colmap_bin/images", lambda d: _resize_photo(d / "view3.png", 2 * W, 2 * H), "data",
                          "colmap_bin/images/view3.png", "other photos"),
    "photo_other_aspect": ("colmap_bin/images", lambda d: _resize_photo(d / "view2.png", W, W), "data",
                           "colmap_bin/images/view2.png", "inconsistent size"),
    "photo_garbage": ("colmap_bin/images", lambda d: (d / "view0.png").write_bytes(b"GIF89a" + bytes(200)), "data",
                      "colmap_bin/images/view0.png", "unreadable"),
    "photo_huge_header": ("colmap_bin/images", lambda d: _png_size(d / "view1.png", 70000, 52500), "data",
                          "colmap_bin/images/view1.png", "claims"),
    "photo_jpeg_huge_header": (CJ, lambda d: _jpeg_size(d / "view0.jpg", 60000, 45000), "data", f"{CJ}/view0.jpg",
                               "claims"),
    # paintings
    "paint_truncated_jpeg": ("paint", lambda d: _cut(d / "painting.jpg", 0.5), "style", "paint/painting.jpg",
                             "truncated"),
    "paint_truncated_png": ("paint/painting.png", lambda f: _cut(f, 0.9), "style", "paint/painting.png",
                            "truncated"),
    "paint_huge_png": ("paint/painting.png", lambda f: _png_size(f, 80000, 60000), "style", "paint/painting.png",
                       "claims"),
    "paint_huge_jpeg": ("paint/painting.jpg", lambda f: _jpeg_size(f, 65000, 65000), "style", "paint/painting.jpg",
                        "claims"),
    "paint_impossible_png": ("paint/painting.png", lambda f: _png_size(f, 20000, 15000), "style",
                             "paint/painting.png", "corrupt PNG"),
    "paint_tiny": ("paint/painting.png", lambda f: _imwrite(f, np.zeros((20, 30, 3), np.uint8)), "style",
                   "paint/painting.png", "at least"),
    "paint_garbage": ("paint/painting.png", lambda f: f.write_bytes(b"\x89PNG garbage" * 10), "style",
                      "paint/painting.png", "unreadable"),
    "paint_missing": ("paint/painting.png", lambda f: f.unlink(), "style", "paint/painting.png", "does not exist"),
    "paint_folder": ("paint/painting.png", lambda f: (f.unlink(), f.mkdir()), "style", "paint/painting.png",
                     "folder"),
    # configs
    "config_bad_yaml": ("config.yaml", lambda f: f.write_text("w_style: [1, 2\nw_tv: 0.1\n"), "config",
                        "config.yaml", "YAML"),
    "config_unknown_key": ("config.yaml", lambda f: f.write_text(f.read_text() + "\nw_stlye: 2.0\n"), "config",
                           "w_stlye", "unknown config key"),
    "config_bad_type": ("config.yaml", lambda f: f.write_text(f.read_text() + "\nw_tv: lots\n"), "config",
                        "w_tv", "lots"),
    "config_not_mapping": ("config.yaml", lambda f: f.write_text("- 1\n- 2\n"), "config", "config.yaml", "mapping"),
    "config_missing": ("config.yaml", lambda f: f.unlink(), "config", "config.yaml", "does not exist"),
    "config_lambda_out_of_range": ("config.yaml", lambda f: f.write_text(f.read_text() + "\ntangential_lambda: 5\n"),
                                   "config", "tangential_lambda", "[0, 1]"),
    # weights files
    "weights_garbage": ("weights.pth", lambda f: f.write_bytes(b"not a state dict" * 100), "weights", "weights.pth",
                        ""),
    "weights_truncated": ("weights.pth", lambda f: _cut(f, 0.5), "weights", "weights.pth", ""),
    "weights_wrong_keys": ("weights.pth", lambda f: torch.save({"conv.weight": torch.zeros(2)}, f), "weights",
                           "weights.pth", ""),
    "weights_missing": ("weights.pth", lambda f: f.unlink(), "weights", "weights.pth", ""),
}
# CLI flags (no file to corrupt): argv tail after `stylize --scene S --data colmap_bin`, culprit, problem
FLAG_CASES = {
    "flag_negative_iterations": (["--iterations", "-5"], "iterations", "-5"),
    "flag_zero_downscale": (["--downscale", "0"], "downscale", "0"),
    "flag_unknown_set_key": (["--set", "w_bogus=1"], "w_bogus", "unknown config key"),
    "flag_set_bad_value": (["--set", "w_align=abc"], "w_align", "abc"),
    "flag_set_no_equals": (["--set", "w_align"], "--set", "key=value"),
    "flag_unknown": (["--colour", "red"], "--colour", "unrecognized"),
    "flag_bad_device": (["--device", "tpu"], "--device", "invalid choice"),
    "flag_iterations_not_int": (["--iterations", "many"], "--iterations", "invalid int"),
    "flag_data_missing": (["--data", "/nonexistent/dataset"], "/nonexistent/dataset", "does not exist"),
    "flag_resume_no_checkpoint": ("resume_empty", "checkpoint.pt", "no checkpoint"),
    "flag_resume_corrupt_checkpoint": ("resume_corrupt", "checkpoint.pt", "unreadable checkpoint"),
}
JUDGE_CASES = {
    "judge_no_key": ("https://judge.invalid/v1", None, "https://judge.invalid/v1", "no API key"),
    "judge_refused": ("http://127.0.0.1:9/v1", None, "http://127.0.0.1:9/v1", "does not answer"),
    "judge_not_url": ("judge.example.com/v1", "k", "judge.example.com/v1", "not an http(s) URL"),
    "judge_bad_port": ("http://127.0.0.1:99999/v1", "k", "http://127.0.0.1:99999/v1", "port"),
}


def _hashes(*roots) -> dict:
    out = {}
    for r in roots:
        for p in sorted(Path(r).rglob("*")):
            out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
    return out


def _run_cli(argv, capsys) -> tuple[int, str]:
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    return rc, capsys.readouterr().err


def _check(rc, err, culprit, problem, out: Path | None):
    lines = err.strip().splitlines()
    assert rc == 2, (rc, err)
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    assert culprit in lines[0] and problem in lines[0], (culprit, problem, lines[0])
    if out is not None:
        assert not out.exists(), sorted(p.name for p in out.rglob("*"))


def test_corpus_size():
    assert len(CASES) + len(FLAG_CASES) + len(JUDGE_CASES) >= 60


@pytest.mark.parametrize("name", sorted(CASES))
def test_malformed_file(valid, tmp_path, capsys, name):
    src, corrupt, cmd, culprit, problem = CASES[name]
    case = tmp_path / "in"
    shutil.copytree(valid, case)  # a few hundred KB
    target = case / src
    corrupt(target)
    before = _hashes(case)
    out = tmp_path / "out"
    scene, data = str(case / S), str(case / "colmap_bin")
    base = ["stylize", "--out", str(out), "--vgg-weights", "random", "--device", "cpu", "--quiet",
            "--iterations", "2", "--set", "orbit_frames=1"]
    argv = {
        "data": ["reconstruct", str(case / src.split("/")[0]), "--out", str(out), "--iterations", "2",
                 "--device", "cpu", "--quiet"],
        "scene": base + ["--scene", scene, "--data", data],
        "style": base + ["--scene", str(valid / S), "--data", str(valid / "colmap_bin"), "--style",
                         str(case / src if src.startswith("paint/") else case / "paint" / "painting.jpg")],
        "config": base + ["--scene", scene, "--data", data, "--config", str(target)],
        "weights": ["stylize", "--out", str(out), "--device", "cpu", "--quiet", "--iterations", "2", "--scene",
                    scene, "--data", data, "--vgg-weights", str(target)],
    }[cmd]
    rc, err = _run_cli(argv, capsys)
    _check(rc, err, culprit, problem, out)
    assert _hashes(case) == before  # inputs untouched


@pytest.mark.parametrize("name", sorted(FLAG_CASES))
def test_malformed_flag(valid, tmp_path, capsys, name):
    tail, culprit, problem = FLAG_CASES[name]
    out = tmp_path / "out"
    before = _hashes(valid)
    argv = ["stylize", "--out", str(out), "--vgg-weights", "random", "--device", "cpu", "--quiet",
            "--iterations", "2", "--set", "orbit_frames=1", "--scene", str(valid / S)]
    if tail in ("resume_empty", "resume_corrupt"):
        run = tmp_path / "run"
        run.mkdir()
        if tail == "resume_corrupt":
            (run / "checkpoint.pt").write_bytes(b"PK\x03\x04 not really a zip")
        before |= _hashes(run)
        argv = ["stylize", "--resume", str(run), "--quiet"]
        out = None
    elif tail[0] == "--data":
        argv += tail
    else:
        argv += ["--data", str(valid / "colmap_bin"), *tail]
    rc, err = _run_cli(argv, capsys)
    _check(rc, err, culprit, problem, out)
    assert _hashes(valid) | (_hashes(tmp_path / "run") if (tmp_path / "run").exists() else {}) == before


@pytest.mark.parametrize("name", sorted(JUDGE_CASES))
def test_malformed_judge_endpoint(tmp_path, capsys, monkeypatch, name):
    url, key, culprit, problem = JUDGE_CASES[name]
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    for r in ("a", "b"):
        _imwrite(tmp_path / r / "renders" / "view_000.png", np.zeros((16, 16, 3), np.uint8) + 100)
    _imwrite(tmp_path / "painting.png", np.zeros((16, 16, 3), np.uint8) + 50)
    out = tmp_path / "judged"
    argv = ["judge", "--a", str(tmp_path / "a"), "--b", str(tmp_path / "b"), "--models", "m", "--base-url", url,
            "--style", str(tmp_path / "painting.png"), "--out", str(out), "--quiet"]
    if key:
        argv += ["--api-key", key]
    rc, err = _run_cli(argv, capsys)
    _check(rc, err, culprit, problem, out)
    assert key is None or key not in err  # the key is never printed
