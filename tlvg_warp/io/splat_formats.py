"""Compressed Gaussian scene formats that viewers and other tools already use:

* the PlayCanvas / SuperSplat **compressed PLY** (``*.compressed.ply``): chunks of 256 Gaussians with
  min/max bounds, each Gaussian packed into four uint32 (position 11/10/11 bits, rotation 2 + 3x10 bits,
  log-scale 11/10/11, RGBA 8888), optional ``sh`` element of uint8 coefficients;
* Niantic's **SPZ** (``*.spz``): version 4 (32-byte header, table of contents, one zstd stream per
  attribute) and the legacy gzip versions 1-3.

Formats as read from playcanvas/engine ``gsplat-compressed-data.js``, playcanvas/supersplat
``splat-serialize.ts`` and nianticlabs/spz ``load-spz.cc`` / README (read, not copied). Every decode and
encode is whole-array numpy. Values come back in this project's convention (SPEC §1): w,x,y,z quaternions,
log scales, opacity logits, SH DC; SPZ's RUB axes are converted to the PLY's RDF axes (and back on write).
Bad files raise a one-line :class:`InputError` naming the file."""
from __future__ import annotations

import gzip
import struct
import zlib
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..fileio import atomic_path
from ..types import SH_C0, Gaussians
from .scene_file import numpy_params, read_header, require_file

# --- shared helpers ---------------------------------------------------------------------------------------------
LOGIT_CLAMP = 0.5 / 255  # an 8-bit opacity of 0 or 255 decodes half a step inside (0, 1) so the logit is finite
_SQRT1_2 = np.sqrt(0.5)


def _logit_u8(a: np.ndarray) -> np.ndarray:
    """uint8 opacity -> logit (float64), half a quantization step away from 0 and 1."""
    p = np.clip(a.astype(np.float64) / 255.0, LOGIT_CLAMP, 1.0 - LOGIT_CLAMP)
    return np.log(p / (1.0 - p))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def _params(g: Gaussians, path) -> dict:
    """float64 numpy parameters; refuses NaN/inf (the file would be unreadable)."""
    return {k: v.astype(np.float64) for k, v in numpy_params(g, path).items()}


def _unit_quats(q: np.ndarray) -> np.ndarray:  # [N, 4] -> [N, 4]
    return q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)


def _gaussians(path, means, quats, log_scales, logits, sh) -> Gaussians:
    """Assemble float32 Gaussians, refusing NaN/inf produced by decoding (a corrupt file)."""
    arrs = {"means": means, "quats": quats, "log_scales": log_scales, "opacity_logits": logits, "sh": sh}
    bad = {k: int((~np.isfinite(v)).sum()) for k, v in arrs.items()}
    bad = {k: c for k, c in bad.items() if c}
    if bad:
        raise InputError("decoded NaN/infinite values (" + ", ".join(f"{c} in {k}" for k, c in bad.items())
                         + "); the file is corrupt", path)
    t = {k: torch.from_numpy(np.ascontiguousarray(v, dtype=np.float32)) for k, v in arrs.items()}
    return Gaussians(**t)


# "others[i]": the three quaternion slots that are stored when slot i (the largest) is dropped
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def _place_largest(idx: np.ndarray, small: np.ndarray) -> np.ndarray:
    """Quaternion [N, 4] from the index of its dropped largest slot [N] and the other three [N, 3]
    (in ascending slot order); the largest is the non-negative square root of the rest."""
    n = idx.shape[0]
    q = np.empty((n, 4), np.float64)
    rows = np.arange(n)[:, None]
    q[rows, _OTHERS[idx]] = small
    q[np.arange(n), idx] = np.sqrt(np.maximum(0.0, 1.0 - (small ** 2).sum(1)))
    return q


def _largest_first(q: np.ndarray):
    """(index of the largest |component| [N], the other three [N, 3] with the largest made positive)."""
    idx = np.argmax(np.abs(q), axis=1)  # first maximum on ties, like both reference encoders
    n = q.shape[0]
    q = q * np.where(q[np.arange(n), idx] < 0, -1.0, 1.0)[:, None]
    return idx, q[np.arange(n)[:, None], _OTHERS[idx]]


