"""Density control on hand-built cases with known outcomes: which Gaussians are cloned, split, pruned;
children inside the parent's 3σ; Adam state after the rebuild; the budget; statistics accumulation."""
import math
from types import SimpleNamespace

import pytest
import torch

from tlvg_warp import Camera, Gaussians, render
from tlvg_warp.train.density import DensityConfig, DensityControl
from tlvg_warp.train.optim import FIELDS, GaussianOptimizer, GaussianParams, LearningRates, quat_to_rotmat

EXTENT = 1.0
HIGH, LOW = 1e-3, 1e-5  # mean gradients above / below the 2e-4 threshold
SMALL, BIG = 0.005, 0.05  # max scales under / over percent_dense·extent = 0.01
STEP = 4000  # after the first opacity reset: the screen/world size rules apply
SIGMA_TOL = 1e-2  # in σ units: float32 rounding of centers up to ~300 against σ down to 0.02 (~1.5e-3 σ)


def build(specs, degree=1):
    """specs: list of (scale, opacity, mean grad, max radius)."""
    n = len(specs)
    gen = torch.Generator().manual_seed(0)
    means = torch.arange(n, dtype=torch.float32)[:, None] * torch.tensor([1.0, 0.5, 0.25])  # unique rows
    q = torch.randn(n, 4, generator=gen)
    ls = torch.log(torch.tensor([[s, s * 0.7, s * 0.4] for s, *_ in specs]))
    op = torch.logit(torch.tensor([o for _, o, *_ in specs]))
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=gen)
    params = GaussianParams(Gaussians(means, q, ls, op, sh))
    opt = GaussianOptimizer(params, LearningRates(), EXTENT)
    for s in range(2):  # real Adam state to carry through the rebuild
        g2 = torch.Generator().manual_seed(s)
        for f in FIELDS:
            p = getattr(params, f)
            p.grad = torch.randn(p.shape, generator=g2)
        opt.step()
    # the Adam step moved everything a little: restore the hand-set values (state unchanged)
    with torch.no_grad():
        params.log_scales.copy_(ls)
        params.opacity_logits.copy_(op)
    dc = DensityControl(DensityConfig(prune_unseen=False), n)
    dc.generator = torch.Generator().manual_seed(0)
    dc.grad_accum = torch.tensor([g for *_, g, _ in specs]) * 4
    dc.denom = torch.full((n,), 4.0)
    dc.max_radii = torch.tensor([float(r) for *_, r in specs])
    return params, opt, dc


def snapshot(params, opt):
    return ({f: getattr(params, f).detach().clone() for f in FIELDS},
            {f: {k: opt.adam.state[getattr(params, f)][k].clone() for k in ("exp_avg", "exp_avg_sq")} for f in FIELDS})


def test_clone_split_prune_known_outcome():
    specs = [(SMALL, 0.5, HIGH, 5),   # 0 clone
             (BIG, 0.5, HIGH, 5),     # 1 split
             (SMALL, 0.5, LOW, 5),    # 2 keep
             (SMALL, 0.001, HIGH, 5),  # 3 prune: opacity < 0.005 (not densified)
             (SMALL, 0.5, LOW, 25),   # 4 prune: screen radius 25 > 20
             (0.2, 0.5, LOW, 5),      # 5 prune: world size 0.2 > 0.1·extent
             (BIG, 0.5, LOW, 5),      # 6 keep (low grad)
             (SMALL, 0.5, HIGH, 5)]   # 7 clone
    params, opt, dc = build(specs)
    old, old_state = snapshot(params, opt)
    res = dc.densify_and_prune(opt, EXTENT, STEP)
    assert res == {"cloned": 2, "split": 1, "pruned": 3, "num": 8 - 3 - 1 + 2 + 2}
    kept = [0, 2, 6, 7]
    layout = kept + [0, 7] + [1, 1]  # survivors, clones, split children
    new = {f: getattr(params, f).detach() for f in FIELDS}
    for f in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
        assert torch.equal(new[f], old[f][layout]), f
    assert torch.equal(new["means"][:6], old["means"][layout[:6]])
    assert torch.equal(new["log_scales"][:6], old["log_scales"][layout[:6]])
    # split children: scale / 1.6, inside the parent's 3σ box (in the parent's frame)
    assert torch.allclose(new["log_scales"][6:].exp(), old["log_scales"][[1, 1]].exp() / 1.6, rtol=1e-5)
    R = quat_to_rotmat(old["quats"][1])
    local = (new["means"][6:] - old["means"][1]) @ R  # R^T d per row
    assert torch.all(local.abs() <= (3 + SIGMA_TOL) * old["log_scales"][1].exp())
    assert not torch.equal(new["means"][6], new["means"][7])
    # Adam moments: kept rows sliced, new rows zero
    for f in FIELDS:
        st = opt.adam.state[getattr(params, f)]
        for k in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(st[k][:4], old_state[f][k][kept]), (f, k)
            assert torch.all(st[k][4:] == 0), (f, k)
    # statistics restart for the new layout
    assert dc.num == 8 and float(dc.grad_accum.abs().sum()) == 0 and float(dc.max_radii.sum()) == 0


