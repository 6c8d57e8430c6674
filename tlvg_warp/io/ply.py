"""Gaussian scenes on disk: the INRIA 3DGS PLY (SPEC §1) and antimatter15's 32-byte ``.splat``, and the entry
points for every scene format: ``load_ply`` (by the file's header; the compressed formats are io/splat_formats.py's)
and ``save_scene`` (by the file's name).

Everything is whole-array numpy: the binary body is read with one ``np.fromfile`` and written with one
``tofile``, so a 3M-Gaussian scene takes seconds, not minutes."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..fileio import atomic_path
from ..types import SH_C0, Gaussians, sh_degree_of
from .scene_file import numpy_params, read_header, require_file
from .splat_formats import (is_compressed_ply_header, is_spz_bytes, load_compressed_ply, load_spz,
                            save_compressed_ply, save_spz)

_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def _read_vertices(f, path, order, elements):
    """The vertex element as a float32 table [N, P] plus its property names (in file order)."""
    offset = 0
    for name, count, props in elements:
        if any(t == "list" for _, t in props):
            if name == "vertex":
                raise InputError(f"PLY element '{name}' has list properties, which a Gaussian PLY never has", path)
            raise InputError(f"cannot skip PLY element '{name}' with list properties before 'vertex'", path)
        if name == "vertex":
            break
        offset += count * sum(np.dtype(t).itemsize for _, t in props)
    else:
        raise InputError("PLY has no 'vertex' element", path)
    names = [p for p, _ in props]
    if len(set(names)) != len(names):
        raise InputError("PLY vertex element has duplicate property names", path)
    if order is None:  # ascii: rare for splats, small files; whitespace-separated numbers
        if elements[0][0] != "vertex":  # would need line counting; no Gaussian writer does this
            raise InputError("ASCII PLY with elements before 'vertex' is not supported", path)
        values = np.array(f.read().split()[: count * len(names)], dtype=np.float64)
        if values.size != count * len(names):
            raise InputError(f"truncated ASCII PLY: expected {count} vertices x {len(names)} values", path)
        return values.reshape(count, len(names)).astype(np.float32), names
    rec = np.dtype([(p, order + t) for p, t in props])
    available = path.stat().st_size - f.tell() - offset
    if available < count * rec.itemsize:
        raise InputError(f"truncated PLY: header declares {count} vertices ({count * rec.itemsize} bytes) "
                         f"but only {max(available, 0)} bytes follow", path)
    f.seek(offset, 1)
    if {t for _, t in props} == {"f4"}:  # the common case: the body is one [N, P] float32 matrix
        table = np.fromfile(f, dtype=order + "f4", count=count * len(names)).reshape(count, len(names))
    else:
        data = np.fromfile(f, dtype=rec, count=count)
        table = np.stack([data[p].astype(np.float32) for p in names], axis=1)  # [N, P]
    if order == ">":
        table = table.astype("<f4")
    return table, names


def _f_rest_names(names, path):
    idx = sorted(int(m.group(1)) for n in names if (m := re.fullmatch(r"f_rest_(\d+)", n)))
    if idx != list(range(len(idx))):
        raise InputError(f"PLY f_rest_* properties are not numbered 0..{len(idx) - 1} without gaps", path)
    if len(idx) % 3 or (len(idx) // 3 + 1) not in (1, 4, 9, 16):
        raise InputError(f"PLY has {len(idx)} f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0..3)", path)
    return [f"f_rest_{i}" for i in idx]


def load_ply(path) -> Gaussians:
    """Read an INRIA-style Gaussian PLY (by property name, any order, normals optional). A PlayCanvas /
    SuperSplat compressed PLY or a Niantic SPZ file is recognized by its header and decoded instead."""
    path = Path(path)
    require_file(path)
    with open(path, "rb") as f:
        head = f.read(4)
        if head == b"NGSP" or head[:2] == b"\x1f\x8b":  # Niantic SPZ (v4, or gzip v1-3)
            return load_spz(path)
        f.seek(0)
        order, elements = read_header(f, path)
        if elements and elements[0][0] == "chunk":  # PlayCanvas / SuperSplat compressed PLY
            return load_compressed_ply(path)
        table, names = _read_vertices(f, path, order, elements)  # [N, P]
    missing = [n for n in _REQUIRED if n not in names]
    if missing:
        raise InputError(f"PLY is missing required properties: {', '.join(missing)}", path)
    rest = _f_rest_names(names, path)
    col = {n: i for i, n in enumerate(names)}

    def cols(wanted):  # [N, len(wanted)]; a strided slice (no copy) when the file stores them in a row
        idx = [col[n] for n in wanted]
        if idx == list(range(idx[0], idx[0] + len(idx))):
            return table[:, idx[0]:idx[0] + len(idx)]
        return table[:, idx]

    finite = np.isfinite(table).all()  # one fast pass; the detailed count only when something is wrong
    if not finite:
        wanted = list(_REQUIRED) + rest
        per = (~np.isfinite(cols(wanted))).sum(axis=0)  # [P]
        if per.any():
            where = ", ".join(f"{per[j]} in {wanted[j]}" for j in np.flatnonzero(per)[:6])
            more = " ..." if np.count_nonzero(per) > 6 else ""
            raise InputError(f"PLY has {int(per.sum())} NaN/infinite values ({where}{more})", path)
    n, k = table.shape[0], len(rest) // 3 + 1
    sh = np.empty((n, k, 3), np.float32)  # [N, K, 3]
    sh[:, 0] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    if rest:  # f_rest is channel-major: all R coefficients, then G, then B: [N, 3, K-1] -> [N, K-1, 3]
        sh[:, 1:] = cols(rest).reshape(n, 3, k - 1).transpose(0, 2, 1)

    def t(names_):
        return torch.from_numpy(np.ascontiguousarray(cols(names_)))

    return Gaussians(means=t(["x", "y", "z"]), quats=t(["rot_0", "rot_1", "rot_2", "rot_3"]),
                     log_scales=t(["scale_0", "scale_1", "scale_2"]), opacity_logits=t(["opacity"])[:, 0],
                     sh=torch.from_numpy(sh))


def ply_property_names(degree: int) -> list[str]:
    """The INRIA property order for SH ``degree``."""
    nrest = 3 * ((degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(nrest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def save_ply(g: Gaussians, path) -> None:
    """Write ``g`` in the INRIA layout and order (float32 little-endian, normals zero), atomically."""
    path = Path(path)
    a = numpy_params(g, path)
    n, k = a["sh"].shape[:2]
    names = ply_property_names(sh_degree_of(k))
    table = np.zeros((n, len(names)), "<f4")  # [N, P]; nx ny nz stay 0
    r = 9 + 3 * (k - 1)  # first column after f_rest
    table[:, 0:3] = a["means"]
    table[:, 6:9] = a["sh"][:, 0]
    table[:, 9:r] = a["sh"][:, 1:].transpose(0, 2, 1).reshape(n, -1)  # channel-major
    table[:, r] = a["opacity_logits"]
    table[:, r + 1:r + 4] = a["log_scales"]
    table[:, r + 4:r + 8] = a["quats"]
    header = ("ply\nformat binary_little_endian 1.0\n" f"element vertex {n}\n"
              + "".join(f"property float {p}\n" for p in names) + "end_header\n")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        table.tofile(f)


# --- antimatter15 .splat: 32 bytes per Gaussian, no header -----------------------------------------------
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert SPLAT_DTYPE.itemsize == 32


def save_splat(g: Gaussians, path) -> None:
    """Write the web-viewer format: activated scales, RGBA from the SH DC term and sigmoid(opacity),
    normalized w,x,y,z quaternion as ``q*128+128`` bytes. Sorted by size x opacity, largest first, as
    antimatter15's convert.py does, so progressive loading shows the big splats first."""
    path = Path(path)
    a = numpy_params(g, path)
    q = a["quats"].astype(np.float64)  # [N, 4]
    q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    alpha = 1.0 / (1.0 + np.exp(-a["opacity_logits"].astype(np.float64)))  # [N]
    rgb = 0.5 + SH_C0 * a["sh"][:, 0].astype(np.float64)  # [N, 3]
    order = np.argsort(-np.exp(a["log_scales"].astype(np.float64).sum(1)) * alpha, kind="stable")
    out = np.empty(len(order), SPLAT_DTYPE)
    out["position"] = a["means"][order]
    out["scale"] = np.exp(a["log_scales"][order])
    to_u8 = lambda v: np.clip(np.round(v * 255.0), 0, 255).astype(np.uint8)  # noqa: E731
    out["rgba"][:, :3] = to_u8(rgb[order])
    out["rgba"][:, 3] = to_u8(alpha[order])
    out["rot"] = np.clip(np.round(q[order] * 128.0 + 128.0), 0, 255).astype(np.uint8)
    with atomic_path(path) as tmp:
        out.tofile(tmp)


