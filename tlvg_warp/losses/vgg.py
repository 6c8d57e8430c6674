"""VGG-16 relu3_1/3_2/3_3 features (torchvision layout, indices 11/13/15, 768 channels at 1/4 resolution).

torchvision is not a dependency: the first 16 modules of ``torchvision.models.vgg16().features`` are
rebuilt here with the same indices, so a torchvision state dict (``vgg16-397923af.pth``) loads as is.
"""
from __future__ import annotations

import os
import socket
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..errors import InputError

VGG_URL = "https://download.pytorch.org/models/vgg16-397923af.pth"
VGG_FILE = "vgg16-397923af.pth"
ENV_VAR = "TLVG_VGG_WEIGHTS"
FEATURE_IDX = (11, 13, 15)  # relu3_1, relu3_2, relu3_3
LAST_IDX = 15
DOWNLOAD_TIMEOUT_S = 10.0  # per socket operation; an offline machine fails fast instead of hanging
RANDOM_SEED = 0
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
STYLE_HEIGHT = 256  # SPEC §3: the style image is resized to height 256 before VGG
RENDER_SCALE = 0.5  # SPEC §3: the render is downscaled x0.5 before VGG

# torchvision vgg16 "D" config up to relu3_3: channels per conv, "M" = max pool
_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256)


def how_to_get_weights() -> str:
    home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch")) / "hub" / "checkpoints"
    return (f"download {VGG_URL} and pass it with --vgg-weights PATH (or set {ENV_VAR}=PATH, or put it in "
            f"{home}/); for a smoke run without weights use --vgg-weights random")


class VGG16Relu3(nn.Module):
    """``features`` holds torchvision's modules 0..15; forward returns relu3_1|relu3_2|relu3_3 [B,768,H/4,W/4]."""

    def __init__(self):
        super().__init__()
        layers, cin = [], 3
        for v in _CFG:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(inplace=False)]
                cin = v
        self.features = nn.Sequential(*layers)
        assert len(self.features) == LAST_IDX + 1
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.is_random = False
        self.source = "uninitialized"

    def forward(self, img: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
        """img: [H,W,3] or [B,3,H,W] in [0,1]; ``scale`` resizes first (bilinear, antialiased when shrinking).
        Runs under the caller's grad mode. Returns [B,768,h,w]."""
        x = img.permute(2, 0, 1).unsqueeze(0) if img.dim() == 3 else img  # [B,3,H,W]
        x = x.to(self.mean.dtype)
        if scale != 1.0:
            x = F.interpolate(x, scale_factor=scale, mode="bilinear", align_corners=False, antialias=scale < 1)
        if min(x.shape[-2:]) < MIN_SIDE:  # two 2x poolings need room: upsample tiny inputs instead of failing
            f = MIN_SIDE / min(x.shape[-2:])
            size = (max(MIN_SIDE, round(x.shape[-2] * f)), max(MIN_SIDE, round(x.shape[-1] * f)))
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        x = (x - self.mean) / self.std
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in FEATURE_IDX:
                out.append(x)
        return torch.cat(out, dim=1)  # [B,768,H/4,W/4]


MIN_SIDE = 16  # smallest side fed to VGG: relu3 features are then at least 4x4 cells


def flatten_feats(f: torch.Tensor) -> torch.Tensor:
    """[1,C,h,w] (or [C,h,w]) -> [C, h*w], the layout the style losses take (pixels row-major)."""
    return f.reshape(f.shape[-3], -1)


def resize_style(style: np.ndarray, height: int = STYLE_HEIGHT) -> np.ndarray:
    """Resize a painting [h,w,3] float to ``height`` rows keeping aspect (INTER_AREA, SPEC §3)."""
    h, w = style.shape[:2]
    new_w = max(1, round(w * height / h))
    interp = cv2.INTER_AREA if height < h else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(style, dtype=np.float32), (new_w, height), interpolation=interp)


