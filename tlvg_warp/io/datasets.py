"""Posed photos from the common layouts, as OpenCV-convention Cameras (SPEC §1).

Detected from the folder's contents, in this order:
  COLMAP   sparse/0 or sparse/ (cameras + images, .bin or .txt), photos in images/ (or images_N/)
  LLFF     poses_bounds.npy (N x 17); photos in images/ or images_N/, sorted by file name
  Blender  transforms_{train,val,test}.json or transforms.json (OpenGL camera axes)
  INRIA    cameras.json written by the 3DGS trainer next to its point cloud

Every camera is stated at some size by its source (COLMAP/LLFF: the original photos) and rescaled to the
photo file actually found; radially distorted cameras are undistorted to pinholes (colmap.undistortion);
``downscale`` then resizes with INTER_AREA. Sizes are read from the file headers up front, so a missing,
unreadable or wrongly sized photo is reported by load_dataset, not halfway through a run.
"""
from __future__ import annotations

import json
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from plyfile import PlyData

from ..errors import InputError
from ..types import Camera
from . import colmap
from .images import IMAGE_EXTS, composite, image_size, list_images, read_image

SIZE_SLACK_PX = 1.0  # a downscaled folder may round (ceil/floor) each side; more than that is a mismatch
_FOLDERS = ("images", "images_2", "images_4", "images_8")


class Dataset:
    """Cameras, names, lazily decoded photos (cached) and optional SfM points."""

    def __init__(self, root, cameras, names, load_fn, points=None, kind="", bounds=None, threaded=True):
        self.root = Path(root)
        self.cameras: list[Camera] = list(cameras)
        self.names: list[str] = list(names)
        self.points = points  # (xyz [P,3], rgb [P,3]) float32 torch, rgb in [0,1]; or None
        self.kind = kind
        self.bounds = bounds  # [N, 2] LLFF near/far per view, else None
        self._load = load_fn  # index -> float32 numpy [H, W, 3]
        self.threaded = threaded  # load_fn may run in several threads at once (file decoding; not a renderer)
        self._cache: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.cameras)

    def __repr__(self) -> str:
        c = self.cameras[0] if self.cameras else None
        size = f"{c.width}x{c.height}" if c else "-"
        return f"Dataset({self.kind} {self.root}, {len(self)} views, {size})"

    def image(self, i: int) -> torch.Tensor:
        """float32 [H, W, 3] in [0, 1]; cached (shared: do not modify it in place)."""
        if i not in self._cache:
            cam = self.cameras[i]
            img = np.ascontiguousarray(self._load(i), dtype=np.float32)
            if img.shape != (cam.height, cam.width, 3):
                raise InputError(f"image {self.names[i]} is {img.shape[1]}x{img.shape[0]}, "
                                 f"its camera says {cam.width}x{cam.height}", self.root)
            self._cache[i] = torch.from_numpy(np.clip(img, 0.0, 1.0))
        return self._cache[i]

    def images(self) -> list:
        """Every view's ``image(i)``, decoded in a few threads (OpenCV releases the GIL: a stylization's setup
        read fern's 20 PNGs one by one); a bad file raises as ``image`` would, the first in view order."""
        if not self.threaded:  # e.g. the demo's photos are renders: Warp launches are not thread-safe
            return [self.image(i) for i in range(len(self.cameras))]
        with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
            futures = [pool.submit(self.image, i) for i in range(len(self.cameras))]
            return [f.result() for f in futures]


def dataset_background(ds) -> tuple:
    """The RGB background a dataset's scene is rendered over (fitted and stylized alike): the dataset's own
    ``background`` where it has one (the built-in demo's white), white for a Blender (NeRF synthetic) scene, whose
    objects stand on an empty white backdrop, black for photos of real places."""
    bg = getattr(ds, "background", None)
    if bg is None:
        bg = (1.0, 1.0, 1.0) if getattr(ds, "kind", "") == "blender" else (0.0, 0.0, 0.0)
    return tuple(float(v) for v in bg)


@dataclass
class _View:
    """One photo as its source states it, before fitting to the file on disk."""

    name: str
    path: Path
    world_to_camera: np.ndarray  # [4, 4] OpenCV axes
    K: np.ndarray  # [3, 3] at ``size`` (pixel centers at +0.5)
    size: tuple  # (W, H) the size K refers to
    dist: np.ndarray | None = None  # OpenCV (k1, k2, p1, p2), None = pinhole
    source: Path | None = None  # the file the pose came from, for error messages
    intrinsics: Path | None = None  # the file the focal length came from, when not ``source`` (COLMAP's cameras)


