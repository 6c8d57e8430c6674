"""What the scene file formats share (io/ply.py: the INRIA PLY and .splat; io/splat_formats.py: the compressed PLY
and SPZ): the file check, the PLY header parser (a compressed PLY is a PLY too) and the float32 parameter export."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..types import Gaussians

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
_MAX_HEADER = 1 << 20  # a real header is a few KB; anything longer is not a PLY header


def require_file(path: Path) -> None:
    if not path.exists():
        raise InputError("file does not exist", path)
    if not path.is_file():
        raise InputError("is not a file", path)


def read_header(f, path):
    """Parse the header; returns (byte-order char or None for ascii, [(element, count, [(prop, dtype)])])."""
    if f.read(4) != b"ply\n":
        raise InputError("not a PLY file (it does not start with 'ply')", path)
    order, elements, size = "?", [], 4
    while True:
        line = f.readline()
        size += len(line)
        if not line.endswith(b"\n") or size > _MAX_HEADER:
            raise InputError("corrupt PLY header (no end_header line)", path)
        words = line.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and len(words) >= 2 and words[1] in _FORMATS:
            order = _FORMATS[words[1]]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        elif words[0] == "property" and elements and words[1] == "list":
            elements[-1][2].append((words[-1], "list"))
        else:
            raise InputError(f"corrupt PLY header line {line.strip()[:60]!r}", path)
    if order == "?":
        raise InputError("PLY header has no known 'format' line", path)
    return order, elements


def numpy_params(g: Gaussians, path):
    """float32 numpy views of the parameters; refuses non-finite values (the file would be unreadable)."""
    arrs = {f: getattr(g, f).detach().to("cpu", torch.float32).numpy() for f in Gaussians.FIELDS}
    bad = {f: int((~np.isfinite(a)).sum()) for f, a in arrs.items()}
    bad = {f: c for f, c in bad.items() if c}
    if bad:
        where = ", ".join(f"{c} in {f}" for f, c in bad.items())
        raise InputError(f"refusing to write Gaussians with NaN/infinite values ({where})", path)
    return arrs