# === PlayCanvas / SuperSplat compressed PLY ======================================================================
CHUNK = 256  # Gaussians per chunk
CHUNK_PROPS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
               "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
               "min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
VERTEX_PROPS = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
SCALE_CLAMP = 20.0  # SuperSplat clamps chunk log-scale bounds to +-20 ("sometimes values are at infinity")
SH_RANGE = 4.0  # compressed-PLY SH bytes cover [-4, 4]: value = byte * 8/255 - 4 (PlayCanvas engine decoder)
MIN_RANGE = 1e-5  # SuperSplat: a chunk range below this packs as 0 (the min)


def is_compressed_ply_header(elements) -> bool:
    """True for the chunk + packed-vertex layout (by element and property names)."""
    names = [e[0] for e in elements]
    return len(names) >= 2 and names[0] == "chunk" and names[1] == "vertex" and \
        [p for p, _ in elements[1][2]] == VERTEX_PROPS


def _unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    return ((v >> np.uint32(shift)) & np.uint32(m)).astype(np.float64) / m


def _unpack_111011(v: np.ndarray) -> np.ndarray:  # [N] uint32 -> [N, 3] in [0, 1]
    return np.stack([_unorm(v, 21, 11), _unorm(v, 11, 10), _unorm(v, 0, 11)], axis=1)