def _image_folder(root: Path, images, downscale):
    """(folder, remaining resize factor)."""
    if images is not None:
        folder = root / images
        if not folder.is_dir():
            raise InputError("image folder does not exist", folder)
        return folder, downscale
    if downscale and (root / f"images_{int(downscale)}").is_dir() and float(downscale) == int(downscale):
        return root / f"images_{int(downscale)}", None  # pre-shrunk copies, as LLFF and 3DGS ship them
    for name in _FOLDERS:
        if (root / name).is_dir():
            return root / name, downscale
    raise InputError(f"no image folder ({', '.join(_FOLDERS)})", root)


def _fit(view: _View, remap_cache: dict):
    """Camera for the photo file as found (rescaled, undistorted); returns (Camera, remap args or None)."""
    w, h = image_size(view.path)
    W, H = view.size
    s = w / W
    if abs(H * s - h) > SIZE_SLACK_PX:
        raise InputError(f"image is {w}x{h}, which is not a scaled copy of the {W}x{H} its camera "
                         f"describes (inconsistent size)", view.path)
    fx, fy = float(view.K[0, 0]), float(view.K[1, 1])
    if not (np.isfinite(view.K).all() and fx > 0 and fy > 0):
        raise InputError(f"view {view.name}: focal length fx={fx}, fy={fy} (it must be a finite positive number; "
                         "corrupt camera intrinsics?)", view.intrinsics or view.source or view.path)
    K = np.diag([w / W, h / H, 1.0]) @ view.K
    remap = None
    if view.dist is not None:
        key = (K.tobytes(), view.dist.tobytes(), w, h)
        if key not in remap_cache:  # new K only; the tables themselves are built when the photo is read
            new_K, _, _ = colmap.undistortion(K, view.dist, w, h, tables=False)
            remap_cache[key] = new_K
        remap, K = (K, view.dist, w, h), remap_cache[key]
    try:
        cam = Camera(torch.from_numpy(view.world_to_camera.copy()), K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h,
                     name=view.name)
    except InputError as e:  # non-finite pose, non-positive focal: blame the file the camera came from
        raise InputError(f"view {view.name}: {e}", view.source or view.path) from None
    return cam, remap


def _finish(root, views, kind, downscale, split, holdout_every, background, points=None, bounds=None):
    if not views:
        raise InputError("dataset has no views", root)
    order = sorted(range(len(views)), key=lambda i: views[i].name)
    if split is not None:
        if split not in ("train", "test"):
            raise InputError(f"split must be None, 'train' or 'test', got {split!r}")
        # LLFF convention: every holdout_every-th view (0, 8, 16, ...) of the name-sorted list is held out
        order = [i for k, i in enumerate(order) if (k % holdout_every == 0) == (split == "test")]
    views = [views[i] for i in order]
    bounds = None if bounds is None else bounds[order]
    if downscale is not None and not downscale > 0:
        raise InputError(f"downscale must be positive, got {downscale}")
    cache, cams, remaps, scale = {}, [], [], None
    for v in views:
        cam, remap = _fit(v, cache)
        # every photo of a dataset is at one scale of its camera (images/ full size, images_4/ a quarter): a photo
        # at another scale is a stray file, not a resized copy
        scale = scale or cam.width / v.size[0]
        want = (round(v.size[0] * scale), round(v.size[1] * scale))
        if max(abs(cam.width - want[0]), abs(cam.height - want[1])) > SIZE_SLACK_PX:
            raise InputError(f"image is {cam.width}x{cam.height}, but its camera says {v.size[0]:g}x{v.size[1]:g} and "
                             f"the other photos are at {scale:g} of their camera size ({want[0]}x{want[1]} here)", v.path)
        cams.append(cam.scaled(downscale) if downscale and downscale != 1 else cam)
        remaps.append(remap)

    def load(i):
        img = composite(read_image(views[i].path), background)  # [h, w, 3]
        h, w = img.shape[:2]
        if (w, h) != image_size(views[i].path):
            raise InputError("decoded size differs from the header", views[i].path)
        if remaps[i] is not None:
            _, mx, my = colmap.undistortion(*remaps[i])
            img = colmap.undistort_image(img, mx, my)
        c = cams[i]
        if (c.width, c.height) != (w, h):
            img = cv2.resize(img, (c.width, c.height), interpolation=cv2.INTER_AREA)
        return img

    return Dataset(root, cams, [v.name for v in views], load, points, kind, bounds)


def _points(xyz, rgb_u8):
    return (torch.from_numpy(np.asarray(xyz, np.float32)),
            torch.from_numpy(np.asarray(rgb_u8, np.float32) / 255.0))


