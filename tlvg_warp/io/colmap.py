"""COLMAP sparse models (binary ``.bin`` and text ``.txt``): cameras, images, points3D, and OpenCV
undistortion of the radial models to a pinhole.

Layouts follow COLMAP's ``src/colmap/scene/reconstruction_io.cc``. Pixel coordinates follow COLMAP (and
SPEC §1): the upper-left pixel's center is at (0.5, 0.5). OpenCV puts it at (0, 0), so intrinsics are
shifted by half a pixel around every OpenCV call."""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError

# model id -> (name, number of params). Only these five are supported; the ids of the others are listed
# so the error can name them.
MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
          4: ("OPENCV", 8)}
_UNSUPPORTED = {5: "OPENCV_FISHEYE", 6: "FULL_OPENCV", 7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE",
                9: "RADIAL_FISHEYE", 10: "THIN_PRISM_FISHEYE"}
_BY_NAME = {name: (mid, n) for mid, (name, n) in MODELS.items()}
SUPPORTED = ", ".join(name for name, _ in MODELS.values())


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # [n_params] float64, COLMAP order

    def intrinsics(self):
        """(K [3,3] float64 in COLMAP pixel convention, OpenCV distortion (k1,k2,p1,p2) or None)."""
        p = self.params
        if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = p[0]
            cx, cy = p[1], p[2]
        else:
            fx, fy, cx, cy = p[:4]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
        dist = {"SIMPLE_RADIAL": lambda: [p[3], 0, 0, 0], "RADIAL": lambda: [p[3], p[4], 0, 0],
                "OPENCV": lambda: list(p[4:8])}.get(self.model, lambda: None)()
        if dist is None or not np.any(dist):
            return K, None
        return K, np.asarray(dist, np.float64)


@dataclass
class ColmapImage:
    id: int
    qvec: np.ndarray  # [4] w, x, y, z (world -> camera rotation)
    tvec: np.ndarray  # [3]
    camera_id: int
    name: str
    xys: np.ndarray = field(repr=False)  # [M, 2] observed keypoints (COLMAP pixel convention)
    point3d_ids: np.ndarray = field(repr=False)  # [M] int64, -1 when the keypoint has no 3D point

    def world_to_camera(self) -> np.ndarray:  # [4, 4]
        m = np.eye(4)
        m[:3, :3] = qvec_to_rotmat(self.qvec)
        m[:3, 3] = self.tvec
        return m


@dataclass
class ColmapPoints:
    ids: np.ndarray  # [P] int64
    xyz: np.ndarray  # [P, 3] float64
    rgb: np.ndarray  # [P, 3] uint8
    error: np.ndarray  # [P] float64
    track_offsets: np.ndarray  # [P+1]; point p's track is [track_offsets[p], track_offsets[p+1])
    track_image_ids: np.ndarray  # [T] int32
    track_point2d_idx: np.ndarray  # [T] int32


def qvec_to_rotmat(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _model(mid_or_name, path):
    if mid_or_name in MODELS:
        return MODELS[mid_or_name]
    if mid_or_name in _BY_NAME:
        return mid_or_name, _BY_NAME[mid_or_name][1]
    label = _UNSUPPORTED.get(mid_or_name, mid_or_name)
    raise InputError(f"unsupported camera model {label!r}; supported: {SUPPORTED}", path)


class _Buf:
    """A bounds-checked cursor over a binary file (truncation becomes an InputError, not struct.error)."""

    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def need(self, n, what):
        if self.pos + n > len(self.data):
            raise InputError(f"truncated COLMAP file: ends inside {what} (byte {len(self.data)})", self.path)

    def unpack(self, fmt, what):
        n = struct.calcsize(fmt)
        self.need(n, what)
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += n
        return out

    def array(self, dtype, count, what):
        dtype = np.dtype(dtype)
        self.need(dtype.itemsize * count, what)
        out = np.frombuffer(self.data, dtype, count, self.pos)
        self.pos += dtype.itemsize * count
        return out

    def done(self):
        if self.pos != len(self.data):
            raise InputError(f"corrupt COLMAP file: {len(self.data) - self.pos} unexpected trailing bytes", self.path)


def _require(path: Path):
    if not path.is_file():
        raise InputError("file does not exist", path)


# --- binary -------------------------------------------------------------------------------------------------
def _cameras_bin(path):
    b, out = _Buf(path), {}
    (n,) = b.unpack("<Q", "the camera count")
    for _ in range(n):
        cid, mid, w, h = b.unpack("<iiQQ", "a camera record")
        name, npar = _model(mid, path)
        out[cid] = ColmapCamera(cid, name, w, h, b.array("<f8", npar, "camera params").copy())
    b.done()
    return out


def _images_bin(path):
    b, out = _Buf(path), {}
    (n,) = b.unpack("<Q", "the image count")
    obs = np.dtype([("xy", "<f8", 2), ("id", "<i8")])
    for _ in range(n):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = b.unpack("<i7di", "an image record")
        end = b.data.find(b"\0", b.pos)
        if end < 0:
            raise InputError("truncated COLMAP file: ends inside an image name", path)
        name = b.data[b.pos:end].decode("utf-8", "replace")
        b.pos = end + 1
        (m,) = b.unpack("<Q", "a keypoint count")
        pts = b.array(obs, m, f"the keypoints of {name}")
        out[iid] = ColmapImage(iid, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), cid, name,
                               pts["xy"].copy(), pts["id"].copy())
    b.done()
    return out


