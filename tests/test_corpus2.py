"""A second corpus of awkward inputs, beyond tests/test_malformed_inputs.py: paths with spaces and non-ASCII names, a
read-only --out, --out inside --data (and --out the dataset itself), symlink loops in a dataset, 16-bit, grayscale
and RGBA paintings, EXIF-rotated photos and paintings, a 20000x20000 painting, PLY headers that declare 10^10
vertices, cameras with NaN or zero focal length. Each case ends in exactly one of: a correct run (exit 0, its
outputs there) or one line naming the file and the problem (exit 2, nothing left in --out). In every case the
inputs are unchanged (hashed before and after) and no temporary file is left.

The runs are the smallest there are (tests/test_malformed_inputs.py's fixture: a ~470-Gaussian scene, 4 views of
32x24, random VGG weights, 2 iterations, on the CPU)."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import struct
import subprocess
import sys
import tracemalloc
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from test_malformed_inputs import S, _hashes, _imwrite, valid  # noqa: F401 (the fixture of small valid inputs)
from _io_helpers import run_cli
from tlvg_warp.fileio import TEMP_MARK

REPO = Path(__file__).resolve().parents[1]
HUGE = 20000  # the large painting's side
HUGE_RSS_MAX = 3584 << 20  # bytes: OpenCV peaks near twice the 1.2 GB of decoded 8-bit pixels; the image as
# float32 at full size (what reading it unshrunk makes) would add 4.8 GB


def _base(out, *extra):
    return ["--out", str(out), "--vgg-weights", "random", "--device", "cpu", "--quiet", "--iterations", "2",
            "--set", "orbit_frames=1", "--set", "comparison_views=1", *extra]


def _stylize(scene, data, out, *extra):
    return ["stylize", "--scene", str(scene), "--data", str(data), *_base(out, *extra)]




def _no_temps(*roots):
    for r in roots:
        if Path(r).exists():
            assert not [p for p in Path(r).rglob(".*") if TEMP_MARK in p.name], r


def _refused(rc, err, culprit, problem, out):
    lines = err.strip().splitlines()
    assert rc == 2, (rc, err)
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert str(culprit) in lines[0] and problem in lines[0], (culprit, problem, lines[0])
    if out is not None:
        assert not Path(out).exists() or not any(Path(out).rglob("*")), sorted(Path(out).rglob("*"))


def _ran(rc, err, out):
    assert rc == 0, err
    assert (Path(out) / "stylized.ply").is_file() and (Path(out) / "metrics.json").is_file()


@pytest.fixture
def case(valid, tmp_path):
    """A private copy of the valid inputs."""
    root = tmp_path / "in"
    shutil.copytree(valid, root, symlinks=True)
    return root


# --- paths ----------------------------------------------------------------------------------------------------
def test_paths_with_spaces_and_non_ascii_names(valid, tmp_path, capsys):
    root = tmp_path / "my data" / "séance 絵 ☃"
    shutil.copytree(valid, root)
    paint = root / "paint" / "peinture à l'huile ü.png"
    shutil.copy(valid / "paint" / "painting.png", paint)
    before = _hashes(root)
    out = tmp_path / "résultats" / "run 1 ✓"
    rc, err = run_cli(_stylize(root / S, root / "colmap_bin", out, "--style", str(paint)), capsys)
    _ran(rc, err, out)
    assert json.loads((out / "metrics.json").read_text())  # outputs readable under the odd name
    assert _hashes(root) == before
    _no_temps(out)


def test_read_only_out(valid, tmp_path, capsys):
    out = tmp_path / "ro"
    out.mkdir()
    mounted = False
    if os.geteuid() == 0:  # root writes through permission bits: a read-only filesystem instead
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(out)],
                                 capture_output=True).returncode == 0
        if not mounted:
            pytest.skip("root, and no read-only tmpfs could be mounted")
    else:
        out.chmod(0o555)
    try:
        before = _hashes(valid)
        rc, err = run_cli(_stylize(valid / S, valid / "colmap_bin", out / "run"), capsys)
        _refused(rc, err, out, "", None)
        assert "writable" in err or "read-only" in err.lower(), err
        assert not (out / "run").exists() and _hashes(valid) == before
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(out)])
        else:
            out.chmod(0o755)


def test_out_inside_data_runs_and_leaves_the_dataset_alone(case, capsys):
    data = case / "colmap_bin"
    before = _hashes(case)
    out = data / "images" / "run"  # even inside the photos' folder
    rc, err = run_cli(_stylize(case / S, data, out), capsys)
    _ran(rc, err, out)
    after = {k: v for k, v in _hashes(case).items() if not k.startswith(str(out))}
    assert after == before  # every input file as it was, no file added beside them
    rc, err = run_cli(["reconstruct", str(data), "--out", str(case / "rec"), "--iterations", "2", "--device", "cpu",
                    "--quiet"], capsys)
    assert rc == 0, err  # the dataset still loads with a run folder inside it


@pytest.mark.parametrize("layout", ["inria", "colmap_bin"])
def test_out_is_the_dataset_itself_is_refused(case, capsys, layout):
    """--out DATA --overwrite would delete a run's files by name, and an INRIA dataset's cameras.json is one."""
    data = case / layout
    before = _hashes(case)
    rc, err = run_cli(["reconstruct", str(data), "--out", str(data), "--overwrite", "--iterations", "2", "--device",
                    "cpu", "--quiet"], capsys)
    _refused(rc, err, data, "input", None)
    assert _hashes(case) == before


def test_symlink_loops_in_the_dataset(case, capsys):
    imgs = case / "colmap_bin" / "images"
    (imgs / "loop").symlink_to(imgs, target_is_directory=True)  # a folder that contains itself
    (imgs / "a.png").symlink_to(imgs / "b.png")  # a.png -> b.png -> a.png
    (imgs / "b.png").symlink_to(imgs / "a.png")
    (case / "colmap_bin" / "sparse" / "up").symlink_to(case / "colmap_bin", target_is_directory=True)
    before = _hashes_nofollow(case)
    out = case.parent / "out"
    rc, err = run_cli(_stylize(case / S, case / "colmap_bin", out), capsys)
    _ran(rc, err, out)  # the model names view0..3; the loops are never followed
    rc, err = run_cli(["reconstruct", str(case / "llff"), "--out", str(case.parent / "rec"), "--iterations", "2",
                    "--device", "cpu", "--quiet"], capsys)
    assert rc == 0, err
    (case / "llff" / "images" / "x.png").symlink_to(case / "llff" / "images" / "x.png")  # a link to itself
    rc, err = run_cli(["reconstruct", str(case / "llff"), "--out", str(case.parent / "rec2"), "--iterations", "2",
                    "--device", "cpu", "--quiet"], capsys)
    assert rc in (0, 2) and len(err.strip().splitlines()) <= 1 and "Traceback" not in err, err
    if rc == 2:
        assert "x.png" in err or "llff" in err
    (case / "llff" / "images" / "x.png").unlink()
    assert _hashes_nofollow(case) == before


def _hashes_nofollow(root) -> dict:
    out = {}
    for dirpath, dirs, files in os.walk(root):  # os.walk does not follow links to folders
        for n in files + [d for d in dirs if os.path.islink(os.path.join(dirpath, d))]:
            p = Path(dirpath) / n
            if p.is_symlink():
                out[str(p)] = "->" + os.readlink(p)
            else:
                out[str(p)] = _file_hash(p)
    return out


# --- paintings ------------------------------------------------------------------------------------------------
def _painting_u8(valid):
    return cv2.imread(str(valid / "paint" / "painting.png"), cv2.IMREAD_COLOR)  # BGR uint8


@pytest.mark.parametrize("kind", ["16bit", "gray", "gray16", "rgba"])
def test_painting_pixel_formats(valid, tmp_path, capsys, kind):
    """Each runs, and the painting the run used (style.png) is the file's picture: 16-bit the same as its 8-bit
    source, gray as gray, RGBA composited onto white (computed here from the file's own pixels)."""
    from tlvg_warp.stylize.inputs import load_style

    bgr = _painting_u8(valid)
    f = tmp_path / f"painting_{kind}.png"
    if kind == "16bit":
        img, want = bgr.astype(np.uint16) * 257, bgr[..., ::-1] / 255.0
    elif kind in ("gray", "gray16"):
        g = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        img = g if kind == "gray" else g.astype(np.uint16) * 257
        want = np.repeat(g[..., None] / 255.0, 3, axis=2)
    else:
        h, w = bgr.shape[:2]
        alpha = np.tile(np.linspace(0, 255, w).astype(np.uint8), (h, 1))
        img = np.dstack([bgr, alpha])
        a = alpha[..., None] / 255.0
        want = bgr[..., ::-1] / 255.0 * a + (1 - a)
    assert cv2.imwrite(str(f), img)
    before = _file_hash(f)
    with pytest.warns(UserWarning) if kind in ("rgba", "gray", "gray16") else contextlib.nullcontext():
        got = load_style(f).numpy()
    np.testing.assert_allclose(got, want, atol=1.5 / 255)
    out = tmp_path / "out"
    rc, err = run_cli(_stylize(valid / S, valid / "colmap_bin", out, "--style", str(f)), capsys)
    _ran(rc, err, out)
    assert _file_hash(f) == before


def _exif_jpeg(path: Path, rgb_u8: np.ndarray, orientation: int):
    from PIL import Image

    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(rgb_u8).save(path, quality=95, exif=exif.tobytes())


def test_exif_rotated_photo_is_read_as_stored(case, capsys):
    """A photo with an EXIF rotation tag is read as its pixels are stored, as COLMAP reads it (the camera's
    width and height are the stored ones): the run works and its photos/ copy equals the stored pixels."""
    from PIL import Image

    view = case / "colmap_jpg" / "images" / "view1.jpg"
    stored = np.asarray(Image.open(case / "colmap_jpg" / "images" / "view1.jpg").convert("RGB"))
    _exif_jpeg(view, stored, 6)  # "rotate 90° clockwise to display"
    raw = np.asarray(Image.open(view).convert("RGB"))  # PIL does not apply the tag unless asked
    before = _hashes(case)
    out = case.parent / "out"
    rc, err = run_cli(_stylize(case / S, case / "colmap_jpg", out), capsys)
    _ran(rc, err, out)
    copy = cv2.imread(str(out / "photos" / "view_001.png"))[..., ::-1]
    assert copy.shape == raw.shape and np.abs(copy.astype(int) - raw).mean() < 2.0
    assert _hashes(case) == before


def test_exif_rotated_painting_runs(valid, tmp_path, capsys):
    from PIL import Image

    from tlvg_warp.stylize.inputs import load_style

    rgb = _painting_u8(valid)[..., ::-1].copy()
    f = tmp_path / "painting_rot.jpg"
    _exif_jpeg(f, rgb, 6)
    raw = np.asarray(Image.open(f).convert("RGB"))
    got = load_style(f).numpy()
    assert got.shape[:2] == raw.shape[:2]  # read as stored, like every image the project reads
    before = _file_hash(f)
    out = tmp_path / "out"
    rc, err = run_cli(_stylize(valid / S, valid / "colmap_bin", out, "--style", str(f)), capsys)
    _ran(rc, err, out)
    assert _file_hash(f) == before


def _constant_png(path: Path, w: int, h: int, rgb=(200, 120, 40)):
    """A valid RGB PNG of one colour, streamed row by row (the test never holds the pixels)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    row = b"\0" + bytes(rgb) * w
    z = zlib.compressobj(9)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)))
        buf = b""
        for _ in range(h):
            buf += z.compress(row)
            if len(buf) > 1 << 20:
                f.write(chunk(b"IDAT", buf))
                buf = b""
        buf += z.flush()
        f.write(chunk(b"IDAT", buf) + chunk(b"IEND", b""))


def test_20000px_painting_runs_in_bounded_memory(valid, tmp_path):
    """Run in its own process so its peak memory (ru_maxrss from wait4) is its own: bounded by the decoded 8-bit
    file plus the working copies, far below the float32 image of the full size."""
    f = tmp_path / "huge.png"
    _constant_png(f, HUGE, HUGE)
    before = _file_hash(f)
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen([sys.executable, "-m", "tlvg_warp", *_stylize(valid / S, valid / "colmap_bin", out,
                                                                         "--style", str(f))],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=REPO)
    _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    err = p.stderr.read().decode()
    assert p.returncode == 0, err
    assert usage.ru_maxrss * 1024 < HUGE_RSS_MAX, f"peak {usage.ru_maxrss / 2**20:.2f} GiB"
    assert (out / "stylized.ply").is_file()
    style = cv2.imread(str(out / "style.png"))[..., ::-1]  # the painting the run used: the file's colour
    assert np.abs(style.reshape(-1, 3).mean(0) - (200, 120, 40)).max() < 2
    assert _file_hash(f) == before


# --- scenes and cameras ---------------------------------------------------------------------------------------
def _ply_header(fmt: str, count: int, props=("x", "y", "z")) -> bytes:
    return (f"ply\nformat {fmt} 1.0\nelement vertex {count}\n" + "".join(f"property float {p}\n" for p in props)
            + "end_header\n").encode()


def _gaussian_props():
    return ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


@pytest.mark.parametrize("kind", ["binary", "ascii", "big_endian", "compressed"])
def test_ply_header_declaring_1e10_vertices_fails_fast(case, capsys, kind):
    """One line naming the file; tracemalloc (numpy's allocations included) sees no allocation near what the
    header claims."""
    f = case / S
    n = 10 ** 10
    if kind == "compressed":
        body = (b"ply\nformat binary_little_endian 1.0\nelement chunk 1\n"
                + b"".join(f"property float {p}\n".encode() for p in
                           ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y",
                            "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"))
                + f"element vertex {n}\n".encode()
                + b"".join(f"property uint {p}\n".encode() for p in
                           ("packed_position", "packed_rotation", "packed_scale", "packed_color"))
                + b"end_header\n" + bytes(48 + 16 * 4))
    else:
        fmt = {"binary": "binary_little_endian", "ascii": "ascii", "big_endian": "binary_big_endian"}[kind]
        body = _ply_header(fmt, n, _gaussian_props())
        body += b"0 " * 17 * 3 + b"\n" if kind == "ascii" else bytes(4 * 17 * 3)
    f.write_bytes(body)
    before = _hashes(case)
    out = case.parent / "out"
    tracemalloc.start()
    try:
        rc, err = run_cli(_stylize(f, case / "colmap_bin", out), capsys)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    _refused(rc, err, f, "", out)
    assert str(n) in err or "truncated" in err or "vertices" in err, err
    assert peak < 256 << 20, f"{peak / 2**20:.0f} MiB allocated"
    assert _hashes(case) == before


def _colmap_cameras_bin(path: Path, fx, fy):
    b = bytearray(path.read_bytes())
    # num_cameras (u64), then camera_id (i32), model (i32), width (u64), height (u64), params (f64 x 4)
    off = 8 + 4 + 4 + 8 + 8
    b[off:off + 16] = struct.pack("<dd", fx, fy)
    path.write_bytes(bytes(b))


CAMERA_CASES = {
    "colmap_nan_focal": ("colmap_bin", lambda d: _colmap_cameras_bin(d / "sparse/0/cameras.bin", float("nan"), 30.0),
                         "colmap_bin/sparse/0/cameras.bin"),
    "colmap_zero_focal": ("colmap_bin", lambda d: _colmap_cameras_bin(d / "sparse/0/cameras.bin", 0.0, 0.0),
                          "colmap_bin/sparse/0/cameras.bin"),
    "colmap_txt_zero_focal": ("colmap_txt", lambda d: _txt_focal(d / "sparse/0/cameras.txt", "0"),
                              "colmap_txt/sparse/0/cameras.txt"),
    "colmap_txt_nan_focal": ("colmap_txt", lambda d: _txt_focal(d / "sparse/0/cameras.txt", "nan"),
                             "colmap_txt/sparse/0/cameras.txt"),
    "inria_zero_fx": ("inria", lambda d: _inria_edit(d / "cameras.json", fx=0.0), "inria/cameras.json"),
    "inria_nan_fy": ("inria", lambda d: _inria_edit(d / "cameras.json", fy=float("nan")), "inria/cameras.json"),
    "blender_zero_fov": ("blender", lambda d: _json(d / "transforms.json", camera_angle_x=0.0),
                         "blender/transforms.json"),
    "blender_nan_fov": ("blender", lambda d: _json(d / "transforms.json", camera_angle_x=float("nan")),
                        "blender/transforms.json"),
    "llff_zero_focal": ("llff", lambda d: _llff_focal(d / "poses_bounds.npy", 0.0), "llff/poses_bounds.npy"),
}


def _txt_focal(path: Path, v: str):
    lines = path.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln and not ln.startswith("#"))
    parts = lines[i].split()
    parts[4] = v  # CAMERA_ID MODEL WIDTH HEIGHT fx fy cx cy
    lines[i] = " ".join(parts)
    path.write_text("\n".join(lines) + "\n")


def _inria_edit(path: Path, **kw):
    cams = json.loads(path.read_text())
    cams[1].update(kw)
    path.write_text(json.dumps(cams))


def _json(path: Path, **kw):
    d = json.loads(path.read_text())
    d.update(kw)
    path.write_text(json.dumps(d))


def _llff_focal(path: Path, v):
    a = np.load(path)
    a[2, 14] = v  # [3x5 pose | h w f] row-major: the focal of view 2
    np.save(path, a)


@pytest.mark.parametrize("name", sorted(CAMERA_CASES))
def test_cameras_with_nan_or_zero_focal_length(case, capsys, name):
    layout, corrupt, culprit = CAMERA_CASES[name]
    corrupt(case / layout)
    before = _hashes(case)
    out = case.parent / "out"
    rc, err = run_cli(["reconstruct", str(case / layout), "--out", str(out), "--iterations", "2", "--device", "cpu",
                    "--quiet"], capsys)
    _refused(rc, err, case / culprit, "", out)
    assert any(w in err.lower() for w in ("focal", "fx", "fy", "camera_angle", "nan", "intrinsic")), err
    assert _hashes(case) == before


def _file_hash(f: Path) -> str:
    import hashlib

    return hashlib.sha256(Path(f).read_bytes()).hexdigest()