# --- COLMAP -----------------------------------------------------------------------------------------------
def _colmap_views(root, model_dir, ext, folder):
    cams = colmap.read_cameras(model_dir / f"cameras{ext}")
    imgs = colmap.read_images(model_dir / f"images{ext}")
    views = []
    for im in imgs.values():
        if im.camera_id not in cams:
            raise InputError(f"image {im.name} refers to camera {im.camera_id}, which is not in cameras{ext}",
                             model_dir / f"images{ext}")
        c = cams[im.camera_id]
        K, dist = c.intrinsics()
        views.append(_View(im.name, folder / im.name, im.world_to_camera(), K, (c.width, c.height), dist,
                           model_dir / f"images{ext}", model_dir / f"cameras{ext}"))
    pfile = model_dir / f"points3D{ext}"
    pts = colmap.read_points3d(pfile) if pfile.is_file() else None
    return views, (None if pts is None else _points(pts.xyz, pts.rgb))


# --- LLFF -------------------------------------------------------------------------------------------------
def llff_to_opencv(poses: np.ndarray) -> np.ndarray:
    """[N, 3, 5] LLFF rows -> [N, 4, 4] world_to_camera in OpenCV axes.

    LLFF's camera-to-world columns are the camera's [down, right, backwards] axes and its center; OpenCV's
    are [right, down, forward]."""
    R = poses[:, :, :3]
    c2w = np.tile(np.eye(4), (len(poses), 1, 1))
    c2w[:, :3, :3] = np.stack([R[:, :, 1], R[:, :, 0], -R[:, :, 2]], axis=2)
    c2w[:, :3, 3] = poses[:, :, 3]
    return np.linalg.inv(c2w)


def _llff_views(root, folder):
    pb = root / "poses_bounds.npy"
    try:
        arr = np.load(pb, allow_pickle=False)
    except Exception as e:  # numpy raises several types for a damaged file
        raise InputError(f"unreadable .npy ({type(e).__name__})", pb) from None
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise InputError(f"expected an N x 17 array, got shape {list(arr.shape)}", pb)
    nbad = int((~np.isfinite(arr)).sum())
    if nbad:
        raise InputError(f"{nbad} NaN/infinite values", pb)
    files = list_images(folder)
    if len(files) != len(arr):
        raise InputError(f"{len(arr)} poses but {len(files)} images in {folder.name}/ (camera count mismatch)", pb)
    poses = arr[:, :15].reshape(-1, 3, 5).astype(np.float64)  # [N, 3, 5]
    w2c = llff_to_opencv(poses)
    # The photos are raw captures. When COLMAP's cameras.bin describes the same camera (one camera, same
    # size and focal), take its principal point and radial distortion so the photos get undistorted;
    # otherwise LLFF's own model: focal from hwf, centered principal point.
    cam = _llff_colmap_camera(root, poses)
    views = []
    for i, f in enumerate(files):
        H, W, foc = poses[i, :, 4]
        K, dist = (cam.intrinsics() if cam is not None else
                   (np.array([[foc, 0, W / 2], [0, foc, H / 2], [0, 0, 1]]), None))
        views.append(_View(f.name, f, w2c[i], K, (W, H), dist, pb))
    # SfM points: LLFF's imgs2poses writes poses_bounds in COLMAP's world frame (recentring and rescaling
    # happen later, inside NeRF's loader), so points3D.bin lines up as is. Checked on fern: all 10,091
    # points are in front of every camera and 96-99% project inside each view (tests/test_io_real.py).
    points = None
    for d in (root / "sparse" / "0", root / "sparse"):
        if (d / "points3D.bin").is_file() or (d / "points3D.txt").is_file():
            p = colmap.read_points3d(d / ("points3D.bin" if (d / "points3D.bin").is_file() else "points3D.txt"))
            points = _points(p.xyz, p.rgb)
            break
    return views, points, arr[:, 15:17].astype(np.float64)


FOCAL_MATCH = 0.01  # relative focal difference under which cameras.bin is taken to be the LLFF camera


def _llff_colmap_camera(root, poses):
    for d in (root / "sparse" / "0", root / "sparse"):
        for ext in (".bin", ".txt"):
            if (d / f"cameras{ext}").is_file():
                cams = list(colmap.read_cameras(d / f"cameras{ext}").values())
                H, W, f = poses[0, :, 4]
                if len(cams) == 1 and (cams[0].width, cams[0].height) == (round(W), round(H)):
                    if abs(cams[0].intrinsics()[0][0, 0] / f - 1) < FOCAL_MATCH:
                        return cams[0]
                return None
    return None