def test_size_rules_wait_for_first_reset():
    specs = [(SMALL, 0.5, LOW, 25), (0.2, 0.5, LOW, 5), (SMALL, 0.5, LOW, 5)]
    params, opt, dc = build(specs)
    res = dc.densify_and_prune(opt, EXTENT, 1000)  # step < opacity_reset_interval: graphdeco skips them
    assert res["pruned"] == 0 and params.num == 3


def test_split_children_within_3_sigma_many():
    n = 300
    params, opt, dc = build([(BIG, 0.5, HIGH, 5)] * n)
    parents = params.means.detach().clone()
    q, ls = params.quats.detach().clone(), params.log_scales.detach().clone()
    dc.densify_and_prune(opt, EXTENT, STEP)
    assert params.num == 2 * n
    for half in range(2):
        child = params.means.detach()[half * n:(half + 1) * n]
        local = torch.einsum("nij,ni->nj", quat_to_rotmat(q), child - parents)
        z = local / ls.exp()
        assert z.abs().max() <= 3 + SIGMA_TOL
        # normal samples: sample std of the standardized offsets ≈ 1 (truncation at 3σ removes 0.3%)
        assert 0.85 < float(z.std()) < 1.15


def test_moment_matched_split_keeps_mean_and_covariance():
    """split_mode="moments": the two children, as an equal mixture, have the parent's mean and covariance
    (oracle: Σ_mix = ½ΣΣ_child + ½Σ(μ_c − μ)(μ_c − μ)ᵀ, computed here in float64)."""
    n = 50
    params, opt, dc = build([(BIG, 0.5, HIGH, 5)] * n)
    dc.config.split_mode = "moments"
    mu, q, ls = (params.means.detach().double().clone(), params.quats.detach().double().clone(),
                 params.log_scales.detach().double().clone())
    R = quat_to_rotmat(q)
    cov = R @ torch.diag_embed((2 * ls).exp()) @ R.transpose(1, 2)
    dc.densify_and_prune(opt, EXTENT, STEP)
    assert params.num == 2 * n
    c = [params.means.detach().double()[k * n:(k + 1) * n] for k in range(2)]
    cl = [params.log_scales.detach().double()[k * n:(k + 1) * n] for k in range(2)]
    qc = params.quats.detach().double()[:n]
    Rc = quat_to_rotmat(qc)
    mix = sum(0.5 * (Rc @ torch.diag_embed((2 * l).exp()) @ Rc.transpose(1, 2)
                     + torch.einsum("ni,nj->nij", m - mu, m - mu)) for m, l in zip(c, cl))
    assert torch.allclose((c[0] + c[1]) / 2, mu, atol=1e-5)
    assert torch.allclose(mix, cov, rtol=1e-4, atol=5e-7)  # float32 centers up to ~50 units: offsets to ~3e-6


def test_tracked_tensors_follow_every_keep_and_append():
    """Registered per-Gaussian tensors (the stylization's anchors) get the same keep / append as the parameters:
    kept rows keep their values, a new Gaussian's row is its own value of the same-named field (zeros otherwise)."""
    params, opt, dc = build([(BIG, 0.5, HIGH, 5), (SMALL, 0.5, HIGH, 5), (SMALL, 0.001, LOW, 5), (BIG, 0.5, LOW, 5)])
    anchor = torch.tensor([10.0, 11.0, 12.0, 13.0])  # distinguishable from the live values
    dc.tracked = {"opacity_logits": anchor.clone(), "extra": torch.ones(4, 2)}
    before_new = params.num
    dc.densify_and_prune(opt, EXTENT, STEP)
    n = params.num
    assert all(t.shape[0] == n for t in dc.tracked.values())
    # survivors: #1 (cloned, kept) and #3 (low gradient, kept); #0 split (replaced), #2 pruned (opacity)
    assert dc.tracked["opacity_logits"][:2].tolist() == [11.0, 13.0]
    assert torch.equal(dc.tracked["opacity_logits"][2:], params.opacity_logits.detach()[2:])
    assert dc.tracked["extra"][:2].eq(1).all() and dc.tracked["extra"][2:].eq(0).all()
    assert n == before_new - 2 + 1 + 2  # -split parent -pruned +clone +2 children
    sd = dc.state_dict()
    dc2 = DensityControl(dc.config, 0)
    dc2.load_state_dict(sd)
    assert torch.equal(dc2.tracked["opacity_logits"], dc.tracked["opacity_logits"])


