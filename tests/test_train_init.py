"""Initialization: kNN scales against brute force, scene extent, random frustum points, refusals."""
import math
from types import SimpleNamespace

import pytest
import torch

from tlvg_warp import Camera, InputError
from tlvg_warp.train.init import (from_points, initialize, knn_distances, knn_scale, random_in_frustums,
                                  scene_extent)
from tlvg_warp.types import SH_C0

DIST_TOL = 1e-5  # float32 distances of O(1) values (cdist vs the expanded-difference oracle)


def brute_knn(x, k):
    d = (x[:, None, :].double() - x[None, :, :].double()).norm(dim=-1)
    d.fill_diagonal_(math.inf)
    return d.sort(dim=1).values[:, :k]


@pytest.mark.parametrize("n,chunk", [(257, 1000), (50, 1 << 24), (5, 7)])
def test_knn_matches_brute_force(n, chunk):
    x = torch.randn(n, 3, generator=torch.Generator().manual_seed(n)) * torch.tensor([1.0, 3.0, 0.2])
    got = knn_distances(x, 3, chunk_elems=chunk)
    assert torch.allclose(got.double(), brute_knn(x, 3), atol=DIST_TOL)
    want = brute_knn(x, 3).square().mean(1).clamp_min(1e-7).sqrt()
    assert torch.allclose(knn_scale(x).double(), want, atol=DIST_TOL)


def test_knn_degenerate_sets():
    assert torch.isinf(knn_distances(torch.zeros(1, 3), 3)).all()
    d = knn_distances(torch.tensor([[0.0, 0, 0], [3.0, 4, 0]]), 3)
    assert d[0, 0] == pytest.approx(5.0) and torch.isinf(d[:, 1:]).all()
    assert torch.isfinite(knn_scale(torch.zeros(4, 3))).all()  # duplicates: clamped, finite


def test_from_points_colors_scales_identity():
    xyz = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0], [0, 0, 3.0], [1.0, 1.0, 1.0]])
    rgb = torch.tensor([[255, 0, 128]] * 5, dtype=torch.float32)  # 8-bit colors are recognized
    g = from_points(xyz, rgb, max_sh_degree=2, opacity=0.1)
    assert g.sh.shape == (5, 9, 3) and torch.all(g.sh[:, 1:] == 0)
    assert torch.allclose(g.sh[0, 0] * SH_C0 + 0.5, torch.tensor([1.0, 0.0, 128 / 255]), atol=1e-6)
    assert torch.allclose(g.opacities, torch.full((5,), 0.1))
    assert torch.equal(g.quats, torch.tensor([[1.0, 0, 0, 0]] * 5))
    assert torch.allclose(g.scales[:, 0], brute_knn(xyz, 3).square().mean(1).sqrt().float())
    assert torch.equal(g.log_scales[:, 0], g.log_scales[:, 2])


def ring_cameras(n=6, radius=3.0):
    return [Camera.look_at((radius * math.cos(a), radius * math.sin(a), 0.5), (0, 0, 0), width=40, height=30)
            for a in torch.linspace(0, 2 * math.pi, n + 1)[:-1].tolist()]


def test_scene_extent_is_graphdeco_radius():
    cams = ring_cameras(6, 3.0)
    centers = torch.stack([c.center for c in cams])
    want = 1.1 * (centers - centers.mean(0)).norm(dim=1).max()
    assert scene_extent(cams) == pytest.approx(float(want)) and scene_extent(cams) == pytest.approx(3.3, rel=1e-6)


def test_random_points_lie_in_some_frustum():
    cams = ring_cameras(5)
    pts = random_in_frustums(cams, 500, torch.Generator().manual_seed(0))
    inside = torch.zeros(500, dtype=torch.bool)
    for c in cams:  # independent check by projection
        p = pts @ c.R.T + c.t
        u, v = c.fx * p[:, 0] / p[:, 2] + c.cx, c.fy * p[:, 1] / p[:, 2] + c.cy
        inside |= (p[:, 2] > c.near) & (u >= 0) & (u <= c.width) & (v >= 0) & (v <= c.height)
    assert inside.all()
    ds = SimpleNamespace(cameras=cams, points=None)
    g, ext, what = initialize(ds, 1, random_points=300)
    assert g.num == 300 and "random" in what and ext == pytest.approx(3.3, rel=1e-6)


def test_points_behind_all_cameras_refused():
    cams = [Camera.look_at((0, -3, 0), (0, 0, 0)), Camera.look_at((0.5, -3, 0), (0.5, 0, 0))]
    behind = torch.tensor([[0.0, -10, 0], [0.3, -8, 0.1]])  # y < -3: behind both cameras
    ds = SimpleNamespace(cameras=cams, points=(behind, torch.rand(2, 3)))
    with pytest.raises(InputError, match="behind"):
        initialize(ds)
    ds.points = (torch.cat([behind, torch.tensor([[0.0, 0, 0]])]), torch.rand(3, 3))
    g, _, _ = initialize(ds)
    assert g.num == 1  # only the point in front is kept
