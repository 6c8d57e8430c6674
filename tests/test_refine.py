"""Stroke-size refinement: coarse splats become stroke-sized children within the budget, keeping coverage."""
import math

import torch

from tlvg_warp.renderer import render
from tlvg_warp.train.optim import quat_to_rotmat
from tlvg_warp.train.refine import MAX_CHILDREN, OVERLAP, refine_to_radius, view_footprints
from tlvg_warp.types import Camera, Gaussians


def _cams():
    return [Camera.look_at((0.3 * k, -4.0, 0.2 * k), (0, 0, 0), width=64, height=48, fov_deg=50.0) for k in (-1, 0, 1)]


def _scene(seed=0, small=200):
    """One large flat opaque wall-like splat and a cloud of small splats in front of it."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.cat([torch.tensor([[0.0, 0.5, 0.0]]), (torch.rand(small, 3, generator=gen) - 0.5) * 1.2])
    log_scales = torch.cat([torch.log(torch.tensor([[1.2, 0.01, 0.9]])), torch.full((small, 3), math.log(0.02))])
    quats = torch.zeros(small + 1, 4)
    quats[:, 0] = 1
    logits = torch.cat([torch.tensor([4.0]), torch.full((small,), 1.0)])
    sh = torch.rand(small + 1, 1, 3, generator=gen) - 0.5
    return Gaussians(means, quats, log_scales, logits, sh)


def test_coarse_splat_becomes_stroke_sized_children_within_budget():
    g, cams = _scene(), _cams()
    r0, _ = view_footprints(g, cams)
    assert r0[0] > 20  # the wall is coarse; the small ones are not
    radius = 8.0
    g2, info = refine_to_radius(g, cams, radius, budget=g.num + 100, passes=1)
    assert g2.num <= g.num + 100
    assert info["refined"] == 1 and info["children"] == g2.num - g.num + 1
    # the small splats are untouched, bit for bit, and in order
    assert torch.equal(g2.means[:g.num - 1], g.means[1:])
    kids = g2.subset(slice(g.num - 1, None))
    shrink = max(radius / float(r0[0]), math.sqrt(OVERLAP / kids.num))
    assert kids.num == min(MAX_CHILDREN, math.ceil(OVERLAP * (float(r0[0]) / radius) ** 2))
    torch.testing.assert_close(kids.log_scales, (g.log_scales[0] + math.log(shrink)).expand_as(kids.log_scales))
    # children stay inside the parent: within 2 sigma along each of its axes
    local = (kids.means - g.means[0]) @ quat_to_rotmat(g.quats[:1])[0]
    assert bool((local.abs() <= 2.0 * g.scales[0] + 1e-6).all())


def test_children_keep_the_parents_moments():
    """Many children of one splat: their mixture's covariance (f²Σ + spread of the centres) is the parent's."""
    g = _scene(small=0)
    from tlvg_warp.train.refine import _children

    kids = _children(g, torch.zeros(1, dtype=torch.int64), torch.tensor([4096]), torch.tensor([0.3]), seed=1)
    c = kids.means.double() - g.means[0].double()
    R = quat_to_rotmat(g.quats[:1].double())[0]
    s2 = g.scales[0].double() ** 2
    sigma = R @ torch.diag(s2) @ R.T
    mixture = 0.09 * sigma + c.T @ c / c.shape[0]
    # 2-sigma truncation of the centres removes 1 - 0.9545 of the mass and some variance: within 10%
    torch.testing.assert_close(torch.diagonal(mixture), torch.diagonal(sigma), rtol=0.1, atol=1e-6)
    assert float(c.mean(0).abs().max()) < 0.02


def test_refinement_keeps_coverage_and_shrinks_footprints():
    g, cams = _scene(), _cams()
    g2, info = refine_to_radius(g, cams, 6.0, budget=g.num + 400, passes=3)
    assert info["passes"] >= 2  # the cap per pass needs a second pass for the wall
    r0, w0 = view_footprints(g, cams)
    r2, w2 = view_footprints(g2, cams)
    share = lambda r, w: float(w[r > 12].sum() / w.sum())  # noqa: E731
    assert share(r2, w2) < 0.5 * share(r0, w0)
    for cam in cams:  # the holes metric (SPEC §4): stylized alpha < 0.5 where the original >= 0.5
        a0, a2 = render(g, cam).alpha.detach(), render(g2, cam).alpha.detach()
        assert float(((a2 < 0.5) & (a0 >= 0.5)).float().mean()) < 0.01


def test_room_comes_from_unseen_splats_only_when_needed():
    g, cams = _scene(), _cams()
    hidden = Gaussians(torch.tensor([[0.0, 30.0, 0.0]] * 50), torch.tensor([[1.0, 0, 0, 0]] * 50),
                       torch.full((50, 3), math.log(0.01)), torch.full((50,), -5.0), torch.zeros(50, 1, 3))
    both = Gaussians(**{f: torch.cat([getattr(g, f), getattr(hidden, f)]) for f in Gaussians.FIELDS})
    _, info = refine_to_radius(both, cams, 8.0, budget=both.num + 100, passes=1)
    assert info["pruned"] == 0  # the budget had room
    out, info = refine_to_radius(both, cams, 8.0, budget=both.num, passes=1)  # no room: unseen splats make it
    assert out.num <= both.num and 0 < info["pruned"] <= 50
    assert info["children"] - info["refined"] == info["pruned"] - (both.num - out.num)
    # every visible small splat survived
    visible_small = g.means[1:]
    assert all(bool((out.means == m).all(1).any()) for m in visible_small)


def test_a_stylization_runs_from_the_refined_scene_within_the_budget():
    """The pipeline refines before the pre-process; density control keeps the input's budget afterwards."""
    from tlvg_warp.stylize.config import StylizeConfig
    from tlvg_warp.stylize.pipeline import StylizeInputs, run_stylize

    g, cams = _scene(), _cams()
    photos = [render(g, c).color.detach().clamp(0, 1) for c in cams]
    style = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(0))
    cfg = StylizeConfig(iterations=6, phases=[2, 2, 2], vgg_weights="random", device="cpu", refine_radius=3.0,
                        stroke_scale=2.0, web_formats=False, orbit_frames=0, comparison_views=0)
    inp = StylizeInputs(g, cams, [f"v{i}" for i in range(3)], photos, style)
    res = run_stylize(inp, cfg, None, progress=False, quiet=True)
    m = res.metrics
    assert m["refine"]["refined"] >= 1 and m["refine"]["radius_px"] == 6.0  # refine_radius x stroke_scale
    assert m["gaussian_budget"] == (6 * g.num) // 5  # floor(1.2 x input), in integers
    assert m["gaussians_before_stylize"] <= m["gaussian_budget"] and res.gaussians.num <= m["gaussian_budget"]
