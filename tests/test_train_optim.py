"""Adam parameter groups, the xyz decay, structural rebuilds of the Adam state, and the tangential hook."""
import math

import pytest
import torch

from tlvg_warp import Gaussians
from tlvg_warp.train.optim import (FIELDS, GaussianOptimizer, GaussianParams, LearningRates, exp_decay,
                                   footprint_normals, quat_to_rotmat, tangential_hook)

FLOAT_TOL = 1e-6  # float32 arithmetic on O(1) values
EXTENT = 2.5


def random_gaussians(n=40, degree=2, seed=0):
    gen = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return Gaussians(torch.randn(n, 3, generator=gen), torch.randn(n, 4, generator=gen),
                     torch.randn(n, 3, generator=gen) * 0.5 - 3, torch.randn(n, generator=gen),
                     torch.randn(n, k, 3, generator=gen))


def fake_grads(params, seed):
    gen = torch.Generator().manual_seed(seed)
    for f in params.trainable():
        p = getattr(params, f)
        p.grad = torch.randn(p.shape, generator=gen)


def test_learning_rates_per_group_and_decay():
    params = GaussianParams(random_gaussians(), 3)
    opt = GaussianOptimizer(params, LearningRates(), EXTENT, decay_steps=1000)
    assert opt.adam.defaults["eps"] == 1e-15
    expect = {"means": 1.6e-4 * EXTENT, "sh_dc": 2.5e-3, "sh_rest": 1.25e-4, "opacity_logits": 0.05,
              "log_scales": 5e-3, "quats": 1e-3}
    for name, lr in expect.items():
        assert opt.lr(name) == pytest.approx(lr)
    assert params.sh_rest.shape[1] == 15  # max degree 3 stored from the start
    assert opt.set_step(0) == pytest.approx(1.6e-4 * EXTENT)
    assert opt.set_step(1000) == pytest.approx(1.6e-6 * EXTENT)
    assert opt.set_step(5000) == pytest.approx(1.6e-6 * EXTENT)  # clamped after the decay
    # log-linear: the midpoint is the geometric mean
    assert opt.set_step(500) == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6) * EXTENT)
    assert exp_decay(250, 1.0, 1e-4, 1000) == pytest.approx(10 ** -1)


def test_frozen_geometry_is_not_optimized():
    params = GaussianParams(random_gaussians(), frozen=("means", "log_scales", "opacity_logits"))
    opt = GaussianOptimizer(params, LearningRates(), EXTENT)
    before = {f: getattr(params, f).detach().clone() for f in FIELDS}
    fake_grads(params, 1)
    opt.step()
    for f in ("means", "log_scales", "opacity_logits"):
        assert torch.equal(getattr(params, f), before[f])
    for f in ("quats", "sh_dc"):
        assert not torch.equal(getattr(params, f), before[f])


def test_rebuild_slices_and_extends_adam_state():
    params = GaussianParams(random_gaussians(30), 2)
    opt = GaussianOptimizer(params, LearningRates(), EXTENT)
    for s in range(3):
        fake_grads(params, s)
        opt.step()
    old_state = {f: {k: opt.adam.state[getattr(params, f)][k].clone() for k in ("exp_avg", "exp_avg_sq")}
                 for f in FIELDS}
    old = {f: getattr(params, f).detach().clone() for f in FIELDS}
    keep = torch.zeros(30, dtype=torch.bool)
    keep[[0, 3, 4, 17, 29]] = True
    appended = {f: torch.full((2,) + old[f].shape[1:], 7.0) for f in FIELDS}
    opt.rebuild(keep, appended)
    for f in FIELDS:
        p = getattr(params, f)
        assert p.shape[0] == 7 and p.is_leaf and p.requires_grad
        assert torch.equal(p[:5], old[f][keep]) and torch.all(p[5:] == 7)
        st = opt.adam.state[p]
        for k in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(st[k][:5], old_state[f][k][keep])
            assert torch.all(st[k][5:] == 0)
        assert opt.adam.param_groups[[g["name"] for g in opt.adam.param_groups].index(f)]["params"][0] is p
    fake_grads(params, 9)
    opt.step()  # the rebuilt optimizer still steps
    assert torch.isfinite(params.means).all()


