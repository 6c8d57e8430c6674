"""VGG-16 features: torchvision-format weights load, missing/bad weights say how to get them, "random" is
flagged, shapes, named layers, and the lookup order (path > env > TORCH_HOME cache > HED package > download)."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tlvg_warp.errors import InputError
from tlvg_warp.losses import load_vgg, resize_style
from tlvg_warp.losses import vgg as vgg_mod

# torchvision vgg16().features, written out independently: (index, in, out) of every conv; the
# classifier's shapes too, since a real checkpoint carries them (they must be ignored).
CONVS = [(0, 3, 64), (2, 64, 64), (5, 64, 128), (7, 128, 128), (10, 128, 256), (12, 256, 256),
         (14, 256, 256), (17, 256, 512), (19, 512, 512), (21, 512, 512), (24, 512, 512), (26, 512, 512),
         (28, 512, 512)]


def torchvision_like_state_dict(seed=0):
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for i, cin, cout in CONVS:
        sd[f"features.{i}.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * 0.05
        sd[f"features.{i}.bias"] = torch.randn(cout, generator=g) * 0.05
    sd["classifier.0.weight"] = torch.zeros(8, 4)  # shape irrelevant: ignored (kept small for speed)
    sd["classifier.0.bias"] = torch.zeros(8)
    return sd


def reference_features(sd, x):
    """relu3_1|relu3_2|relu3_3 with plain functional ops from the state dict (the oracle)."""
    f = torch.nn.functional
    x = (x - torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)) / torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    conv = lambda x, i: f.relu(f.conv2d(x, sd[f"features.{i}.weight"], sd[f"features.{i}.bias"], padding=1))  # noqa
    x = f.max_pool2d(conv(conv(x, 0), 2), 2)
    x = f.max_pool2d(conv(conv(x, 5), 7), 2)
    r1 = conv(x, 10)
    r2 = conv(r1, 12)
    r3 = conv(r2, 14)
    return torch.cat([r1, r2, r3], 1)


def test_torchvision_layout_loads_and_matches_functional_oracle(tmp_path):
    sd = torchvision_like_state_dict()
    p = tmp_path / "vgg16-397923af.pth"
    torch.save(sd, p)
    net = load_vgg(str(p))
    assert not net.is_random and net.source == str(p)
    assert all(not q.requires_grad for q in net.parameters()) and not net.training
    x = torch.rand(1, 3, 36, 52)
    feats = net(x)
    assert feats.shape == (1, 768, 9, 13)
    assert torch.allclose(feats, reference_features(sd, x), atol=1e-5)
    # [H,W,3] input and the x0.5 render scale: 72x104 -> 36x52 -> cells 9x13
    assert net(torch.rand(72, 104, 3), scale=0.5).shape == (1, 768, 9, 13)
    # features follow the caller's grad mode (the render needs its gradient)
    img = torch.rand(1, 3, 16, 16, requires_grad=True)
    net(img).sum().backward()
    assert img.grad is not None and img.grad.abs().sum() > 0


def test_missing_file_names_path_and_how_to_get_weights(tmp_path):
    missing = tmp_path / "nope.pth"
    with pytest.raises(InputError) as e:
        load_vgg(str(missing))
    msg = str(e.value)
    assert str(missing) in msg and vgg_mod.VGG_URL in msg and "random" in msg and "\n" not in msg


def test_wrong_state_dict_is_input_error(tmp_path):
    sd = torchvision_like_state_dict()
    del sd["features.14.bias"]
    p = tmp_path / "bad.pth"
    torch.save(sd, p)
    with pytest.raises(InputError, match="features.14.bias"):
        load_vgg(str(p))
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="junk.pth"):
        load_vgg(str(tmp_path / "junk.pth"))


def test_random_is_flagged_and_seeded(monkeypatch):
    a, b = load_vgg("random"), load_vgg("RANDOM")
    assert a.is_random and "random" in a.source
    assert torch.equal(a.features[0].weight, b.features[0].weight)
    monkeypatch.setenv(vgg_mod.ENV_VAR, "random")
    assert load_vgg().is_random


def test_lookup_order_env_then_cache_then_download(tmp_path, monkeypatch):
    sd = torchvision_like_state_dict()
    env_p, home = tmp_path / "env.pth", tmp_path / "th"
    torch.save(sd, env_p)
    monkeypatch.setenv("TORCH_HOME", str(home))
    monkeypatch.setenv(vgg_mod.ENV_VAR, str(env_p))
    assert load_vgg().source == str(env_p)
    monkeypatch.delenv(vgg_mod.ENV_VAR)
    monkeypatch.setattr(vgg_mod.hed, "find_hed_weights", lambda: None)  # no HED package either
    calls = []
    monkeypatch.setattr(vgg_mod, "_download", lambda d: calls.append(d))  # offline: returns None
    with pytest.raises(InputError) as e:
        load_vgg()
    assert calls == [home / "hub" / "checkpoints"] and vgg_mod.VGG_URL in str(e.value)
    cached = home / "hub" / "checkpoints" / vgg_mod.VGG_FILE
    cached.parent.mkdir(parents=True)
    torch.save(sd, cached)
    assert load_vgg().source == str(cached) and len(calls) == 1  # cache hit: no download attempt


def test_resize_style_to_height_256():
    out = resize_style(np.random.default_rng(0).random((600, 800, 3)).astype(np.float32))
    assert out.shape == (256, 341, 3)


def test_named_layers_down_to_relu5_3_match_functional_oracle(tmp_path):
    """``layers`` offers relu1_2 .. relu5_3 (evaluation reads relu1_2..relu4_3), computed independently here."""
    sd = torchvision_like_state_dict(1)
    p = tmp_path / "vgg.pth"
    torch.save(sd, p)
    net = load_vgg(str(p))
    f = torch.nn.functional
    conv = lambda x, i: f.relu(f.conv2d(x, sd[f"features.{i}.weight"], sd[f"features.{i}.bias"], padding=1))  # noqa
    x = torch.rand(1, 3, 48, 64)
    y = (x - torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)) / torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    ref = {}
    ref["relu1_2"] = y = conv(conv(y, 0), 2)
    ref["relu2_2"] = y = conv(conv(f.max_pool2d(y, 2), 5), 7)
    ref["relu3_3"] = y = conv(conv(conv(f.max_pool2d(y, 2), 10), 12), 14)
    ref["relu4_3"] = y = conv(conv(conv(f.max_pool2d(y, 2), 17), 19), 21)
    ref["relu5_3"] = conv(conv(conv(f.max_pool2d(y, 2), 24), 26), 28)
    got = net.layers(x, list(ref))
    assert set(got) == set(ref)
    for k in ref:
        assert got[k].shape == ref[k].shape and torch.allclose(got[k], ref[k], atol=1e-5), k


def test_batched_features_and_precision_options(tmp_path):
    """features_of (one batched pass) equals separate calls; channels_last is float32 arithmetic; bf16 stays
    within its rounding of float32 and leaves the modules (HED side outputs, evaluation) in float32."""
    sd = torchvision_like_state_dict(2)
    p = tmp_path / "vgg.pth"
    torch.save(sd, p)
    net = load_vgg(str(p))
    img = torch.rand(40, 56, 3)
    lum = img.mean(-1, keepdim=True).expand_as(img)
    f_lum, f_rgb = net.features_of([lum, img], scale=0.5)
    assert f_lum.shape == (768, 5 * 7)
    assert torch.allclose(f_lum, net(lum, scale=0.5).reshape(768, -1), atol=1e-5)
    assert torch.allclose(f_rgb, net(img, scale=0.5).reshape(768, -1), atol=1e-5)
    # the deep term's conv4 features continued from the batch's relu3 equal one pass through conv1-4 of that image
    *_, f_deep = net.features_of([lum, img], scale=0.5, deep=True)
    one_pass = net.layers(lum, ("relu4_1", "relu4_2", "relu4_3"), scale=0.5)
    assert f_deep.shape == (1536, 2 * 3)
    ref_deep = torch.cat(list(one_pass.values()), 1).reshape(1536, -1)  # values up to ~10: float32 round-off scales
    assert torch.allclose(f_deep, ref_deep, rtol=1e-5, atol=1e-5 * float(ref_deep.abs().max()))
    ref = net(img)
    net.set_precision(channels_last=True)
    assert torch.allclose(net(img), ref, atol=1e-5)
    net.set_precision(torch.bfloat16)
    x = img.clone().requires_grad_(True)
    low = net(x)
    low.sum().backward()
    assert low.dtype == torch.float32 and x.grad is not None
    assert (low - ref).norm() / ref.norm() < 3e-2  # bf16 keeps 8 bits of mantissa through seven convolutions
    assert all(m.weight.dtype == torch.float32 for m in net.features if isinstance(m, torch.nn.Conv2d))
    assert not any(k.startswith("lowp") for k in net.state_dict())
    net.set_precision()
    assert torch.allclose(net(img), ref, atol=1e-6) and not net._lowp
    with pytest.raises(ValueError):
        net.set_precision(torch.int8)


GRAPH_TOL = 1e-4  # float32 convolutions: cuDNN may pick other algorithms inside a capture (sums reordered)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_cuda_graphed_features_and_gradients_match_eager():
    """``use_cuda_graphs``: the replayed pass gives the eager features and input gradients for inputs that change
    between calls (a graph that kept its first input, or returned a stale gradient, fails), one graph per size."""
    dev = torch.device("cuda")
    eager = load_vgg("random", dev).set_precision(channels_last=True)
    graphed = load_vgg("random", dev).set_precision(channels_last=True).use_cuda_graphs(True)
    gen = torch.Generator(device=dev).manual_seed(0)
    for h, w in ((70, 90), (70, 90), (70, 90), (48, 64)):
        img = torch.rand(h, w, 3, device=dev, generator=gen)
        up = [torch.rand(768, ((h // 2) // 4) * ((w // 2) // 4), device=dev, generator=gen) for _ in range(2)]
        grads, feats = [], []
        for net in (eager, graphed):
            x = img.clone().requires_grad_(True)
            f = net.features_of([x.mean(-1, keepdim=True).expand_as(x), x], 0.5)
            feats.append([fi.detach().clone() for fi in f])
            ((f[0] * up[0]).sum() + (f[1] * up[1]).sum()).backward()
            grads.append(x.grad)
        for a, b in zip(*feats):
            assert torch.allclose(a, b, rtol=GRAPH_TOL, atol=GRAPH_TOL * a.abs().max())
        assert torch.allclose(grads[0], grads[1], rtol=GRAPH_TOL, atol=GRAPH_TOL * grads[0].abs().max())
    assert len(graphed._graphed) == 2 and not eager._graphed


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_cuda_graph_capture_does_not_import_sympy():
    """The graphs are captured with a scalar backward seed: autograd given a tensor seed (make_graphed_callables)
    imports torch.fx's symbolic shapes and sympy, 2 s of a stylize run's start. Checked in a fresh process."""
    code = ("import sys, torch\n"
            "from tlvg_warp.losses.vgg import load_vgg\n"
            "net = load_vgg('random', torch.device('cuda')).use_cuda_graphs(True)\n"
            "x = torch.rand(1, 3, 64, 64, device='cuda', requires_grad=True)\n"
            "net.features_of([x])[0].sum().backward()\n"
            "assert net._graphed and x.grad is not None and x.grad.abs().sum() > 0\n"
            "print('symbolic_shapes imported:', 'torch.fx.experimental.symbolic_shapes' in sys.modules)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("symbolic_shapes imported: False"), out.stdout