def _random_init(net: VGG16Relu3, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    for m in net.features:
        if isinstance(m, nn.Conv2d):  # torchvision's VGG init: kaiming normal (fan_out, relu), zero bias
            std = (2.0 / (m.out_channels * m.kernel_size[0] * m.kernel_size[1])) ** 0.5
            with torch.no_grad():
                m.weight.copy_(torch.randn(m.weight.shape, generator=g) * std)
                m.bias.zero_()


def _load_file(net: VGG16Relu3, path: Path) -> None:
    if not path.is_file():
        raise InputError(f"VGG-16 weights not found; {how_to_get_weights()}", path)
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # truncated download, wrong format
        raise InputError(f"cannot read VGG-16 weights ({type(e).__name__}: {e}); {how_to_get_weights()}", path)
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise InputError(f"not a state dict (got {type(sd).__name__}); expected torchvision's {VGG_FILE}", path)
    # keep features.0 .. features.15; deeper layers and classifier.* are not needed
    sub = {k: v for k, v in sd.items()
           if k.startswith("features.") and k.split(".")[1].isdigit() and int(k.split(".")[1]) <= LAST_IDX}
    want = net.state_dict()
    missing = sorted(set(want) - set(sub))
    extra = sorted(set(sub) - set(want))
    if missing or extra:
        raise InputError(f"not a torchvision VGG-16 state dict: missing {missing[:4]}, unexpected {extra[:4]}", path)
    bad = [k for k in want if tuple(sub[k].shape) != tuple(want[k].shape)]
    if bad:
        raise InputError(f"VGG-16 weight {bad[0]} has shape {tuple(sub[bad[0]].shape)}, "
                         f"expected {tuple(want[bad[0]].shape)}", path)
    net.load_state_dict({k: v.float() for k, v in sub.items()}, strict=True)


def _download(dest_dir: Path) -> Path | None:
    """Fetch the torchvision checkpoint into ``dest_dir``; None when offline or the download fails."""
    old = socket.getdefaulttimeout()
    socket.setdefaulttimeout(DOWNLOAD_TIMEOUT_S)
    try:
        torch.hub.load_state_dict_from_url(VGG_URL, model_dir=str(dest_dir), map_location="cpu",
                                           progress=True, check_hash=True, file_name=VGG_FILE)
        return dest_dir / VGG_FILE
    except Exception:
        return None
    finally:
        socket.setdefaulttimeout(old)


def load_vgg(weights=None, device="cpu", download: bool = True) -> VGG16Relu3:
    """The frozen, eval-mode feature network. ``weights``: a path, "random" (seeded random init, flagged
    ``.is_random``), or None: ``$TLVG_VGG_WEIGHTS`` (path or "random"), then
    ``$TORCH_HOME/hub/checkpoints/vgg16-397923af.pth`` (TORCH_HOME defaults to ~/.cache/torch), then a
    download when online; otherwise an InputError saying how to get the weights. An explicit path that
    does not exist is an error (no fallback: the user asked for that file). ``.source`` says which one."""
    net = VGG16Relu3()
    if weights is None:
        weights = os.environ.get(ENV_VAR) or None
    if isinstance(weights, str) and weights.strip().lower() == "random":
        _random_init(net, RANDOM_SEED)
        net.is_random, net.source = True, f"random (seed {RANDOM_SEED}; NOT pretrained, smoke runs only)"
    else:
        if weights is None:
            ckpt_dir = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch")) / "hub" / "checkpoints"
            path = ckpt_dir / VGG_FILE
            if not path.is_file() and download:
                path = _download(ckpt_dir) or path
            if not path.is_file():
                raise InputError(f"no VGG-16 weights and no network to download them; {how_to_get_weights()}",
                                 path)
        else:
            path = Path(weights).expanduser()
        _load_file(net, path)
        net.source = str(path)
    net.eval().requires_grad_(False)
    return net.to(device)
