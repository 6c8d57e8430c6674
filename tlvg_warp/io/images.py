"""Photo files: size from the header (cheap, so a whole folder is checked before anything is decoded)
and decoding to float RGB(A). Every failure is an InputError naming the file."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..errors import InputError

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
_PNG_SIG = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers carry the size; C4 (DHT), C8 (JPG), CC (DAC) share the range but do not
_SOF = set(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def list_images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file()),
                  key=lambda p: p.name)


def _jpeg_size(f):
    f.seek(2)
    while True:
        b = f.read(1)
        while b == b"\xff":  # fill bytes before the marker code
            b = f.read(1)
        if not b:
            return None
        marker = b[0]
        if marker in (0x01, *range(0xD0, 0xD9)):  # markers without a length field
            continue
        seg = f.read(2)
        if len(seg) < 2:
            return None
        (length,) = struct.unpack(">H", seg)
        if marker in _SOF:
            body = f.read(5)
            if len(body) < 5:
                return None
            h, w = struct.unpack(">HH", body[1:5])
            return w, h
        f.seek(length - 2, 1)
        if f.read(1) != b"\xff":  # every segment is followed by the next marker
            return None
        f.seek(-1, 1)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, from its header for PNG/JPEG (EXIF orientation ignored, as
    COLMAP and :func:`read_image` do); other formats are decoded."""
    if not path.is_file():
        raise InputError("missing image file", path)
    with open(path, "rb") as f:
        head = f.read(24)
        size = None
        if head[:8] == _PNG_SIG and head[12:16] == b"IHDR":
            size = struct.unpack(">II", head[16:24])
        elif head[:2] == b"\xff\xd8":
            size = _jpeg_size(f)
        elif path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
            img = read_image(path)
            size = img.shape[1], img.shape[0]
    if not size or min(size) <= 0:
        raise InputError("unreadable image (not a valid PNG/JPEG header)", path)
    return int(size[0]), int(size[1])


def read_image(path: Path) -> np.ndarray:
    """float32 [H, W, 3 or 4] RGB(A) in [0, 1]; 8- and 16-bit, gray or color."""
    import cv2

    if not path.is_file():
        raise InputError("missing image file", path)
    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if a is None or a.size == 0:
        raise InputError("unreadable image (corrupt or unsupported format)", path)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(a.dtype)
    if scale is None:
        raise InputError(f"unsupported image sample type {a.dtype}", path)
    if a.ndim == 2:
        a = cv2.cvtColor(a, cv2.COLOR_GRAY2RGB)
    elif a.shape[2] == 4:
        a = cv2.cvtColor(a, cv2.COLOR_BGRA2RGBA)
    else:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2RGB)
    return a.astype(np.float32) / np.float32(scale)


def composite(img: np.ndarray, background) -> np.ndarray:
    """RGBA over a constant background -> RGB [H, W, 3]; RGB passes through."""
    if img.shape[2] == 3:
        return img
    a = img[:, :, 3:4]  # [H, W, 1]
    bg = np.asarray(background, np.float32).reshape(1, 1, 3)
    return img[:, :, :3] * a + bg * (1.0 - a)