_POINT_HEAD = 51  # id u64, xyz 3xf64, rgb 3xu8, error f64, track length u64


def _points_bin(path):
    b = _Buf(path)
    (n,) = b.unpack("<Q", "the point count")
    offs, lens = np.empty(n, np.int64), np.empty(n, np.int64)  # [P]
    pos, size, data = 8, len(b.data), b.data
    for i in range(n):  # records vary in length with the track, so only their starts need a sequential walk
        if pos + _POINT_HEAD > size:
            raise InputError(f"truncated COLMAP file: ends inside point {i} of {n}", path)
        offs[i] = pos
        lens[i] = struct.unpack_from("<Q", data, pos + 43)[0]
        pos += _POINT_HEAD + 8 * int(lens[i])
    if pos != size:
        what = "ends inside a point track" if pos > size else f"{size - pos} unexpected trailing bytes"
        raise InputError(f"corrupt COLMAP file: {what}", path)
    u8 = np.frombuffer(data, np.uint8)
    head = u8[offs[:, None] + np.arange(_POINT_HEAD)]  # [P, 51] the fixed-size part of every record
    starts = np.zeros(n + 1, np.int64)
    np.cumsum(lens, out=starts[1:])
    # byte offset of every track element: record start + 51 + 8 * (index within its track)
    within = np.arange(starts[-1]) - np.repeat(starts[:-1], lens)  # [T]
    track = u8[(np.repeat(offs + _POINT_HEAD, lens) + 8 * within)[:, None] + np.arange(8)]  # [T, 8]
    track = track.view("<i4").reshape(-1, 2)  # [T, 2] image id, point2D index
    return ColmapPoints(head[:, 0:8].copy().view("<u8")[:, 0].astype(np.int64),
                        head[:, 8:32].copy().view("<f8"), head[:, 32:35].copy(),
                        head[:, 35:43].copy().view("<f8")[:, 0], starts,
                        track[:, 0].copy(), track[:, 1].copy())


# --- text ---------------------------------------------------------------------------------------------------
def _lines(path):
    """(line number, stripped line) of the non-comment lines."""
    text = path.read_text(encoding="utf-8", errors="replace").splitlines()
    return [(i + 1, s.strip()) for i, s in enumerate(text) if s.strip() and not s.lstrip().startswith("#")]


def _parse(path, lineno, fn):
    try:
        return fn()
    except (ValueError, IndexError) as e:
        raise InputError(f"corrupt COLMAP text at line {lineno}: {e}", path) from None


def _cameras_txt(path):
    out = {}
    for ln, s in _lines(path):
        w = s.split()
        name, npar = _model(w[1] if len(w) > 1 else "?", path)
        cam = _parse(path, ln, lambda: ColmapCamera(int(w[0]), name, int(w[2]), int(w[3]),
                                                    np.array(w[4:], np.float64)))
        if cam.params.size != npar:
            raise InputError(f"line {ln}: {name} needs {npar} params, got {cam.params.size}", path)
        out[cam.id] = cam
    return out


