"""Photo files: size from the header (cheap, so a whole folder is checked before anything is decoded)
and decoding to float RGB(A). Every failure is an InputError naming the file."""
from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError, one_line

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


MAX_PIXELS = 1 << 30  # OpenCV's decode limit (CV_IO_MAX_IMAGE_PIXELS); larger claims are refused from the header
_TAIL = 1 << 16  # bytes read from the end of a file to find its end marker


def _damage(f, kind: str, size) -> str | None:
    """Why a PNG/JPEG cannot decode to ``size``, or None. A PNG must end with its IEND chunk, a JPEG's last scan
    with the EOI marker FFD9 (libjpeg and libpng only warn on stderr and return a partly grey image). Reads the
    file's tail, the whole JPEG only when the tail has no FFD9 (bytes appended after EOI; the marker cannot occur
    inside entropy-coded data), and a PNG's chunk headers: deflate expands at most 1032:1, so image data too
    small for the size in the header means a corrupt header (libpng would print its error on stderr)."""
    end = f.seek(0, 2)
    f.seek(max(0, end - _TAIL))
    tail = f.read()
    if kind == "png":
        if b"IEND" not in tail[-12:]:
            return "truncated PNG file (it ends before its IEND chunk)"
        f.seek(8)
        idat, bits = 0, None
        while (head := f.read(8)) and len(head) == 8:
            n, typ = struct.unpack(">I4s", head)
            if typ == b"IHDR":
                depth, color = f.read(n)[8:10]
                bits = depth * {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(color, 4)
                f.seek(4, 1)
            else:
                idat += n if typ == b"IDAT" else 0
                f.seek(n + 4, 1)
        raw = size[1] * (1 + (size[0] * (bits or 8) + 7) // 8)
        if idat * 1032 + 1024 < raw:
            return f"corrupt PNG: the header claims {size[0]}x{size[1]} but the file holds {idat} bytes of image data"
        return None
    if b"\xff\xd9" in tail:
        return None
    f.seek(0)
    data = f.read()
    if data.rfind(b"\xff\xd9") < data.rfind(b"\xff\xda"):  # no EOI after the last start-of-scan
        return "truncated JPEG file (it ends before its end-of-image marker)"
    return None


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, from its header for PNG/JPEG (EXIF orientation ignored, as
    COLMAP and :func:`read_image` do); other formats are decoded. Also refuses, naming the file, a PNG/JPEG
    that is cut short and a header that claims more than MAX_PIXELS, so a dataset's photos are all checked
    before anything is decoded or written."""
    if not path.is_file():
        raise InputError("missing image file", path)
    with open(path, "rb") as f:
        head = f.read(24)
        size, kind = None, None
        if head[:8] == _PNG_SIG and head[12:16] == b"IHDR":
            size, kind = struct.unpack(">II", head[16:24]), "png"
        elif head[:2] == b"\xff\xd8":
            size, kind = _jpeg_size(f), "jpeg"
        elif path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
            img = read_image(path)
            size = img.shape[1], img.shape[0]
        if not size or min(size) <= 0:
            raise InputError("unreadable image (not a valid PNG/JPEG header)", path)
        if size[0] * size[1] > MAX_PIXELS:
            raise InputError(f"image header claims {size[0]}x{size[1]} pixels, more than the "
                             f"{MAX_PIXELS} an image may have (corrupt header?)", path)
        damage = _damage(f, kind, size) if kind is not None else None
        if damage:
            raise InputError(damage, path)
    return int(size[0]), int(size[1])


def read_image(path: Path, max_side: int | None = None) -> np.ndarray:
    """See :func:`read_image_fit`; the image only."""
    return read_image_fit(path, max_side)[0]


def read_image_fit(path: Path, max_side: int | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """(image, (width, height) of the file). The image: float32 [H, W, 3 or 4] RGB(A) in [0, 1]; 8- and 16-bit,
    gray or color. PNG/JPEG files are checked (:func:`image_size`) before the decoder sees them. ``max_side``: a larger image is shrunk (area average) to
    fit it before it becomes float, so memory stays near the decoded file's own size (a large JPEG is decoded
    at 1/2, 1/4 or 1/8 scale by libjpeg itself)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("missing image file", path)
    with open(path, "rb") as f:
        head = f.read(8)
    size = image_size(path) if head == _PNG_SIG or head[:2] == b"\xff\xd8" else None
    flags = cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION
    if max_side and size and head[:2] == b"\xff\xd8" and max(size) >= 2 * max_side:
        k = max(f for f in (2, 4, 8) if max(size) >= f * max_side)
        flags = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                 8: cv2.IMREAD_REDUCED_COLOR_8}[k] | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        a = cv2.imread(str(path), flags)
    except cv2.error as e:  # e.g. OpenCV's own pixel limit for formats whose header we do not read
        raise InputError(f"unreadable image ({one_line(e.err or e)[:120]})", path) from None
    if a is None or a.size == 0:
        raise InputError("unreadable image (corrupt or unsupported format)", path)
    full = size or (a.shape[1], a.shape[0])
    if max_side and max(a.shape[:2]) > max_side:
        s = max_side / max(a.shape[:2])
        a = cv2.resize(a, (max(1, round(a.shape[1] * s)), max(1, round(a.shape[0] * s))),
                       interpolation=cv2.INTER_AREA)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(a.dtype)
    if scale is None:
        raise InputError(f"unsupported image sample type {a.dtype}", path)
    if a.ndim == 2:
        a = cv2.cvtColor(a, cv2.COLOR_GRAY2RGB)
    elif a.shape[2] == 4:
        a = cv2.cvtColor(a, cv2.COLOR_BGRA2RGBA)
    else:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2RGB)
    f = a.astype(np.float32)
    f /= np.float32(scale)  # in place: one float copy of the image, not two
    return f, (int(full[0]), int(full[1]))


def composite(img: np.ndarray, background) -> np.ndarray:
    """RGBA over a constant background -> RGB [H, W, 3]; RGB passes through."""
    if img.shape[2] == 3:
        return img
    a = img[:, :, 3:4]  # [H, W, 1]
    bg = np.asarray(background, np.float32).reshape(1, 1, 3)
    return img[:, :, :3] * a + bg * (1.0 - a)