def _check_compressed_layout(path, order, elements):
    """Validate the header; returns (n_chunks, n, chunk prop count, sh coefficient count per channel)."""
    if order != "<":
        raise InputError("compressed PLY must be binary_little_endian", path)
    (_, nchunk, cprops), (_, n, vprops) = elements[0], elements[1]
    cnames = [p for p, _ in cprops]
    if cnames not in (CHUNK_PROPS[:12], CHUNK_PROPS) or any(t != "f4" for _, t in cprops):
        raise InputError("compressed PLY chunk element must hold 12 or 18 float min/max properties", path)
    if any(t != "u4" for _, t in vprops):
        raise InputError("compressed PLY packed_* properties must be uint", path)
    if nchunk != -(-n // CHUNK):
        raise InputError(f"compressed PLY counts disagree: {n} vertices need {-(-n // CHUNK)} chunks of {CHUNK}, "
                         f"the header declares {nchunk}", path)
    ksh = 0
    if len(elements) > 2:
        sname, ns, sprops = elements[2]
        want = [f"f_rest_{i}" for i in range(len(sprops))]
        if (sname != "sh" or len(elements) > 3 or [p for p, _ in sprops] != want or len(sprops) not in (9, 24, 45)
                or any(t != "u1" for _, t in sprops)):
            raise InputError("compressed PLY has unexpected elements after 'vertex' (only an 'sh' element of 9, 24 "
                             "or 45 uchar f_rest_* is defined)", path)
        if ns != n:
            raise InputError(f"compressed PLY counts disagree: {ns} sh rows for {n} vertices", path)
        ksh = len(sprops) // 3
    return nchunk, n, len(cnames), ksh


def load_compressed_ply(path) -> Gaussians:
    """Decode a PlayCanvas / SuperSplat compressed PLY (file order is kept)."""
    path = Path(path)
    require_file(path)
    with open(path, "rb") as f:
        order, elements = read_header(f, path)
        start = f.tell()
    nchunk, n, ncp, ksh = _check_compressed_layout(path, order, elements)
    need = nchunk * ncp * 4 + n * 16 + n * 3 * ksh
    have = path.stat().st_size - start
    if have != need:
        what = "truncated" if have < need else "has extra bytes after the data:"
        raise InputError(f"compressed PLY {what} header declares {nchunk} chunks and {n} vertices "
                         f"({need} bytes) but {have} bytes follow", path)
    body = np.fromfile(path, dtype=np.uint8, offset=start)
    chunks = body[:nchunk * ncp * 4].view("<f4").reshape(nchunk, ncp).astype(np.float64)  # [C, 12|18]
    packed = body[nchunk * ncp * 4:nchunk * ncp * 4 + n * 16].view("<u4").reshape(n, 4)  # [N, 4]
    ch = chunks[np.arange(n) // CHUNK]  # [N, 12|18]

    def lerp(lo, t):  # chunk columns lo..lo+2 (min) and lo+3..lo+5 (max)
        return ch[:, lo:lo + 3] + (ch[:, lo + 3:lo + 6] - ch[:, lo:lo + 3]) * t

    means = lerp(0, _unpack_111011(packed[:, 0]))  # [N, 3]
    log_scales = lerp(6, _unpack_111011(packed[:, 2]))  # [N, 3]
    rgba = np.stack([_unorm(packed[:, 3], s, 8) for s in (24, 16, 8, 0)], axis=1)  # [N, 4]
    rgb = lerp(12, rgba[:, :3]) if ncp == 18 else rgba[:, :3]
    rot = packed[:, 1]
    small = np.stack([_unorm(rot, s, 10) for s in (20, 10, 0)], axis=1)  # [N, 3]
    quats = _place_largest((rot >> np.uint32(30)).astype(np.int64), (small - 0.5) * np.sqrt(2.0))  # w,x,y,z
    logits = _logit_u8((packed[:, 3] & np.uint32(0xFF)).astype(np.uint8))
    sh = np.zeros((n, 1 + ksh, 3))  # [N, K, 3]
    sh[:, 0] = (rgb - 0.5) / SH_C0
    if ksh:  # channel-major like INRIA f_rest: [N, 3, K-1] -> [N, K-1, 3]
        raw = body[nchunk * ncp * 4 + n * 16:].reshape(n, 3, ksh).astype(np.float64)
        sh[:, 1:] = (raw * (2 * SH_RANGE / 255) - SH_RANGE).transpose(0, 2, 1)
    return _gaussians(path, means, quats, log_scales, logits, sh)


def _morton_order(means: np.ndarray) -> np.ndarray:
    """Indices sorting points along a 3D Morton curve (10 bits per axis), so that each chunk of 256 is
    spatially compact and its min/max box small (SuperSplat does the same)."""
    lo, hi = means.min(0), means.max(0)
    q = np.clip(((means - lo) / np.maximum(hi - lo, 1e-30) * 1024).astype(np.int64), 0, 1023)  # [N, 3]
    code = np.zeros(len(means), np.int64)
    for bit in range(10):  # 10 bit planes, each vectorized over all Gaussians
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.argsort(code, kind="stable")


def _pack_unorm(t: np.ndarray, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    return np.clip(np.floor(t * m + 0.5), 0, m).astype(np.uint32)


def _chunk_minmax(v: np.ndarray, n: int):
    """Per-chunk min and max [C, D] of v [N, D]."""
    starts = np.arange(0, n, CHUNK)
    return np.minimum.reduceat(v, starts, axis=0), np.maximum.reduceat(v, starts, axis=0)


def _normalize(v: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(v - lo) / (hi - lo) per Gaussian with its chunk's bounds [N, D]; 0 where the range is degenerate."""
    rng = hi - lo
    t = np.where(rng < MIN_RANGE, 0.0, (v - lo) / np.where(rng < MIN_RANGE, 1.0, rng))
    return np.clip(t, 0.0, 1.0)


def _pack_111011(t: np.ndarray) -> np.ndarray:  # [N, 3] in [0,1] -> [N] uint32
    return (_pack_unorm(t[:, 0], 11) << np.uint32(21)) | (_pack_unorm(t[:, 1], 10) << np.uint32(11)) \
        | _pack_unorm(t[:, 2], 11)


def save_compressed_ply(g: Gaussians, path) -> np.ndarray:
    """Write ``g`` as a PlayCanvas / SuperSplat compressed PLY, atomically. Gaussians are reordered along a
    Morton curve (each chunk's bounds stay tight); returns that order: file row i holds ``g[order[i]]``.
    SH bands beyond DC go to the ``sh`` element as bytes over [-4, 4]."""
    path = Path(path)
    a = _params(g, path)
    n, k = a["sh"].shape[:2]
    if n == 0:
        raise InputError("refusing to write a compressed PLY with no Gaussians", path)
    order = _morton_order(a["means"])
    a = {key: v[order] for key, v in a.items()}
    idx = np.arange(n) // CHUNK
    rgb = a["sh"][:, 0] * SH_C0 + 0.5  # [N, 3]
    log_s = a["log_scales"]
    bounds = {}
    for name, v in (("pos", a["means"]), ("scale", log_s), ("rgb", rgb)):
        lo, hi = _chunk_minmax(v, n)
        if name == "scale":
            lo, hi = np.clip(lo, -SCALE_CLAMP, SCALE_CLAMP), np.clip(hi, -SCALE_CLAMP, SCALE_CLAMP)
        bounds[name] = (lo, hi)

    def packed_of(name, v):
        lo, hi = bounds[name]
        return _pack_111011(_normalize(v, lo[idx], hi[idx]))

    qi, small = _largest_first(_unit_quats(a["quats"]))  # slots in w,x,y,z order, as rot_0..rot_3
    s = _pack_unorm(small * _SQRT1_2 + 0.5, 10)  # [N, 3]
    rot = (qi.astype(np.uint32) << np.uint32(30)) | (s[:, 0] << np.uint32(20)) | (s[:, 1] << np.uint32(10)) | s[:, 2]
    lo, hi = bounds["rgb"]
    c = _normalize(rgb, lo[idx], hi[idx])
    alpha = _sigmoid(a["opacity_logits"])
    color = ((_pack_unorm(c[:, 0], 8) << np.uint32(24)) | (_pack_unorm(c[:, 1], 8) << np.uint32(16))
             | (_pack_unorm(c[:, 2], 8) << np.uint32(8)) | _pack_unorm(alpha, 8))
    vertex = np.stack([packed_of("pos", a["means"]), rot, packed_of("scale", log_s), color], axis=1).astype("<u4")
    chunk = np.concatenate([bounds["pos"][0], bounds["pos"][1], bounds["scale"][0], bounds["scale"][1],
                            bounds["rgb"][0], bounds["rgb"][1]], axis=1).astype("<f4")  # [C, 18]
    header = ["ply", "format binary_little_endian 1.0", "comment Generated by tlvg_warp",
              f"element chunk {len(chunk)}"] + [f"property float {p}" for p in CHUNK_PROPS] + \
             [f"element vertex {n}"] + [f"property uint {p}" for p in VERTEX_PROPS]
    sh_bytes = b""
    if k > 1:
        rest = a["sh"][:, 1:].transpose(0, 2, 1).reshape(n, -1)  # [N, 3(K-1)] channel-major
        sh_bytes = _u8((rest + SH_RANGE) * (255 / (2 * SH_RANGE))).tobytes()
        header += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(rest.shape[1])]
    header.append("end_header\n")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write("\n".join(header).encode("ascii"))
        f.write(chunk.tobytes())
        f.write(vertex.tobytes())
        f.write(sh_bytes)
    return order


# === Niantic SPZ ================================================================================================
SPZ_MAGIC = 0x5053474E  # b"NGSP" little-endian
SPZ_COLOR_SCALE = 0.15  # SPZ color byte = dc * 0.15 * 255 + 127.5 (wider than SH_C0 so DC may leave [0,1])
SPZ_MAX_VERSION = 4
SPZ_FRACTIONAL_BITS = 12  # fixed-point position fraction the reference writer uses (~0.24 mm per unit metre)
SPZ_SH_BUCKET = {1: 8, 2: 16, 3: 16}  # reference writer: 5 bits for degree-1 SH, 4 bits for higher bands
SPZ_ZSTD_LEVEL = 12  # what the reference writer and gsply use
SPZ_COORDINATE_EXT = 0xADBE0003  # SPZ_ADOBE_coordinate_system: data not in RUB; not supported here
_SH_DIM = {0: 0, 1: 3, 2: 8, 3: 15}
# RDF (PLY) <-> RUB (SPZ) flips y and z: positions (1,-1,-1); quaternion x,y,z by (y*z, x*z, x*y) = (1,-1,-1)
# (w never flips); SH coefficient k by the reference converter's table with x=1, y=z=-1.
_FLIP_P = np.array([1.0, -1.0, -1.0])
_FLIP_Q_WXYZ = np.array([1.0, 1.0, -1.0, -1.0])
_FLIP_SH = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float64)  # [15]


def is_spz_bytes(head: bytes) -> bool:
    return head[:4] == b"NGSP" or head[:2] == b"\x1f\x8b"


def _spz_sizes(n: int, version: int, sh_dim: int) -> list:
    """Byte sizes of positions, alphas, colors, scales, rotations, sh."""
    return [n * (6 if version == 1 else 9), n, 3 * n, 3 * n, n * (4 if version >= 3 else 3), n * sh_dim * 3]


def _spz_read_v4(raw: bytes, path):
    """(header dict, [six section byte strings]) from the NGSP v4 container."""
    if len(raw) < 32:
        raise InputError(f"truncated SPZ: {len(raw)} bytes, the v4 header alone is 32", path)
    magic, version, n, deg, frac, flags, nstreams, toc = struct.unpack_from("<IIIBBBBI", raw, 0)
    if version != 4:
        raise InputError(f"unsupported SPZ version {version} in an uncompressed NGSP header (only 4 is; "
                         "versions 1-3 are gzip files)", path)
    if deg > 3:
        raise InputError(f"unsupported SPZ SH degree {deg} (0..3 are)", path)
    if toc < 32 or toc + 16 * nstreams > len(raw):
        raise InputError(f"truncated SPZ: table of contents at byte {toc} ({nstreams} streams) lies past the "
                         f"end of the {len(raw)}-byte file", path)
    if flags & 0x2:
        _spz_check_extensions(raw[32:toc], path)
    entries = np.frombuffer(raw, "<u8", count=2 * nstreams, offset=toc).reshape(nstreams, 2)  # [S, 2]
    want = [s for s in _spz_sizes(n, version, _SH_DIM[deg]) if s]
    if nstreams != len(want) or [int(u) for u in entries[:, 1]] != want:
        raise InputError(f"SPZ counts disagree: header says {n} points at SH degree {deg} (streams of {want} bytes) "
                         f"but the table lists {nstreams} streams of {[int(u) for u in entries[:, 1]]} bytes", path)
    pos = toc + 16 * nstreams
    end = pos + int(entries[:, 0].sum())
    if end > len(raw):
        raise InputError(f"truncated SPZ: streams need {end} bytes, the file has {len(raw)}", path)
    if end < len(raw):
        raise InputError(f"SPZ counts disagree: {len(raw) - end} bytes follow the last stream", path)
    try:  # lazy: only SPZ version 4 needs it, and a missing one is a one-line error
        import zstandard
    except ImportError as e:
        raise InputError("SPZ version 4 needs the 'zstandard' package (pip install zstandard)", path) from e
    out, d = [], zstandard.ZstdDecompressor()
    for cs, us in entries:
        try:
            block = d.decompress(raw[pos:pos + int(cs)], max_output_size=int(us))
        except zstandard.ZstdError as e:
            raise InputError(f"corrupt SPZ stream ({e})", path) from None
        if len(block) != us:
            raise InputError(f"SPZ counts disagree: a stream decompressed to {len(block)} bytes, the table says {us}",
                             path)
        out.append(block)
        pos += int(cs)
    out += [b""] * (6 - len(out))  # the empty SH stream is not stored
    return {"version": version, "n": n, "deg": deg, "frac": frac, "flags": flags}, out


def _spz_check_extensions(block: bytes, path) -> None:
    """Skip extension records; refuse the one that changes the stored coordinate system."""
    off = 0
    while off + 8 <= len(block):
        typ, length = struct.unpack_from("<II", block, off)
        if typ == SPZ_COORDINATE_EXT:
            raise InputError("unsupported SPZ extension SPZ_ADOBE_coordinate_system (data not stored in RUB)", path)
        off += 8 + length


def _spz_read_legacy(raw: bytes, path):
    """(header dict, sections) from a gzip SPZ (versions 1-3)."""
    try:
        data = gzip.decompress(raw)
    except (OSError, EOFError, zlib.error) as e:
        raise InputError(f"corrupt or truncated gzip SPZ ({e})", path) from None
    if len(data) < 16:
        raise InputError(f"truncated SPZ: {len(data)} bytes after gunzip, the header alone is 16", path)
    magic, version, n, deg, frac, flags, _ = struct.unpack_from("<IIIBBBB", data, 0)
    if magic != SPZ_MAGIC:
        raise InputError(f"not an SPZ file (gzip payload starts with {data[:4]!r}, expected b'NGSP')", path)
    if not 1 <= version <= 3:
        raise InputError(f"unsupported SPZ version {version} in a gzip file (1-3 are)", path)
    if deg > 3:
        raise InputError(f"unsupported SPZ SH degree {deg} (0..3 are)", path)
    sizes = _spz_sizes(n, version, _SH_DIM[deg])
    need = 16 + sum(sizes)
    if len(data) < need or (len(data) > need and not flags & 0x2):
        what = "truncated SPZ:" if len(data) < need else "SPZ counts disagree:"
        raise InputError(f"{what} header says {n} points ({need} bytes), the payload has {len(data)}", path)
    if flags & 0x2:
        _spz_check_extensions(data[need:], path)
    out, pos = [], 16
    for s in sizes:
        out.append(data[pos:pos + s])
        pos += s
    return {"version": version, "n": n, "deg": deg, "frac": frac, "flags": flags}, out


def _spz_rotations(buf: bytes, n: int, version: int) -> np.ndarray:
    """[N, 4] quaternions x,y,z,w (SPZ order, RUB)."""
    if version < 3:  # x,y,z as bytes / 127.5 - 1; w = sqrt(1 - |xyz|^2) >= 0
        xyz = np.frombuffer(buf, np.uint8).reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        return np.concatenate([xyz, np.sqrt(np.maximum(0.0, 1.0 - (xyz ** 2).sum(1)))[:, None]], axis=1)
    comp = np.frombuffer(buf, "<u4").astype(np.int64)  # [N]
    fields = np.stack([(comp >> s) & 0x3FF for s in (20, 10, 0)], axis=1)  # [N, 3] in ascending slot order
    small = _SQRT1_2 * (fields & 0x1FF) / 511.0 * np.where(fields & 0x200, -1.0, 1.0)
    return _place_largest((comp >> 30).astype(np.int64), small)


def load_spz(path) -> Gaussians:
    """Decode a Niantic SPZ file (v4 zstd container or gzip v1-3), converting RUB to the PLY's RDF axes."""
    path = Path(path)
    require_file(path)
    raw = path.read_bytes()
    if raw[:4] == b"NGSP":
        h, sec = _spz_read_v4(raw, path)
    elif raw[:2] == b"\x1f\x8b":
        h, sec = _spz_read_legacy(raw, path)
    else:
        raise InputError(f"not an SPZ file (starts with {raw[:4]!r}; expected b'NGSP' or gzip)", path)
    n, v, deg = h["n"], h["version"], h["deg"]
    if v == 1:
        means = np.frombuffer(sec[0], "<f2").reshape(n, 3).astype(np.float64)
    else:
        b = np.frombuffer(sec[0], np.uint8).reshape(n, 3, 3).astype(np.int64)
        fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)  # [N, 3] 24-bit two's complement
        means = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed) / float(1 << h["frac"])
    logits = _logit_u8(np.frombuffer(sec[1], np.uint8))
    dc = (np.frombuffer(sec[2], np.uint8).reshape(n, 3) / 255.0 - 0.5) / SPZ_COLOR_SCALE
    log_scales = np.frombuffer(sec[3], np.uint8).reshape(n, 3) / 16.0 - 10.0
    xyzw = _spz_rotations(sec[4], n, v)
    dim = _SH_DIM[deg]
    sh = np.zeros((n, 1 + dim, 3))  # [N, K, 3]
    sh[:, 0] = dc
    if dim:  # coefficient-major, channel fastest; legacy (x - 128) / 128
        sh[:, 1:] = (np.frombuffer(sec[5], np.uint8).reshape(n, dim, 3) - 128.0) / 128.0 * _FLIP_SH[:dim, None]
    quats = xyzw[:, [3, 0, 1, 2]] * _FLIP_Q_WXYZ  # RUB x,y,z,w -> RDF w,x,y,z
    return _gaussians(path, means * _FLIP_P, quats, log_scales, logits, sh)