def read_inria_cameras(path) -> tuple[list, list]:
    """An INRIA cameras.json (the 3DGS trainer's) -> (names, [Camera]); one-line errors naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError("missing file", path)
    data = _read_json(path)
    if not isinstance(data, list) or not data:
        raise InputError("expected a non-empty list of cameras", path)
    names, cams = [], []
    for name, w2c, fx, fy, w, h in inria_camera_entries(data, path):
        cams.append(Camera(torch.from_numpy(w2c), fx, fy, w / 2, h / 2, int(w), int(h), name=name))
        names.append(name)
    return names, cams


# --- NeRF / Blender transforms ------------------------------------------------------------------------------
def _read_json(path):
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"corrupt JSON ({e.__class__.__name__}: {str(e)[:80]})", path) from None
    except OSError as e:
        raise InputError(f"unreadable ({e.__class__.__name__})", path) from None


def _blender_intrinsics(get, w, h):
    """(K, W, H) from instant-ngp keys (fl_x, cx, w, ...) or NeRF's camera_angle_x; defaults: file size."""
    W, H = float(get("w", w)), float(get("h", h))
    if get("fl_x") is not None:
        fx = float(get("fl_x"))
        fy = float(get("fl_y", fx))
    elif get("camera_angle_x") is not None:
        ax, ay = float(get("camera_angle_x")), get("camera_angle_y")
        if not 0 < ax < np.pi or (ay is not None and not 0 < float(ay) < np.pi):
            raise ValueError("camera_angle_x/y must be in (0, pi) radians")
        fx = 0.5 * W / np.tan(0.5 * ax)
        fy = 0.5 * H / np.tan(0.5 * float(ay)) if ay is not None else fx
    else:
        raise ValueError("no camera_angle_x or fl_x")
    K = np.array([[fx, 0, float(get("cx", W / 2))], [0, fy, float(get("cy", H / 2))], [0, 0, 1]])
    return K, W, H


def _blender_views(root, files):
    views = []
    for jf in files:
        meta = _read_json(jf)
        frames = meta.get("frames") if isinstance(meta, dict) else None
        if not isinstance(frames, list):
            raise InputError("no 'frames' list", jf)
        for k, fr in enumerate(frames):
            try:
                rel = fr["file_path"]
                c2w = np.asarray(fr["transform_matrix"], np.float64)
            except (KeyError, TypeError, ValueError):
                raise InputError(f"frame {k} lacks file_path or a valid transform_matrix", jf) from None
            if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
                raise InputError(f"frame {k}: transform_matrix must be a finite 4x4", jf)
            path = (jf.parent / rel).resolve()
            if path.suffix.lower() not in IMAGE_EXTS:
                path = path.with_name(path.name + ".png")  # NeRF synthetic omits the extension
            w, h = image_size(path)
            get = lambda key, default=None: fr.get(key, meta.get(key, default))  # noqa: E731 per-frame wins
            try:
                K, W, H = _blender_intrinsics(get, w, h)
            except (TypeError, ValueError) as e:
                raise InputError(f"frame {k}: bad camera intrinsics ({e})", jf) from None
            c2w[:3, 1:3] *= -1  # OpenGL camera axes (y up, z backwards) -> OpenCV (y down, z forward)
            try:
                name = path.relative_to(root.resolve()).as_posix()
            except ValueError:
                name = path.name
            views.append(_View(name, path, np.linalg.inv(c2w), K, (W, H), source=jf))
    return views