def test_budget_never_exceeded_and_highest_gradients_first():
    n = 100
    grads = torch.linspace(3e-4, 1e-2, n)[torch.randperm(n, generator=torch.Generator().manual_seed(1))]
    params, opt, dc = build([(SMALL, 0.5, float(g), 5) for g in grads])
    dc.config.max_gaussians = 130
    old_means = params.means.detach().clone()
    res = dc.densify_and_prune(opt, EXTENT, STEP)
    assert params.num == 130 and res["cloned"] == 30
    top = torch.topk(grads, 30).indices.sort().values
    assert torch.equal(params.means.detach()[100:], old_means[top])
    # a mix of splits (net +1 each) and clones against a tight budget
    specs = [(SMALL if i % 2 else BIG, 0.5, 1e-3 + i * 1e-5, 5) for i in range(50)]
    params, opt, dc = build(specs)
    dc.config.max_gaussians = 61
    dc.densify_and_prune(opt, EXTENT, STEP)
    assert params.num <= 61
    # survivors alone over budget (lowered budget): the least opaque go
    ops = torch.linspace(0.1, 0.9, 20)
    params, opt, dc = build([(SMALL, float(o), LOW, 5) for o in ops])
    dc.config.max_gaussians = 15
    dc.densify_and_prune(opt, EXTENT, STEP)
    assert params.num == 15
    assert torch.allclose(torch.sigmoid(params.opacity_logits.detach()), ops[5:], atol=1e-6)


def test_repeated_densify_under_budget_random():
    gen = torch.Generator().manual_seed(5)
    specs = [(float(s), 0.5, float(g), 5) for s, g in zip(torch.rand(80, generator=gen) * 0.03 + 0.001,
                                                         torch.rand(80, generator=gen) * 1e-3)]
    params, opt, dc = build(specs)
    dc.config.max_gaussians = 200
    for it in range(8):
        n = params.num
        dc.grad_accum = torch.rand(n, generator=gen) * 1e-3
        dc.denom = torch.ones(n)
        dc.densify_and_prune(opt, EXTENT, STEP)
        assert params.num <= 200
        for f in FIELDS:
            assert getattr(params, f).shape[0] == params.num == opt.adam.state[getattr(params, f)]["exp_avg"].shape[0]


def test_accumulate_scales_pixel_gradients_to_ndc():
    n, W, H = 5, 64, 48
    dc = DensityControl(DensityConfig(), n)
    g = torch.tensor([[1.0, 0.0], [0.0, 1.0], [3.0, 4.0], [1.0, 1.0], [2.0, 2.0]])
    probe = torch.zeros(n, 2, requires_grad=True)
    probe.grad = g
    out = SimpleNamespace(radii=torch.tensor([3, 4, 5, 0, 7], dtype=torch.int32), means2d=probe, weights=None)
    dc.accumulate(out, W, H)
    dc.accumulate(out, W, H)
    want = torch.tensor([W / 2, H / 2, math.hypot(3 * W / 2, 4 * H / 2), 0.0, math.hypot(W, H)])
    assert torch.allclose(dc.mean_grads(), want)
    assert torch.equal(dc.denom, torch.tensor([2.0, 2, 2, 0, 2]))
    assert torch.equal(dc.max_radii, torch.tensor([3.0, 4, 5, 0, 7]))


def test_accumulate_from_a_real_render():
    gen = torch.Generator().manual_seed(2)
    g = Gaussians.from_colors(torch.randn(60, 3, generator=gen) * 0.4, torch.rand(60, 3, generator=gen), 0.08, 0.5)
    g.means[0] = torch.tensor([0.0, 0.0, -50.0])  # behind the camera: culled
    cam = Camera.look_at((0, -3, 0), (0, 0, 0), width=48, height=32)
    dc = DensityControl(DensityConfig(), g.num)
    out = render(g, cam, return_weights=True)
    out.color.square().mean().backward()
    dc.accumulate(out, cam.width, cam.height)
    gr = out.means2d.grad
    want = (gr * torch.tensor([cam.width / 2, cam.height / 2])).norm(dim=1) * (out.radii > 0)
    assert torch.allclose(dc.grad_accum, want.float(), rtol=1e-5, atol=1e-12)
    assert dc.denom[0] == 0 and dc.max_radii[0] == 0 and dc.denom[1:].sum() > 0
    assert torch.allclose(dc.contrib, out.weights.float())