def load_splat(path) -> Gaussians:
    """Read a ``.splat`` back into (degree-0) Gaussians, in file order."""
    path = Path(path)
    require_file(path)
    size = path.stat().st_size
    if size % SPLAT_DTYPE.itemsize:
        raise InputError(f"truncated .splat: {size} bytes is not a multiple of 32", path)
    d = np.fromfile(path, dtype=SPLAT_DTYPE)
    pos, scale = d["position"], d["scale"]
    for name, v in (("position", pos), ("scale", scale)):
        nbad = int((~np.isfinite(v)).sum())
        if nbad:
            raise InputError(f".splat has {nbad} NaN/infinite values in {name}", path)
    q = (d["rot"].astype(np.float32) - 128.0) / 128.0  # [N, 4]
    q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    # half a quantization step away from 0 and 255 so the logit stays finite
    alpha = np.clip(d["rgba"][:, 3].astype(np.float64) / 255.0, 0.5 / 255, 1 - 0.5 / 255)
    dc = (d["rgba"][:, :3].astype(np.float32) / 255.0 - 0.5) / SH_C0  # [N, 3]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return Gaussians(means=t(pos), quats=t(q), log_scales=t(np.log(np.maximum(scale, 1e-30))),
                     opacity_logits=t(np.log(alpha / (1 - alpha))), sh=t(dc[:, None, :]))


# --- any scene file: the kind by content, the writer by name --------------------------------------------
def scene_kind(path) -> str:
    """'spz', 'compressed_ply', 'ply' or 'splat' from the file's first bytes (and name for .splat)."""
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(4)
    if is_spz_bytes(head):
        return "spz"
    if head == b"ply\n":
        with open(path, "rb") as f:
            _, elements = read_header(f, path)
        return "compressed_ply" if is_compressed_ply_header(elements) else "ply"
    return "splat" if path.suffix.lower() == ".splat" else "unknown"


def save_scene(g: Gaussians, path) -> None:
    """Write by file name: ``*.compressed.ply``, ``*.spz``, ``*.splat`` or (else) the INRIA ``*.ply``."""
    name = Path(path).name.lower()
    if name.endswith(".compressed.ply"):
        save_compressed_ply(g, path)
    elif name.endswith(".spz"):
        save_spz(g, path)
    elif name.endswith(".splat"):
        save_splat(g, path)
    else:
        save_ply(g, path)
