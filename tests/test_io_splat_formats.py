"""PlayCanvas compressed PLY and Niantic SPZ: the two shipped biker files agree within their
quantization, our writers round-trip within the formats' closed-form step sizes, files we write decode the
same in an independent scalar decoder (and in gsply when installed), and bad files fail with one line."""
from __future__ import annotations

import gzip
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from tlvg_warp.errors import InputError
from tlvg_warp.io import load_ply
from tlvg_warp.io.ply import save_scene, scene_kind
from tlvg_warp.io.splat_formats import load_compressed_ply, load_spz, save_compressed_ply, save_spz
from tlvg_warp.types import SH_C0, Gaussians

SPLATS = Path(__file__).resolve().parents[2] / "shared" / "data" / "splats"
BIKER_CPLY, BIKER_SPZ = SPLATS / "biker.compressed.ply", SPLATS / "biker.spz"
BIKER_N = 152_746

# --- the formats' quantization, in closed form (a half step of each code) -------------------------------------
F32 = 2e-6  # float32 arithmetic slop on values of order 1-10 (a few ulp)
SPZ_POS = 0.5 / 4096  # 24-bit fixed point with 12 fractional bits
SPZ_LOG_SCALE = 0.5 / 16  # byte = (log s + 10) * 16
SPZ_LOG_SCALE_RANGE = (-10.0, 255 / 16 - 10)  # what one byte can hold; SPZ clamps outside it
SPZ_DC = 0.5 / (0.15 * 255)  # byte = dc * 0.15 * 255 + 127.5
SPZ_SH = {1: 4.5 / 128, 2: 8.5 / 128}  # round(x*128) then 5-bit (degree 1) or 4-bit (higher) buckets
ALPHA = 0.5 / 255  # both formats store sigmoid(opacity) in 8 bits
SPZ_QUAT = 0.5 * math.sqrt(0.5) / 511  # per stored component: sign + 9-bit magnitude over [0, 1/sqrt2]
CPLY_QUAT = 0.5 * math.sqrt(2) / 1023  # per stored component: 10-bit unorm over [-1/sqrt2, 1/sqrt2]
CPLY_SH = 4 / 255  # half of a byte step over [-4, 4]


def quat_angle_bound(h: float) -> float:
    """Rotation angle bound when each of the 3 stored components is off by <= h: the derived largest one
    (>= 1/2) is then off by <= 3h, |dq| <= sqrt(3 h^2 + 9 h^2), and the angle 2 acos|q.q'| ~ 2|dq|."""
    return 2 * math.sqrt(12) * h * 1.01