def _spz_sections(a: dict, frac: int) -> list:
    """The six SPZ sections (bytes) of float64 parameters already in RDF, version >= 3 rotations."""
    n, k = a["sh"].shape[:2]
    fixed = np.round(a["means"] * _FLIP_P * (1 << frac)).astype(np.int64)  # [N, 3]
    pos = np.stack([(fixed >> s) & 0xFF for s in (0, 8, 16)], axis=-1).astype(np.uint8)  # [N, 3, 3]
    alphas = _u8(_sigmoid(a["opacity_logits"]) * 255.0)
    colors = _u8(a["sh"][:, 0] * (SPZ_COLOR_SCALE * 255.0) + 127.5)
    scales = _u8((a["log_scales"] + 10.0) * 16.0)
    xyzw = _unit_quats(a["quats"] * _FLIP_Q_WXYZ)[:, [1, 2, 3, 0]]
    qi, small = _largest_first(xyzw)
    fields = (np.abs(small) / _SQRT1_2 * 511.0 + 0.5).astype(np.int64).clip(0, 511) | ((small < 0).astype(np.int64) << 9)
    comp = (qi << 30) | (fields[:, 0] << 20) | (fields[:, 1] << 10) | fields[:, 2]
    sh = b""
    if k > 1:
        q = np.round(a["sh"][:, 1:] * _FLIP_SH[:k - 1, None] * 128.0) + 128.0  # [N, K-1, 3]
        bucket = np.where(np.arange(k - 1) < 3, SPZ_SH_BUCKET[1], SPZ_SH_BUCKET[2])[None, :, None]
        sh = np.clip((q + bucket // 2) // bucket * bucket, 0, 255).astype(np.uint8).tobytes()
    return [pos.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(), comp.astype("<u4").tobytes(), sh]


def save_spz(g: Gaussians, path, version: int = 3) -> None:
    """Write ``g`` as SPZ, atomically: version 3 (gzip; every SPZ reader loads it) or 4 (zstd streams).
    Positions use 12 fractional bits unless the scene is too large for 24-bit fixed point."""
    path = Path(path)
    if version not in (3, 4):
        raise InputError(f"can only write SPZ version 3 or 4, not {version}", path)
    a = _params(g, path)
    n, k = a["sh"].shape[:2]
    deg = {1: 0, 4: 1, 9: 2, 16: 3}[k]
    extent = float(np.abs(a["means"]).max()) if n else 0.0
    frac = SPZ_FRACTIONAL_BITS
    while frac > 0 and extent * (1 << frac) >= (1 << 23) - 1:
        frac -= 1
    if extent * (1 << frac) >= (1 << 23) - 1:
        raise InputError(f"scene extends to {extent:.3g}; SPZ's 24-bit positions cannot hold it", path)
    sec = _spz_sections(a, frac)
    if version == 3:
        payload = struct.pack("<IIIBBBB", SPZ_MAGIC, 3, n, deg, frac, 0, 0) + b"".join(sec)
        data = gzip.compress(payload, compresslevel=6, mtime=0)
    else:
        import zstandard  # lazy: only version 4 needs it (as in _spz_read_v4)

        cz = zstandard.ZstdCompressor(level=SPZ_ZSTD_LEVEL)
        streams = [(cz.compress(s), len(s)) for s in sec if s]
        head = struct.pack("<IIIBBBBI12x", SPZ_MAGIC, 4, n, deg, frac, 0, len(streams), 32)
        toc = b"".join(struct.pack("<QQ", len(c), u) for c, u in streams)
        data = head + toc + b"".join(c for c, _ in streams)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


__all__ = ["load_compressed_ply", "save_compressed_ply", "load_spz", "save_spz", "is_compressed_ply_header",
           "is_spz_bytes"]