def test_footprint_normal_is_thinnest_axis():
    g = random_gaussians(50)
    n = footprint_normals(g.quats, g.log_scales)
    R = quat_to_rotmat(g.quats)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(50, 3, 3), atol=1e-5)
    k = g.log_scales.argmin(1)
    for i in range(50):  # independent per-Gaussian oracle
        assert torch.allclose(n[i], R[i][:, k[i]], atol=FLOAT_TOL)
    # identity rotation, z thinnest -> n = e_z
    n0 = footprint_normals(torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([[0.0, -1.0, -2.0]]))
    assert torch.allclose(n0, torch.tensor([[0.0, 0.0, 1.0]]))


@pytest.mark.parametrize("lam", [1.0, 0.5, 0.0])
def test_tangential_hook_closed_form(lam):
    g = random_gaussians(64, 0, seed=3)
    pa, pb = GaussianParams(g), GaussianParams(g)
    opt_a = GaussianOptimizer(pa, LearningRates(means=1e-2), EXTENT)  # plain Adam: the reference step
    opt_b = GaussianOptimizer(pb, LearningRates(means=1e-2), EXTENT)
    opt_b.register_post_step_hook(tangential_hook(lam), fields=("means",))
    mu0 = g.means.clone()
    for s in range(2):
        fake_grads(pa, 10 + s)
        fake_grads(pb, 10 + s)
        start_b = pb.means.detach().clone()
        opt_a.step()
        opt_b.step()
        if s == 0:
            delta = pa.means.detach() - mu0  # the step Adam takes (same state, same grads)
            n = footprint_normals(pb.quats.detach(), pb.log_scales.detach())
            want = mu0 + delta - lam * (delta * n).sum(1, keepdim=True) * n
            assert torch.allclose(pb.means, want, atol=FLOAT_TOL)
            got = pb.means.detach() - mu0
            normal = (got * n).sum(1)
            assert torch.allclose(normal, (1 - lam) * (delta * n).sum(1), atol=FLOAT_TOL)
            tang = got - normal[:, None] * n
            assert torch.allclose(tang, delta - (delta * n).sum(1, keepdim=True) * n, atol=FLOAT_TOL)
            assert (delta * n).sum(1).abs().max() > 1e-3  # the step did have a normal part to remove
        else:
            n = footprint_normals(pb.quats.detach(), pb.log_scales.detach())
            if lam == 1.0:
                assert ((pb.means.detach() - start_b) * n).sum(1).abs().max() < FLOAT_TOL


def test_hook_handle_removes():
    params = GaussianParams(random_gaussians(8, 0))
    opt = GaussianOptimizer(params, LearningRates(), EXTENT)
    calls = []
    h = opt.register_post_step_hook(lambda p, before: calls.append(before["means"].shape))
    fake_grads(params, 0)
    opt.step()
    h.remove()
    opt.step()
    assert calls == [torch.Size([8, 3])]