def quat_angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # [N] radians, sign-blind
    a = a.double() / a.double().norm(dim=1, keepdim=True)
    b = b.double() / b.double().norm(dim=1, keepdim=True)
    return 2 * torch.acos((a * b).sum(1).abs().clamp(max=1.0))


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    """Values of a trained scene's ranges, not already on any quantization grid."""
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    sh = (torch.rand(n, k, 3, generator=g, dtype=torch.float64) - 0.5) * 1.6  # rest in [-0.8, 0.8]
    sh[:, 0] = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 1.1 - 0.55) / SH_C0  # rgb in [-0.05, 1.05]
    return Gaussians(means=(torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 6,
                     quats=torch.randn(n, 4, generator=g, dtype=torch.float64),
                     log_scales=torch.rand(n, 3, generator=g, dtype=torch.float64) * 6 - 8,
                     opacity_logits=torch.randn(n, generator=g, dtype=torch.float64) * 3,
                     sh=sh).to(dtype=torch.float32)


def chunk_table(path: Path) -> np.ndarray:
    """[C, 18] chunk bounds read with plyfile (a parser independent of ours)."""
    from plyfile import PlyData

    el = PlyData.read(str(path))["chunk"].data
    return np.stack([el[name].astype(np.float64) for name in el.dtype.names], axis=1)


def needs_biker():
    if not (BIKER_CPLY.is_file() and BIKER_SPZ.is_file()):
        pytest.skip("../shared/data/splats (biker) is absent in this checkout")


# --- the two shipped files hold one scene ---------------------------------------------------------------------
def test_biker_compressed_ply_and_spz_agree_within_quantization():
    needs_biker()
    a, b = load_ply(BIKER_CPLY), load_ply(BIKER_SPZ)  # dispatch by header from the generic loader
    assert a.num == b.num == BIKER_N and a.sh_degree == b.sh_degree == 0
    ch = chunk_table(BIKER_CPLY)[np.arange(BIKER_N) // 256]  # [N, 18] each Gaussian's chunk bounds
    half = 0.5 / np.array([2047.0, 1023.0, 2047.0])  # 11/10/11-bit unorm half steps
    pos_tol = (ch[:, 3:6] - ch[:, 0:3]) * half + SPZ_POS + F32  # [N, 3]
    assert np.all((a.means - b.means).abs().numpy() <= pos_tol)
    lo, hi = SPZ_LOG_SCALE_RANGE  # SPZ cannot hold log scales below -10: the writer clamped them there
    scale_tol = (ch[:, 9:12] - ch[:, 6:9]) * half + SPZ_LOG_SCALE + F32
    assert np.all((a.log_scales.clamp(lo, hi) - b.log_scales).abs().numpy() <= scale_tol)
    rgb_tol = (ch[:, 15:18] - ch[:, 12:15]) / 255 / 2 + SPZ_DC * SH_C0 + F32
    assert np.all(((a.sh[:, 0] - b.sh[:, 0]) * SH_C0).abs().numpy() <= rgb_tol)
    assert (a.opacities - b.opacities).abs().max() <= 2 * ALPHA + F32
    ang = quat_angle(a.quats, b.quats)
    assert ang.max() <= quat_angle_bound(CPLY_QUAT + SPZ_QUAT)


# --- our writers ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("degree", [0, 2])
def test_compressed_ply_round_trip_within_chunk_quantization(tmp_path, degree):
    g = random_gaussians(700, degree)  # 3 chunks, the last one partial
    path = tmp_path / "s.compressed.ply"
    order = torch.from_numpy(save_compressed_ply(g, path))
    assert sorted(order.tolist()) == list(range(g.num))
    r, src = load_ply(path), g.subset(order)
    ch = chunk_table(path)[np.arange(g.num) // 256]
    half = 0.5 / np.array([2047.0, 1023.0, 2047.0])
    assert np.all((r.means - src.means).abs().numpy() <= (ch[:, 3:6] - ch[:, 0:3]) * half + F32)
    assert np.all((r.log_scales - src.log_scales).abs().numpy() <= (ch[:, 9:12] - ch[:, 6:9]) * half + F32)
    rgb_err = ((r.sh[:, 0] - src.sh[:, 0]) * SH_C0).abs().numpy()
    assert np.all(rgb_err <= (ch[:, 15:18] - ch[:, 12:15]) / 510 + F32)
    assert (r.opacities - src.opacities).abs().max() <= ALPHA + F32
    assert quat_angle(r.quats, src.quats).max() <= quat_angle_bound(CPLY_QUAT)
    assert r.sh_degree == degree
    if degree:
        assert (r.sh[:, 1:] - src.sh[:, 1:]).abs().max() <= CPLY_SH + F32


def test_compressed_ply_chunks_are_spatially_compact(tmp_path):
    """Morton order: 16 chunks of 256 uniform points; each chunk's box is a fraction of the scene's (in file
    order of the random input, 256 points would span ~97% of it), so the quantization steps shrink alike."""
    g = random_gaussians(4096, 0, seed=5)
    save_compressed_ply(g, tmp_path / "m.compressed.ply")
    box = chunk_table(tmp_path / "m.compressed.ply")
    frac = np.prod(box[:, 3:6] - box[:, 0:3], axis=1) / np.prod(np.ptp(g.means.numpy(), axis=0))  # [C]
    assert frac.mean() < 0.25  # measured 0.15


@pytest.mark.parametrize("version,degree", [(3, 1), (4, 3), (4, 0)])
def test_spz_round_trip_within_quantization(tmp_path, version, degree):
    g = random_gaussians(500, degree, seed=version)
    path = tmp_path / "s.spz"
    save_spz(g, path, version=version)
    assert path.read_bytes()[:4] == (b"NGSP" if version == 4 else b"\x1f\x8b\x08\x00")
    r = load_ply(path)
    assert r.num == g.num and r.sh_degree == degree
    assert (r.means - g.means).abs().max() <= SPZ_POS + F32
    assert (r.log_scales - g.log_scales).abs().max() <= SPZ_LOG_SCALE + F32
    assert (r.sh[:, 0] - g.sh[:, 0]).abs().max() <= SPZ_DC + F32
    assert (r.opacities - g.opacities).abs().max() <= ALPHA + F32
    assert quat_angle(r.quats, g.quats).max() <= quat_angle_bound(SPZ_QUAT)
    if degree:
        assert (r.sh[:, 1:4] - g.sh[:, 1:4]).abs().max() <= SPZ_SH[1] + F32
        assert (r.sh[:, 4:] - g.sh[:, 4:]).abs().max() <= SPZ_SH[2] + F32 if degree > 1 else True


def test_save_scene_picks_the_format_by_name(tmp_path):
    """save_scene writes by name; scene_kind reads the kind back from the content (the name only for .splat)."""
    g = random_gaussians(40, 0)
    for name, head, kind in (("a.compressed.ply", b"ply\n", "compressed_ply"), ("a.spz", b"\x1f\x8b", "spz"),
                             ("a.ply", b"ply\n", "ply"), ("a.splat", None, "splat")):
        save_scene(g, tmp_path / name)
        assert head is None or (tmp_path / name).read_bytes().startswith(head)
        assert scene_kind(tmp_path / name) == kind, name
    assert (tmp_path / "a.splat").stat().st_size == 32 * g.num
    (tmp_path / "b.spz").write_bytes((tmp_path / "a.ply").read_bytes())  # the content decides, not the name
    assert scene_kind(tmp_path / "b.spz") == "ply"
    assert "packed_position" in (tmp_path / "a.compressed.ply").read_bytes()[:2000].decode("ascii", "replace")
    assert "packed_position" not in (tmp_path / "a.ply").read_bytes()[:2000].decode("ascii", "replace")


# --- an independent decoder: one Gaussian at a time, python ints, straight from the format texts --------------
def _scalar_cply(path: Path, rows: int):
    data = path.read_bytes()
    body = data[data.index(b"end_header\n") + 11:]
    nchunk = int(data.split(b"element chunk ")[1].split(b"\n")[0])
    out = []
    for i in range(rows):
        c = struct.unpack_from("<18f", body, (i // 256) * 72)
        p, rot, s, col = struct.unpack_from("<4I", body, nchunk * 72 + 16 * i)
        un = lambda v, b: (v & ((1 << b) - 1)) / ((1 << b) - 1)  # noqa: E731
        t3 = lambda v: (un(v >> 21, 11), un(v >> 11, 10), un(v, 11))  # noqa: E731
        pos = [c[j] + (c[j + 3] - c[j]) * t for j, t in enumerate(t3(p))]
        sc = [c[6 + j] + (c[9 + j] - c[6 + j]) * t for j, t in enumerate(t3(s))]
        rgb = [c[12 + j] + (c[15 + j] - c[12 + j]) * un(col >> (24 - 8 * j), 8) for j in range(3)]
        abc = [(un(rot >> sh, 10) - 0.5) * math.sqrt(2) for sh in (20, 10, 0)]
        q = list(abc)
        q.insert(rot >> 30, math.sqrt(max(0.0, 1 - sum(x * x for x in abc))))  # w,x,y,z with the largest back
        out.append((pos, q, sc, un(col, 8), rgb))
    return out


def _scalar_spz(path: Path, rows: int):
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        data = gzip.decompress(raw)
        n = struct.unpack_from("<I", data, 8)[0]
        frac, off = data[13], 16
        sec, sizes = [], [9 * n, n, 3 * n, 3 * n, 4 * n]
        for s in sizes:
            sec.append(data[off:off + s])
            off += s
    else:
        import zstandard

        n, frac, nst, toc = struct.unpack_from("<I", raw, 8)[0], raw[13], raw[15], struct.unpack_from("<I", raw, 16)[0]
        off, sec = toc + 16 * nst, []
        for j in range(nst):
            cs, us = struct.unpack_from("<QQ", raw, toc + 16 * j)
            sec.append(zstandard.ZstdDecompressor().decompress(raw[off:off + cs], max_output_size=us))
            off += cs
    out = []
    for i in range(rows):
        xyz = []
        for j in range(3):
            v = int.from_bytes(sec[0][9 * i + 3 * j:9 * i + 3 * j + 3], "little", signed=True)
            xyz.append(v / (1 << frac) * (1 if j == 0 else -1))  # RUB -> RDF
        comp = struct.unpack_from("<I", sec[4], 4 * i)[0]
        largest, vals = comp >> 30, []
        for k in range(3):  # the first stored slot sits in the highest bits
            f = (comp >> (20 - 10 * k)) & 0x3FF
            vals.append((f & 0x1FF) / 511 * math.sqrt(0.5) * (-1 if f & 0x200 else 1))
        vals.insert(largest, math.sqrt(max(0.0, 1 - sum(v * v for v in vals))))
        x, y, z, w = vals
        q = [w, x, -y, -z]
        sc = [sec[3][3 * i + j] / 16 - 10 for j in range(3)]
        dc = [(sec[2][3 * i + j] / 255 - 0.5) / 0.15 for j in range(3)]
        out.append((xyz, q, sc, sec[1][i] / 255, dc))
    return out


@pytest.mark.parametrize("fmt", ["compressed.ply", "spz3", "spz4"])
def test_files_we_write_decode_the_same_in_a_scalar_decoder(tmp_path, fmt):
    g = random_gaussians(300, 0, seed=7)
    path = tmp_path / ("s.compressed.ply" if fmt == "compressed.ply" else "s.spz")
    if fmt == "compressed.ply":
        save_compressed_ply(g, path)
        ref = _scalar_cply(path, 300)
    else:
        save_spz(g, path, version=int(fmt[-1]))
        ref = _scalar_spz(path, 300)
    ours = load_ply(path)
    pos, q, sc, alpha, col = (torch.tensor([r[j] for r in ref], dtype=torch.float64) for j in range(5))
    assert torch.allclose(ours.means.double(), pos, atol=F32)
    assert torch.allclose(ours.log_scales.double(), sc, atol=F32)
    assert quat_angle(ours.quats, q).max() < 1e-3  # float32 acos near 1 resolves ~3e-4 rad
    assert torch.allclose(ours.opacities.double(), alpha.clamp(0.5 / 255, 1 - 0.5 / 255), atol=F32)
    dc = ours.sh[:, 0].double()
    assert torch.allclose(dc * SH_C0 + 0.5 if fmt == "compressed.ply" else dc, col, atol=1e-5)


# --- gsply (an independent Python implementation), when installed ---------------------------------------------
def _gsply():
    return pytest.importorskip("gsply", reason="gsply is not installed (pip install -e '.[interop]')")


def _as_t(x, flip=1.0):
    return torch.from_numpy(np.asarray(x, dtype=np.float64)) * flip


FLIP_P, FLIP_Q = torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64), torch.tensor([1.0, 1, -1, -1], dtype=torch.float64)


def _compare_gsply(ours: Gaussians, theirs, rub: bool):
    """gsply keeps SPZ in its stored RUB axes; we convert to the PLY's RDF."""
    assert torch.allclose(ours.means.double(), _as_t(theirs.means, FLIP_P if rub else 1.0), atol=F32)
    assert torch.allclose(ours.log_scales.double(), _as_t(theirs.scales), atol=F32)
    assert quat_angle(ours.quats, _as_t(theirs.quats, FLIP_Q if rub else 1.0)).max() < 1e-3
    assert torch.allclose(ours.sh[:, 0].double(), _as_t(theirs.sh0), atol=1e-5)
    # logits of a saturated byte (0 or 255) differ by clamp convention; the opacities agree within it
    assert (ours.opacities.double() - torch.sigmoid(_as_t(theirs.opacities))).abs().max() <= ALPHA + F32


def test_gsply_decodes_the_biker_files_as_we_do():
    gsply = _gsply()
    needs_biker()
    _compare_gsply(load_compressed_ply(BIKER_CPLY), gsply.plyread(str(BIKER_CPLY)), rub=False)
    _compare_gsply(load_spz(BIKER_SPZ), gsply.read_spz(str(BIKER_SPZ)), rub=True)


def test_gsply_reads_files_we_write(tmp_path):
    gsply = _gsply()
    g = random_gaussians(600, 0, seed=3)
    save_compressed_ply(g, tmp_path / "a.compressed.ply")
    _compare_gsply(load_ply(tmp_path / "a.compressed.ply"), gsply.plyread(str(tmp_path / "a.compressed.ply")), False)
    for v in (3, 4):
        save_spz(g, tmp_path / f"a{v}.spz", version=v)
        _compare_gsply(load_ply(tmp_path / f"a{v}.spz"), gsply.read_spz(str(tmp_path / f"a{v}.spz")), True)


# --- bad input: one line naming the file ------------------------------------------------------------------------
def _expect_input_error(path: Path, *words):
    with pytest.raises(InputError) as e:
        load_ply(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg, msg
    for w in words:
        assert w in msg.lower(), msg


@pytest.fixture(scope="module")
def good_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("good")
    g = random_gaussians(300, 1, seed=11)
    save_compressed_ply(g, d / "g.compressed.ply")
    save_spz(g, d / "g3.spz", version=3)
    save_spz(g, d / "g4.spz", version=4)
    return {k: (d / n).read_bytes() for k, n in (("cply", "g.compressed.ply"), ("spz3", "g3.spz"), ("spz4", "g4.spz"))}


@pytest.mark.parametrize("kind", ["cply", "spz3", "spz4"])
def test_truncated_files(tmp_path, good_files, kind):
    p = tmp_path / ("t.compressed.ply" if kind == "cply" else "t.spz")
    p.write_bytes(good_files[kind][:-100])
    _expect_input_error(p, "trunc")
    p.write_bytes(good_files[kind][:20])  # inside the header
    with pytest.raises(InputError, match="t\\."):
        load_ply(p)


def test_wrong_magic(tmp_path, good_files):
    p = tmp_path / "m.spz"
    p.write_bytes(b"XXXX" + good_files["spz4"][4:])
    with pytest.raises(InputError) as e:
        load_spz(p)
    assert "not an spz" in str(e.value).lower() and str(p) in str(e.value)
    gz = gzip.decompress(good_files["spz3"])
    p.write_bytes(gzip.compress(b"NGSQ" + gz[4:]))
    _expect_input_error(p, "not an spz")


def test_unsupported_versions(tmp_path, good_files):
    p = tmp_path / "v.spz"
    raw = bytearray(good_files["spz4"])
    raw[4:8] = struct.pack("<I", 5)
    p.write_bytes(bytes(raw))
    _expect_input_error(p, "unsupported spz version 5")
    gz = bytearray(gzip.decompress(good_files["spz3"]))
    gz[4:8] = struct.pack("<I", 9)
    p.write_bytes(gzip.compress(bytes(gz)))
    _expect_input_error(p, "unsupported spz version 9")


def test_counts_that_disagree_with_the_data(tmp_path, good_files):
    p = tmp_path / "c.spz"
    raw = bytearray(good_files["spz4"])
    raw[8:12] = struct.pack("<I", 299)  # header count one short of what the streams hold
    p.write_bytes(bytes(raw))
    _expect_input_error(p, "disagree")
    gz = bytearray(gzip.decompress(good_files["spz3"]))
    gz[8:12] = struct.pack("<I", 250)
    p.write_bytes(gzip.compress(bytes(gz)))
    _expect_input_error(p, "disagree")
    q = tmp_path / "c.compressed.ply"
    q.write_bytes(good_files["cply"].replace(b"element chunk 2\n", b"element chunk 3\n"))
    _expect_input_error(q, "disagree")
    q.write_bytes(good_files["cply"].replace(b"element sh 300\n", b"element sh 299\n"))
    _expect_input_error(q, "disagree")


def test_nan_after_decoding(tmp_path, good_files):
    data = good_files["cply"]
    start = data.index(b"end_header\n") + 11
    q = tmp_path / "n.compressed.ply"
    q.write_bytes(data[:start] + struct.pack("<f", float("nan")) + data[start + 4:])  # chunk 0 min_x
    _expect_input_error(q, "nan")
    # SPZ v1 stores float16 positions: a NaN there decodes to NaN
    n = 4
    payload = (struct.pack("<IIIBBBB", 0x5053474E, 1, n, 0, 12, 0, 0) + np.full(3 * n, np.nan, "<f2").tobytes()
               + bytes(n) + bytes(3 * n) + bytes(3 * n) + bytes(3 * n))
    p = tmp_path / "n.spz"
    p.write_bytes(gzip.compress(payload))
    _expect_input_error(p, "nan")
