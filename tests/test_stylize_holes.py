"""No holes or cracks from density control . The demo scene, 8 views at 80x60, 60 iterations with
density control every 10 (it fills the Gaussian budget at its first step: the stylization's gradients pass
3DGS's threshold nearly everywhere at this size), random VGG. Measured against the un-stylized scene:
- holes: pixels with stylized alpha < 0.5 where the un-stylized alpha >= 0.5;
- cracks: stylized alpha < 0.9 where the un-stylized alpha >= 0.9;
at the training size and at 2x (a camera of twice the resolution, where thin gaps between splats show).
Measured here: 3DGS splits (children sampled in the parent, scales / 1.6) leave cracks of 2.1% at 2x (13.4% before
the style terms stopped seeing the empty background); the moment-matched split 0.02% / 0.12%, holes 0."""
import dataclasses
import math

import pytest
import torch

from tlvg_warp import render
from _demo_helpers import demo_stylize_inputs
from tlvg_warp.stylize import run_stylize
from tlvg_warp.stylize.config import config_from_dict

W, H, VIEWS = 80, 60, 8
HOLES_MAX = 0.01  # the bound a stylization must meet, at 1x and 2x
CRACKS_MAX = 0.01  # ten times under what 3DGS splits leave here
COUNT_MAX = 1.2  # Gaussians relative to the input (the default budget)


@pytest.fixture(scope="module")
def demo():
    return demo_stylize_inputs(VIEWS, W, H, spacing=2.0)


def _scaled(cam, k):
    return dataclasses.replace(cam, width=cam.width * k, height=cam.height * k, fx=cam.fx * k, fy=cam.fy * k,
                               cx=cam.cx * k, cy=cam.cy * k)


def coverage_loss(g0, g1, cams, k) -> tuple[float, float]:
    """(holes, cracks) of g1 against g0 over the views at k times their resolution."""
    tot = holes = cracks = base = 0
    for cam in cams:
        c = _scaled(cam, k)
        with torch.no_grad():
            a0, a1 = render(g0, c, (1, 1, 1)).alpha, render(g1, c, (1, 1, 1)).alpha
        cov = a0 >= 0.5
        tot += int(cov.sum())
        holes += int((cov & (a1 < 0.5)).sum())
        full = a0 >= 0.9
        base += int(full.sum())
        cracks += int((full & (a1 < 0.9)).sum())
    return holes / tot, cracks / base


def _run(inp, **kw):
    cfg = config_from_dict({"iterations": 60, "device": "cpu", "vgg_weights": "random", "density.interval": 10,
                            "log_every": 10, **kw})
    return run_stylize(inp, cfg, None, progress=False, quiet=True)


def test_stylized_demo_has_no_holes_or_cracks(demo):
    ds, inp = demo
    res = _run(inp)
    assert any(e["split"] > 0 for e in res.metrics["densify_events"])  # density control did split
    assert res.gaussians.num <= math.floor(COUNT_MAX * ds.gaussians.num + 1e-6)
    for k in (1, 2):
        holes, cracks = coverage_loss(ds.gaussians, res.gaussians, ds.cameras, k)
        assert holes <= HOLES_MAX and cracks <= CRACKS_MAX, (k, holes, cracks)


def test_3dgs_splits_crack_here(demo):
    """The same run with graphdeco's split (abcgs.yaml's choice): the measure sees the cracks."""
    ds, inp = demo
    res = _run(inp, **{"density.split_mode": "3dgs"})
    _, cracks = coverage_loss(ds.gaussians, res.gaussians, ds.cameras, 2)
    assert cracks > 1.5 * CRACKS_MAX, cracks


def _large_splat_threshold(ds, quantile: float) -> float:
    """max_world_size (a fraction of the scene extent) that the given quantile of the demo's splats exceeds."""
    from tlvg_warp.train.init import scene_extent

    size = ds.gaussians.log_scales.detach().exp().amax(dim=1)  # [N] largest axis
    return float(torch.quantile(size, quantile)) / scene_extent(list(ds.cameras))


def test_fitted_scenes_large_splats_survive_stylization(demo):
    """The holes of deleting large splats: a fitted scene keeps large splats (no opacity reset ever pruned them), and the
    stylization's density control deleted them at its first step (size_rules 'always'; fern 126x94: 35% holes).
    Now the size rules split them (size_rules 'split', the stylize default): with a world-size limit that 30% of
    the demo's splats exceed, holes stay under the bound at 1x and 2x; with 'always' the same run loses those
    splats and the measure sees it; and with gradients unable to trigger a split, the size rules alone split
    (and delete nothing), so the large splats are refined, not kept whole as 'after_reset' would."""
    ds, inp = demo
    limit = {"density.max_world_size": _large_splat_threshold(ds, 0.7)}
    res = _run(inp, **limit)
    assert res.gaussians.num <= math.floor(COUNT_MAX * ds.gaussians.num + 1e-6)
    for k in (1, 2):
        holes, _ = coverage_loss(ds.gaussians, res.gaussians, ds.cameras, k)
        assert holes <= HOLES_MAX, (k, holes)
    pruned = _run(inp, **limit, **{"density.size_rules": "always"})
    holes, _ = coverage_loss(ds.gaussians, pruned.gaussians, ds.cameras, 1)
    assert holes > 5 * HOLES_MAX, holes
    forced = _run(inp, **limit, **{"density.grad_threshold": 1e9, "density.min_opacity": 0.0,
                                   "density.prune_unseen": False})
    events = forced.metrics["densify_events"]
    assert sum(e["split"] for e in events) > 0 and sum(e["cloned"] + e["pruned"] for e in events) == 0, events