def test_functional_adam_equals_torch_adam_and_imports_no_dynamo():
    """FunctionalAdam (GaussianOptimizer's Adam) against torch.optim.Adam itself, the oracle: five steps with
    the learning rates changed between them and a group without gradient, bit-identical parameters and
    moments. Catches other betas/eps, a bias correction off by one step, a moment not carried over. And the
    reason it exists: a fresh process that builds and steps a GaussianOptimizer never imports torch._dynamo."""
    import subprocess
    import sys

    from tlvg_warp.train.optim import FunctionalAdam

    gen = torch.Generator().manual_seed(3)
    a = [torch.randn(7, 3, generator=gen).requires_grad_(), torch.randn(5, generator=gen).requires_grad_(),
         torch.randn(2, 4, generator=gen).requires_grad_()]
    b = [t.detach().clone().requires_grad_() for t in a]
    ours = FunctionalAdam([{"params": [t], "lr": 0.01 * (i + 1), "name": str(i)} for i, t in enumerate(a)], 0.0,
                          1e-15, False)
    ref = torch.optim.Adam([{"params": [t], "lr": 0.01 * (i + 1)} for i, t in enumerate(b)], lr=0.0, eps=1e-15)
    for step in range(5):
        for x, y in zip(a, b):
            if step == 2 and x is a[1]:
                x.grad = y.grad = None  # no gradient this step: neither moves it
                continue
            x.grad = torch.randn(x.shape, generator=gen)
            y.grad = x.grad.clone()
        for go, gr in zip(ours.param_groups, ref.param_groups):
            go["lr"] = gr["lr"] = gr["lr"] * 0.7
        ours.step()
        ref.step()
    for x, y in zip(a, b):
        assert torch.equal(x, y)
        for k in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(ours.state[x][k], ref.state[y][k]), k
    code = ("import sys, torch; from tlvg_warp.train.optim import GaussianOptimizer, GaussianParams; "
            "from tlvg_warp import Gaussians; g = Gaussians(torch.zeros(3, 3), torch.ones(3, 4), torch.zeros(3, 3), "
            "torch.zeros(3), torch.zeros(3, 1, 3)); p = GaussianParams(g, 0); o = GaussianOptimizer(p); "
            "p.means.grad = torch.ones(3, 3); o.step(); print('torch._dynamo' in sys.modules)")
    import os
    from pathlib import Path

    repo = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=repo + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.stdout.strip().splitlines()[-1] == "False", out.stderr[-2000:]


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-14), (torch.float32, 2e-6)])  # a few float ops per value
def test_tangential_kernel_equals_its_torch_twin(dtype, tol):
    """The Warp hook against tangential_hook_torch on the same step: random rotations (unnormalized), ties in
    the log-scales (torch.argmin takes the first) and an all-zero quaternion. Catches a wrong column of R, a
    tie broken the other way, an unnormalized quaternion."""
    from tlvg_warp.train.optim import tangential_hook_torch

    gen = torch.Generator().manual_seed(5)
    n = 200
    q = torch.randn(n, 4, generator=gen, dtype=dtype) * 3
    q[0] = 0.0
    ls = torch.randn(n, 3, generator=gen, dtype=dtype)
    ls[1] = torch.tensor([-1.0, -1.0, 0.0])  # tie between x and y: x
    ls[2] = torch.tensor([0.5, -2.0, -2.0])  # tie between y and z: y
    ls[3] = torch.tensor([0.0, 0.0, 0.0])
    before = torch.randn(n, 3, generator=gen, dtype=dtype)
    after = before + 0.01 * torch.randn(n, 3, generator=gen, dtype=dtype)
    for cap in (0.0, 0.02):  # 0.02 widths: the cap binds on some splats and not on others
        outs = []
        for make in (tangential_hook, tangential_hook_torch):
            g = Gaussians(after.clone(), q, ls, torch.zeros(n, dtype=dtype), torch.zeros(n, 1, 3, dtype=dtype))
            p = GaussianParams(g, 0)
            with torch.no_grad():
                make(0.7, cap)(p, {"means": before})
            outs.append(p.means.detach().clone())
        assert (outs[0] - outs[1]).abs().max() < tol
        assert (outs[1] - after).abs().max() > 1e-3  # the hook did change the step


@pytest.mark.parametrize("make_name", ["tangential_hook", "tangential_hook_torch"])
def test_step_cap_in_footprint_widths(make_name):
    """cap > 0: the tangential step is shortened to cap x the middle scale, in its own direction, and a step
    already shorter is left alone. The oracle is numpy in float64 on hand-made splats whose middle scale is
    on each axis in turn (catches the largest or smallest scale taken for the width, a cap on the step before
    its normal part is removed, a rescale that turns the step)."""
    import numpy as np
    from tlvg_warp.train import optim

    make = getattr(optim, make_name)
    ls = torch.log(torch.tensor([[0.1, 0.02, 0.5], [0.3, 0.9, 0.01], [2.0, 0.05, 0.2], [0.1, 0.02, 0.5]],
                                dtype=torch.float64))
    q = torch.tensor([[1.0, 0, 0, 0]] * 4, dtype=torch.float64)  # axes = world axes
    before = torch.zeros(4, 3, dtype=torch.float64)
    after = torch.tensor([[0.3, 0.4, 0.2], [-0.5, 0.1, 0.7], [0.2, 0.3, -0.6], [1e-4, 2e-4, 0.0]], dtype=torch.float64)
    g = Gaussians(after.clone(), q, ls, torch.zeros(4, dtype=torch.float64), torch.zeros(4, 1, 3, dtype=torch.float64))
    p = GaussianParams(g, 0)
    with torch.no_grad():
        make(1.0, 0.5)(p, {"means": before})
    s = np.exp(ls.numpy())
    d = after.numpy().copy()
    d[np.arange(4), s.argmin(1)] = 0.0  # λ = 1 with identity rotations: the thinnest axis's component goes
    limit = 0.5 * np.sort(s, 1)[:, 1]
    want = d * np.minimum(1.0, limit / np.linalg.norm(d, axis=1))[:, None]
    np.testing.assert_allclose(p.means.detach().numpy(), want, rtol=1e-6, atol=1e-12)
    assert np.linalg.norm(want[:3], axis=1) == pytest.approx(limit[:3])  # the cap bound the first three
    np.testing.assert_allclose(want[3], d[3])  # and left the short step alone