def _images_txt(path):
    # Two lines per image; the keypoint line may be empty, so walk the raw lines after the header comments.
    raw = path.read_text(encoding="utf-8", errors="replace").splitlines()
    body = [(i + 1, s) for i, s in enumerate(raw) if not s.startswith("#")]
    while body and not body[-1][1].strip():
        body.pop()
    out = {}
    for k in range(0, len(body), 2):
        ln, head = body[k]
        pts_line = body[k + 1][1] if k + 1 < len(body) else ""
        w = head.split(maxsplit=9)

        def build():
            pts = np.array(pts_line.split(), np.float64).reshape(-1, 3)
            return ColmapImage(int(w[0]), np.array(w[1:5], np.float64), np.array(w[5:8], np.float64),
                               int(w[8]), w[9], pts[:, :2].copy(), pts[:, 2].astype(np.int64))
        img = _parse(path, ln, build)
        out[img.id] = img
    return out


def _points_txt(path):
    ids, xyz, rgb, err, lens, tracks = [], [], [], [], [], []
    for ln, s in _lines(path):
        w = s.split()

        def row():
            t = np.array(w[8:], np.int64).reshape(-1, 2)
            return int(w[0]), [float(v) for v in w[1:4]], [int(v) for v in w[4:7]], float(w[7]), t
        i, p, c, e, t = _parse(path, ln, row)
        ids.append(i), xyz.append(p), rgb.append(c), err.append(e), lens.append(len(t)), tracks.append(t)
    starts = np.zeros(len(ids) + 1, np.int64)
    np.cumsum(lens, out=starts[1:])
    t = np.concatenate(tracks) if tracks else np.zeros((0, 2), np.int64)
    return ColmapPoints(np.array(ids, np.int64), np.array(xyz, np.float64).reshape(-1, 3),
                        np.array(rgb, np.uint8).reshape(-1, 3), np.array(err, np.float64), starts,
                        t[:, 0].astype(np.int32), t[:, 1].astype(np.int32))


def read_cameras(path) -> dict[int, ColmapCamera]:
    path = Path(path)
    _require(path)
    return _cameras_bin(path) if path.suffix == ".bin" else _cameras_txt(path)


def read_images(path) -> dict[int, ColmapImage]:
    path = Path(path)
    _require(path)
    return _images_bin(path) if path.suffix == ".bin" else _images_txt(path)


def read_points3d(path) -> ColmapPoints:
    path = Path(path)
    _require(path)
    return _points_bin(path) if path.suffix == ".bin" else _points_txt(path)


def find_model(folder) -> tuple[Path, str] | None:
    """(model folder, '.bin' or '.txt') for ``folder/sparse/0``, ``folder/sparse`` or ``folder`` itself,
    when it holds cameras and images files; None otherwise."""
    folder = Path(folder)
    for d in (folder / "sparse" / "0", folder / "sparse", folder):
        for ext in (".bin", ".txt"):
            if (d / f"cameras{ext}").is_file() and (d / f"images{ext}").is_file():
                return d, ext
    return None


# --- undistortion -------------------------------------------------------------------------------------------
_HALF = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]])  # COLMAP pixel convention -> OpenCV


def undistortion(K, dist, width, height, tables=True):
    """Pinhole intrinsics and remap tables for an image of ``width x height`` taken with (K, dist).

    ``alpha=0`` in getOptimalNewCameraMatrix keeps only valid pixels (no black border), at the same size.
    Returns (new K [3,3] in COLMAP pixel convention, map_x [H,W] float32, map_y [H,W] float32); the
    maps are None when ``tables`` is False (they cost 8 bytes a pixel, so datasets build them per photo)."""
    K_cv = _HALF @ K
    new_cv, _ = cv2.getOptimalNewCameraMatrix(K_cv, dist, (width, height), 0, (width, height))
    new_K = np.linalg.solve(_HALF, new_cv)
    if not tables:
        return new_K, None, None
    map_x, map_y = cv2.initUndistortRectifyMap(K_cv, dist, None, new_cv, (width, height), cv2.CV_32FC1)
    return new_K, map_x, map_y


def undistort_image(img, map_x, map_y):
    """Resample ``img`` [H,W,C] through the tables from :func:`undistortion` (bilinear)."""
    return cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
