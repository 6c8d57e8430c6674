"""The tangential update hook as the stylization wires it (one Adam, hook after each step): the position
update loses exactly λ of its component along the footprint normal n = R(q)·e_argmin(scale), the rest is
Adam's own step, and Adam's moments are those of an optimizer without the hook. Oracles: a twin optimizer
without the hook, and the closed-form plane distance (μ − μ0)·n."""
import math

import torch

from tlvg_warp.train.optim import GaussianParams, LearningRates, footprint_normals, GaussianOptimizer, tangential_hook
from tlvg_warp.types import Gaussians

STEP_TOL = 1e-12  # float64 parameters: the hook is a few multiply-adds on top of Adam's step
PLANE_TOL = 1e-12  # distance to the footprint plane after 50 float64 steps of ~1e-2


def _scene(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=torch.float64)
    ls = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5
    return Gaussians(torch.randn(n, 3, generator=g, dtype=torch.float64), q, ls,
                     torch.zeros(n, dtype=torch.float64), torch.zeros(n, 1, 3, dtype=torch.float64))


def _opt(g, lam=None):
    p = GaussianParams(g, 0, frozen=("quats", "log_scales"))  # fixed footprints: a fixed plane per Gaussian
    o = GaussianOptimizer(p, LearningRates(means=1e-2, means_final=1e-2), extent=1.0)
    if lam is not None:
        o.register_post_step_hook(tangential_hook(lam), fields=("means",))
    return p, o


def _step(p, o, grad):
    p.means.grad = grad.clone()
    o.step()
    o.zero_grad()


def test_removes_exactly_lambda_of_the_normal_component():
    g = _scene()
    n = footprint_normals(g.quats, g.log_scales)
    for lam in (1.0, 0.5, 0.0):
        p, o = _opt(g, lam)
        twin_p, twin_o = _opt(g, None)
        gen = torch.Generator().manual_seed(1)
        for _ in range(5):
            grad = torch.randn(g.num, 3, generator=gen, dtype=torch.float64)
            before, twin_before = p.means.detach().clone(), twin_p.means.detach().clone()
            _step(p, o, grad)
            _step(twin_p, twin_o, grad)
            d, d_adam = p.means.detach() - before, twin_p.means.detach() - twin_before
            expect = d_adam - lam * (d_adam * n).sum(1, keepdim=True) * n
            assert (d - expect).abs().max() < STEP_TOL
            # the moments are Adam's own: the hook touches the parameters only
            s, ts = o.adam.state[p.means], twin_o.adam.state[twin_p.means]
            assert torch.equal(s["exp_avg"], ts["exp_avg"]) and torch.equal(s["exp_avg_sq"], ts["exp_avg_sq"])
            twin_p.means.data.copy_(p.means.detach())  # same position for the next comparison


def test_lambda_one_keeps_every_gaussian_on_its_footprint_plane():
    g = _scene()
    n = footprint_normals(g.quats, g.log_scales)
    p, o = _opt(g, 1.0)
    gen = torch.Generator().manual_seed(2)
    for _ in range(50):
        _step(p, o, torch.randn(g.num, 3, generator=gen, dtype=torch.float64))
    moved = p.means.detach() - g.means
    assert moved.norm(dim=1).min() > 1e-3  # it did move (Adam steps of ~1e-2)
    assert ((moved * n).sum(1)).abs().max() < PLANE_TOL
    # and without the hook the same gradients leave the plane (the test can fail)
    p2, o2 = _opt(g, None)
    gen = torch.Generator().manual_seed(2)
    for _ in range(50):
        _step(p2, o2, torch.randn(g.num, 3, generator=gen, dtype=torch.float64))
    assert ((p2.means.detach() - g.means) * n).sum(1).abs().max() > 1e-3
    assert math.isfinite(float(p.means.detach().sum()))
