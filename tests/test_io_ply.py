"""PLY / .splat: round trips against files written independently with plyfile, and every bad input."""
import time

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from tlvg_warp import InputError, load_ply, save_ply
from tlvg_warp.io.ply import load_splat, save_splat
from tlvg_warp.types import SH_C0, Gaussians

SPLAT_COLOR_TOL = 0.5 / 255 + 1e-6  # rounding to the nearest of 256 levels, plus float slack
SPLAT_ROT_TOL = 0.5 / 128 + 1e-6  # q*128+128 rounded: half a step of 1/128 per component
SPLAT_ROT_RENORM_TOL = 4 * SPLAT_ROT_TOL  # after renormalizing the quantized quaternion (norm error ~2 steps)


def _params(n, degree, seed=0):
    r = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return dict(xyz=r.normal(size=(n, 3)).astype(np.float32), sh=r.normal(size=(n, k, 3)).astype(np.float32),
                opacity=r.normal(size=n).astype(np.float32), scale=(r.normal(size=(n, 3)) - 3).astype(np.float32),
                rot=r.normal(size=(n, 4)).astype(np.float32))


def _write_plyfile(path, p, order_seed=1, drop=(), normals=False, text=False):
    """A Gaussian PLY in a shuffled property order, written by plyfile (independent of save_ply)."""
    n, k = p["sh"].shape[:2]
    cols = {**{a: p["xyz"][:, i] for i, a in enumerate("xyz")},
            **{f"f_dc_{c}": p["sh"][:, 0, c] for c in range(3)},
            # channel-major: f_rest index = c * (K-1) + (coefficient - 1)
            **{f"f_rest_{c * (k - 1) + j}": p["sh"][:, 1 + j, c] for c in range(3) for j in range(k - 1)},
            "opacity": p["opacity"], **{f"scale_{i}": p["scale"][:, i] for i in range(3)},
            **{f"rot_{i}": p["rot"][:, i] for i in range(4)}}
    if normals:
        cols.update(nx=np.zeros(n, np.float32), ny=np.zeros(n, np.float32), nz=np.ones(n, np.float32))
    names = [c for c in cols if c not in drop]
    np.random.default_rng(order_seed).shuffle(names)
    arr = np.empty(n, [(c, "f4") for c in names])
    for c in names:
        arr[c] = cols[c]
    PlyData([PlyElement.describe(arr, "vertex")], text=text).write(str(path))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_load_independent_file_any_order_without_normals(tmp_path, degree):
    p = _params(500, degree)
    _write_plyfile(tmp_path / "a.ply", p)
    g = load_ply(tmp_path / "a.ply")
    assert g.sh_degree == degree and g.dtype == torch.float32 and g.device.type == "cpu"
    assert np.array_equal(g.means.numpy(), p["xyz"]) and np.array_equal(g.sh.numpy(), p["sh"])
    assert np.array_equal(g.quats.numpy(), p["rot"]) and np.array_equal(g.log_scales.numpy(), p["scale"])
    assert np.array_equal(g.opacity_logits.numpy(), p["opacity"])


def test_ascii_and_normals(tmp_path):
    p = _params(20, 1)
    _write_plyfile(tmp_path / "a.ply", p, normals=True, text=True)
    g = load_ply(tmp_path / "a.ply")
    assert np.array_equal(g.sh.numpy(), p["sh"]) and np.array_equal(g.means.numpy(), p["xyz"])


def test_save_writes_inria_order_bit_exact(tmp_path):
    p = _params(300, 3)
    _write_plyfile(tmp_path / "in.ply", p)
    save_ply(load_ply(tmp_path / "in.ply"), tmp_path / "out.ply")
    v = PlyData.read(str(tmp_path / "out.ply"))["vertex"]
    expect = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
              + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert [q.name for q in v.properties] == expect
    assert all(v[name].dtype == np.dtype("<f4") for name in expect)
    assert np.array_equal(v["f_rest_15"], p["sh"][:, 1, 1])  # G channel block starts at 15 (channel-major)
    assert np.array_equal(v["f_rest_44"], p["sh"][:, 15, 2])
    assert np.array_equal(v["rot_0"], p["rot"][:, 0]) and np.array_equal(v["scale_2"], p["scale"][:, 2])
    assert not np.any(v["nx"])
    # and our own reader round-trips it bit for bit
    g2 = load_ply(tmp_path / "out.ply")
    assert np.array_equal(g2.sh.numpy(), p["sh"]) and np.array_equal(g2.opacity_logits.numpy(), p["opacity"])


def test_float64_gaussians_saved_as_float32(tmp_path):
    g = Gaussians.from_colors(torch.rand(10, 3, dtype=torch.float64), torch.rand(10, 3, dtype=torch.float64), 0.1)
    save_ply(g, tmp_path / "g.ply")
    assert np.array_equal(load_ply(tmp_path / "g.ply").means.numpy(), g.means.float().numpy())


SPEED_N = 300_000
SPEED_LIMIT_S = 6.0  # save + load of 300k degree-3 Gaussians (~75 MB); vectorized code takes ~0.5 s, a
#                      per-Gaussian Python loop takes minutes, so the bound fails only the wrong design


def test_speed(tmp_path):
    p = _params(SPEED_N, 3)
    g = Gaussians(*(torch.from_numpy(p[k]) for k in ("xyz", "rot", "scale", "opacity", "sh")))
    t = time.perf_counter()
    save_ply(g, tmp_path / "big.ply")
    h = load_ply(tmp_path / "big.ply")
    assert time.perf_counter() - t < SPEED_LIMIT_S
    assert torch.equal(h.sh, g.sh)