def test_colour_floor_hook_lifts_dead_channels_so_the_renderer_passes_them_a_gradient():
    """A splat whose red channel is under 0 renders red 0 and gets no gradient on it (kernels/sh.py clamps); after the
    hook the channel sits at 0 and the same loss moves it. Oracle for the floor: max(colour, 0) in float64; for the
    gradient: the renderer's own backward. With view-dependent bands the hook leaves the colours alone."""
    from tlvg_warp.renderer import render
    from tlvg_warp.train.optim import GaussianParams, colour_floor_hook
    from tlvg_warp.types import SH_C0, Camera, Gaussians

    rgb = torch.tensor([[-0.3, 0.4, 0.9], [0.2, -0.01, 1.3]], dtype=torch.float64)
    g = Gaussians.from_colors(torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.1, 0.0]]), rgb.float(), 0.3, opacity=0.8)
    cam = Camera.look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=24, height=24, fov_deg=40.0)
    p = GaussianParams(g, 0)

    def red_grad() -> torch.Tensor:
        p.sh_dc.grad = None
        render(p.gaussians(), cam, (0.0, 0.0, 0.0)).color[..., 0].sum().backward()
        return p.sh_dc.grad[:, 0, 0].detach()

    assert float(red_grad()[0]) == 0.0  # dead: red is clamped
    with torch.no_grad():
        colour_floor_hook()(p, {})
    after = SH_C0 * p.sh_dc[:, 0].detach().double() + 0.5
    assert torch.allclose(after, rgb.clamp_min(0.0), atol=1e-5)
    assert float(after.min()) >= 0.0
    assert float(red_grad()[0]) > 0.0  # alive: more red would add red
    p3 = GaussianParams(g.with_sh_degree(1), 1)
    before = p3.sh_dc.detach().clone()
    with torch.no_grad():
        colour_floor_hook()(p3, {})
    assert torch.equal(p3.sh_dc, before)


def test_clear_moments_makes_the_next_step_adams_first_for_the_named_groups_only():
    """Adam's first step is lr * g / |g| elementwise (closed form: both bias-corrected moments are g and g^2). After a
    history of large gradients a small one does not move sh_dc that way (the old moments dominate the step); after
    clear_moments(("sh_dc",)) the same small gradient moves it by lr exactly, while the other groups keep their
    state."""
    params = GaussianParams(random_gaussians(), 0)
    opt = GaussianOptimizer(params, LearningRates(), EXTENT)
    for seed in range(5):  # large gradients: a large second moment
        fake_grads(params, seed)
        for f in params.trainable():
            getattr(params, f).grad.mul_(100.0)
        opt.step()
    small = torch.randn(params.sh_dc.shape, generator=torch.Generator().manual_seed(9)) * 1e-3

    def step_of_small():
        before = params.sh_dc.detach().clone()
        for f in params.trainable():
            getattr(params, f).grad = torch.zeros_like(getattr(params, f))
        params.sh_dc.grad = small.clone()
        opt.step()
        return params.sh_dc.detach() - before
    stale = step_of_small()
    first_step = -opt.lr("sh_dc") * torch.sign(small)
    assert not torch.allclose(stale, first_step, rtol=1e-2)
    quats_step = int(opt.adam.state[params.quats]["step"])
    opt.clear_moments(("sh_dc",))
    fresh = step_of_small()
    assert torch.allclose(fresh, first_step, rtol=1e-4, atol=1e-9)
    assert int(opt.adam.state[params.sh_dc]["step"]) == 1
    assert int(opt.adam.state[params.quats]["step"]) == quats_step + 1  # not cleared