# --- INRIA cameras.json -----------------------------------------------------------------------------------
def inria_camera_entries(data, path) -> list:
    """The INRIA trainer's cameras.json entries -> [(img_name, world_to_camera [4,4], fx, fy, W, H)].
    ``rotation`` and ``position`` are camera-to-world in COLMAP (OpenCV) axes; the principal point is the center."""
    out = []
    for k, c in enumerate(data):
        try:
            name, W, H = str(c["img_name"]), float(c["width"]), float(c["height"])
            rot, pos = np.asarray(c["rotation"], np.float64), np.asarray(c["position"], np.float64)
            fx, fy = float(c["fx"]), float(c["fy"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"camera {k} lacks img_name/width/height/rotation/position/fx/fy", path) from None
        if rot.shape != (3, 3) or pos.shape != (3,) or not (np.isfinite(rot).all() and np.isfinite(pos).all()):
            raise InputError(f"camera {k}: rotation must be a finite 3x3 and position 3 numbers", path)
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rot, pos
        try:
            out.append((name, np.linalg.inv(c2w), fx, fy, W, H))
        except np.linalg.LinAlgError:
            raise InputError(f"camera {k}: singular rotation", path) from None
    return out


def _inria_views(root, images):
    cj = root / "cameras.json"
    data = _read_json(cj)
    if not isinstance(data, list):
        raise InputError("expected a list of cameras", cj)
    folders = [root / images] if images else [root / n for n in _FOLDERS]
    cfg = root / "cfg_args"  # the trainer's Namespace repr: points back at the source photos
    if cfg.is_file() and not images:
        m = re.search(r"source_path='([^']*)'", cfg.read_text(errors="replace"))
        sub = re.search(r"images='([^']*)'", cfg.read_text(errors="replace"))
        if m:
            folders.append(Path(m.group(1)) / (sub.group(1) if sub else "images"))
    folder = next((f for f in folders if f.is_dir()), folders[0])
    views = []
    for name, w2c, fx, fy, W, H in inria_camera_entries(data, cj):
        path = next((folder / (name + e) for e in IMAGE_EXTS + tuple(x.upper() for x in IMAGE_EXTS)
                     if (folder / (name + e)).is_file()), folder / name)
        K = np.array([[fx, 0, W / 2], [0, fy, H / 2], [0, 0, 1]])
        views.append(_View(name, path, w2c, K, (W, H), source=cj))
    points = None
    if (root / "input.ply").is_file():  # the trainer's copy of the SfM points
        try:
            v = PlyData.read(str(root / "input.ply"))["vertex"]
            points = _points(np.stack([v["x"], v["y"], v["z"]], 1),
                             np.stack([v["red"], v["green"], v["blue"]], 1))
        except Exception as e:  # plyfile raises many types on a damaged file
            raise InputError(f"unreadable point cloud ({type(e).__name__})", root / "input.ply") from None
    return views, points


# --- entry point ----------------------------------------------------------------------------------------
def load_dataset(path, images=None, downscale=None, split=None, holdout_every=8, background=(1.0, 1.0, 1.0)):
    """Load a posed-photo dataset (format detected from the folder). See the module docstring.

    images: image sub-folder ("images_4"); downscale: resize factor (uses images_<f>/ when it exists);
    split: None (all views), "train" or "test" (every ``holdout_every``-th view by name is test; Blender
    uses its own transforms_train/test files); background: RGB that RGBA photos are composited onto."""
    root = Path(path)
    if not root.exists():
        raise InputError("dataset folder does not exist", root)
    if not root.is_dir():
        raise InputError("is not a folder (a dataset is a folder of photos and poses)", root)
    model = colmap.find_model(root)
    if model is not None:
        folder, rest = _image_folder(root, images, downscale)
        views, points = _colmap_views(root, *model, folder)
        return _finish(root, views, "colmap", rest, split, holdout_every, background, points)
    if (root / "poses_bounds.npy").is_file():
        folder, rest = _image_folder(root, images, downscale)
        views, points, bounds = _llff_views(root, folder)
        return _finish(root, views, "llff", rest, split, holdout_every, background, points, bounds)
    splits = {s: root / f"transforms_{s}.json" for s in ("train", "val", "test")}
    if any(f.is_file() for f in splits.values()):
        if images is not None:
            raise InputError("images= does not apply to a NeRF/Blender dataset (paths are in the JSON)", root)
        files = [f for s, f in splits.items() if f.is_file() and split in (None, s)]
        if not files:
            raise InputError(f"no transforms_{split}.json", root)
        return _finish(root, _blender_views(root, files), "blender", downscale, None, holdout_every, background)
    if (root / "transforms.json").is_file():
        views = _blender_views(root, [root / "transforms.json"])
        return _finish(root, views, "blender", downscale, split, holdout_every, background)
    if (root / "cameras.json").is_file():
        views, points = _inria_views(root, images)
        return _finish(root, views, "inria", downscale, split, holdout_every, background, points)
    for d in (root / "sparse" / "0", root / "sparse", root):  # a COLMAP model with one of its two files missing
        for ext in (".bin", ".txt"):
            have = [f for f in ("cameras", "images") if (d / f"{f}{ext}").is_file()]
            if len(have) == 1:
                missing = "images" if have == ["cameras"] else "cameras"
                raise InputError(f"COLMAP model has {have[0]}{ext} but no {missing}{ext} (missing file)",
                                 d / f"{missing}{ext}")
    raise InputError("no dataset found: expected sparse/0 (COLMAP), poses_bounds.npy (LLFF), "
                     "transforms_*.json (Blender) or cameras.json (INRIA)", root)