def test_splat_matches_independent_decode(tmp_path):
    p = _params(400, 2)
    g = Gaussians(*(torch.from_numpy(p[k]) for k in ("xyz", "rot", "scale", "opacity", "sh")))
    save_splat(g, tmp_path / "a.splat")
    raw = np.fromfile(tmp_path / "a.splat", np.uint8).reshape(-1, 32)  # decode by byte offsets
    pos = raw[:, 0:12].copy().view("<f4")
    scale = raw[:, 12:24].copy().view("<f4")
    rgba, rot = raw[:, 24:28] / 255.0, (raw[:, 28:32] - 128.0) / 128.0
    # the file is sorted; match rows to the source by their (exact) positions
    src = np.lexsort(p["xyz"].T[::-1])
    got = np.lexsort(pos.T[::-1])
    assert np.array_equal(pos[got], p["xyz"][src])
    assert np.allclose(scale[got], np.exp(p["scale"][src]), rtol=1e-6)
    color = np.clip(0.5 + SH_C0 * p["sh"][src, 0], 0, 1)
    assert np.abs(rgba[got, :3] - color).max() <= SPLAT_COLOR_TOL
    assert np.abs(rgba[got, 3] - 1 / (1 + np.exp(-p["opacity"][src]))).max() <= SPLAT_COLOR_TOL
    q = p["rot"][src] / np.linalg.norm(p["rot"][src], axis=1, keepdims=True)
    assert np.abs(rot[got] - q).max() <= SPLAT_ROT_TOL
    # importance order as antimatter15's convert.py: size x opacity, descending
    perm = np.empty_like(got)
    perm[got] = src  # file row i holds source Gaussian perm[i]
    imp = np.exp(p["scale"][perm].astype(np.float64).sum(1)) / (1 + np.exp(-p["opacity"][perm].astype(np.float64)))
    assert np.all(np.diff(imp) <= 1e-6 * imp[:-1])
    h = load_splat(tmp_path / "a.splat")
    assert h.sh_degree == 0 and np.array_equal(h.means.numpy(), pos)
    back_rgb = h.sh[:, 0].numpy() * SH_C0 + 0.5
    assert np.abs(back_rgb[got] - color).max() <= SPLAT_COLOR_TOL
    assert np.abs(torch.sigmoid(h.opacity_logits).numpy()[got] - 1 / (1 + np.exp(-p["opacity"][src]))).max() \
        <= SPLAT_COLOR_TOL
    dots = np.abs(np.sum(h.quats.numpy()[got] * q, 1))  # q and -q are the same rotation
    assert np.all(1 - dots <= SPLAT_ROT_RENORM_TOL)


# --- bad input ----------------------------------------------------------------------------------------------
def _raises(fn, *words):
    with pytest.raises(InputError) as e:
        fn()
    msg = str(e.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)
    return msg


def test_truncated_ply(tmp_path):
    _write_plyfile(tmp_path / "t.ply", _params(50, 1))
    data = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[:-100])
    _raises(lambda: load_ply(tmp_path / "t.ply"), "t.ply", "truncated")
    (tmp_path / "h.ply").write_bytes(data[:60])  # cut inside the header
    _raises(lambda: load_ply(tmp_path / "h.ply"), "h.ply", "header")


def test_missing_properties_named(tmp_path):
    _write_plyfile(tmp_path / "m.ply", _params(5, 0), drop=("opacity", "rot_2"))
    _raises(lambda: load_ply(tmp_path / "m.ply"), "m.ply", "opacity", "rot_2")


def test_bad_f_rest_count(tmp_path):
    _write_plyfile(tmp_path / "r.ply", _params(5, 1), drop=("f_rest_8",))
    _raises(lambda: load_ply(tmp_path / "r.ply"), "r.ply", "f_rest")


def test_nan_values_counted_and_located(tmp_path):
    p = _params(40, 1)
    p["scale"][[3, 7], 1] = np.nan
    p["xyz"][5, 0] = np.inf
    _write_plyfile(tmp_path / "n.ply", p)
    msg = _raises(lambda: load_ply(tmp_path / "n.ply"), "n.ply", "3 NaN/infinite", "2 in scale_1", "1 in x")
    assert "opacity" not in msg


def test_not_a_ply_and_missing_path(tmp_path):
    (tmp_path / "x.ply").write_bytes(b"hello world\n")
    _raises(lambda: load_ply(tmp_path / "x.ply"), "x.ply", "not a PLY")
    _raises(lambda: load_ply(tmp_path / "nope.ply"), "nope.ply", "does not exist")
    _raises(lambda: load_splat(tmp_path / "nope.splat"), "nope.splat", "does not exist")


def test_truncated_splat(tmp_path):
    save_splat(Gaussians.from_colors(torch.rand(4, 3), torch.rand(4, 3), 0.1), tmp_path / "s.splat")
    (tmp_path / "s.splat").write_bytes((tmp_path / "s.splat").read_bytes()[:-5])
    _raises(lambda: load_splat(tmp_path / "s.splat"), "s.splat", "truncated")


def test_save_refuses_nan_and_leaves_no_file(tmp_path):
    g = Gaussians.from_colors(torch.rand(4, 3), torch.rand(4, 3), 0.1)
    good = tmp_path / "keep.ply"
    save_ply(g, good)
    before = good.read_bytes()
    g.means[1, 2] = float("nan")
    _raises(lambda: save_ply(g, good), "keep.ply", "1 in means")
    assert good.read_bytes() == before  # the previous file is untouched
    assert sorted(x.name for x in tmp_path.iterdir()) == ["keep.ply"]  # no temporary left behind