def test_unseen_gaussians_are_pruned_after_a_window():
    n = 6
    params, opt, dc = build([(SMALL, 0.5, LOW, 5)] * n)
    dc.config.prune_unseen, dc.window, dc.config.min_contribution = True, 3, 0.5
    w = torch.tensor([1.0, 0.0, 0.3, 0.0, 2.0, 0.1])  # per view; over 3 views: 3, 0, 0.9, 0, 6, 0.3
    probe = torch.zeros(n, 2)
    probe.grad = torch.zeros(n, 2)
    out = SimpleNamespace(radii=torch.ones(n, dtype=torch.int32), means2d=probe, weights=w)
    dc.accumulate(out, 10, 10)
    dc.accumulate(out, 10, 10)
    assert dc.densify_and_prune(opt, EXTENT, STEP)["pruned"] == 0  # window not complete yet
    dc.accumulate(out, 10, 10)
    old = params.means.detach().clone()
    assert dc.densify_and_prune(opt, EXTENT, STEP)["pruned"] == 3
    assert torch.equal(params.means.detach(), old[[0, 2, 4]])
    assert torch.all(dc.contrib_views == 0)  # the next window starts


def test_opacity_reset_caps_and_zeroes_state():
    params, opt, dc = build([(SMALL, 0.5, LOW, 5), (SMALL, 0.005, LOW, 5), (SMALL, 0.9, LOW, 5)])
    dc.reset_opacity(opt)
    o = torch.sigmoid(params.opacity_logits.detach())
    assert torch.allclose(o, torch.tensor([0.01, 0.005, 0.01]), atol=1e-6)
    st = opt.adam.state[params.opacity_logits]
    assert torch.all(st["exp_avg"] == 0) and torch.all(st["exp_avg_sq"] == 0)
    assert opt.adam.param_groups[[g["name"] for g in opt.adam.param_groups].index("opacity_logits")]["params"][0] \
        is params.opacity_logits


@pytest.mark.parametrize("step,expect", [(400, False), (500, True), (550, False), (600, True), (15000, False)])
def test_schedule(step, expect):
    assert DensityControl(DensityConfig()).is_densify_step(step) is expect


def test_weights_requested_only_before_checks():
    dc = DensityControl(DensityConfig(start=500, interval=100, until=1000), window=33)
    asked = [s for s in range(1, 1200) if dc.wants_weights(s)]
    # steps 468..500, 568..600, ..., 968..999: the 33 steps before each densify step (and none after `until`)
    want = [s for k in range(500, 1000, 100) for s in range(k - 32, k + 1)] + list(range(968, 1000))
    assert asked == want
    dc.views_per_step = 2  # two views per step: a 33-view window is held by the last 17 steps
    assert [s for s in range(1, 601) if dc.wants_weights(s)] == [*range(484, 501), *range(584, 601)]
    dc.config.prune_unseen = False
    assert not any(dc.wants_weights(s) for s in range(1, 1200))


@pytest.mark.parametrize("s, n, densify", [(100, 300, True), (300, 300, False), (200, 200, False), (50, 300, False)])
def test_no_structural_change_at_a_phases_last_step(s, n, densify):
    """Within a phase of n steps density control never changes the set at step n (what a phase hands on is
    what it trained); until=0 means no end."""
    dc = DensityControl(DensityConfig(start=0, until=0, interval=100))
    assert dc.is_densify_step(s, n) is densify
    assert dc.accumulating(10 ** 9)


def test_step_densifies_on_schedule_and_records_events():
    params, opt, dc = build([(SMALL, 0.5, HIGH, 5), (BIG, 0.5, LOW, 5)])
    dc.config.start, dc.config.interval, dc.config.opacity_reset_interval = 0, 2, 0
    assert dc.step(opt, 1, 10, {"phase": "x"}) is None and params.num == 2  # not a densify step
    ev = dc.step(opt, 2, 10, {"phase": "x"})
    assert ev == {"cloned": 1, "split": 0, "pruned": 0, "num": 3, "phase": "x"} and dc.events == [ev]
    assert dc.step(opt, 10, 10) is None  # the phase's last step


def test_budget_from_the_starting_count():
    c = DensityConfig(max_gaussians=0, budget_factor=1.5)
    assert DensityControl(c, 100).budget == 150 and DensityConfig(max_gaussians=7).budget(100) == 7
    c.use_budget = False
    assert DensityControl(c, 100).budget is None


@pytest.mark.parametrize("num", [5, 10, 162451, 300000, 140138])
def test_budget_never_above_the_factor(num):
    """1.2 x the input is a ceiling: the budget is floor(1.2 x num), computed here in integers (a fitted beer of
    162,451 Gaussians got 194,942 from a ceil, one over 1.2x)."""
    assert DensityConfig(max_gaussians=0, budget_factor=1.2).budget(num) == (6 * num) // 5
