"""The sliced Wasserstein terms (tlvg_warp/losses/sliced.py) against independent oracles:
- equal sample counts: the sorted matching is the optimal assignment of the squared cost on each direction
  (oracle: SciPy's Hungarian solver on the full cost matrix, float64);
- unequal counts: each sorted render value meets the painting's at the same mid-rank quantile (numpy);
- the gradient against central finite differences (float64);
- zero for any reordering of the painting's own samples, not for a shifted copy;
- descent on a one-colour blob reaches a two-colour target in the target's proportions (what nearest-neighbour
  matching does not ask for: all samples may sit on the nearer colour);
- the painting's subsample: rows of the painting, none twice, seeded, its quantiles those of the whole;
- the draws: seeded, different call to call, and a resumed counter draws what an uninterrupted run would;
- the cell grid VGG's features have, for the coverage of the feature term.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from tlvg_warp.losses import VGG16Features
from tlvg_warp.losses.sliced import SlicedWasserstein, quantile_index, random_directions, sliced_wasserstein, subsample


def _dirs(d, p, seed=0):
    return random_directions(d, p, seed, "cpu").double()


def test_directions_are_unit_and_seeded():
    a, b, c = _dirs(5, 7, 3), _dirs(5, 7, 3), _dirs(5, 7, 4)
    assert a.shape == (5, 7)
    assert torch.allclose(a.norm(dim=0), torch.ones(7, dtype=torch.float64), atol=1e-6)
    assert torch.equal(a, b) and not torch.allclose(a, c)


def test_equal_counts_match_the_optimal_assignment():
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(9, 4)), rng.normal(size=(9, 4)) * 2 + 0.5
    dirs = _dirs(4, 6, 2)
    got = float(sliced_wasserstein(torch.from_numpy(x), torch.from_numpy(y), dirs))
    want = []
    for d in dirs.numpy().T:  # per direction: the cheapest one-to-one matching of the squared distances
        px, py = x @ d, y @ d
        cost = (px[:, None] - py[None, :]) ** 2
        r, c = linear_sum_assignment(cost)
        want.append(cost[r, c].mean())
    assert got == pytest.approx(float(np.mean(want)), rel=1e-12)


def test_unequal_counts_meet_at_the_same_quantile():
    rng = np.random.default_rng(2)
    x, y = rng.normal(size=(5, 3)), rng.normal(size=(23, 3))
    dirs = _dirs(3, 4, 5)
    got = float(sliced_wasserstein(torch.from_numpy(x), torch.from_numpy(y), dirs))
    px, py = np.sort(x @ dirs.numpy(), axis=0), np.sort(y @ dirs.numpy(), axis=0)
    rows = [int(np.floor((k + 0.5) * 23 / 5)) for k in range(5)]  # mid-ranks: 2, 6, 11, 16, 20
    assert rows == [2, 6, 11, 16, 20] and quantile_index(5, 23, "cpu").tolist() == rows
    assert got == pytest.approx(float(((px - py[rows]) ** 2).mean()), rel=1e-12)


def test_gradient_matches_finite_differences():
    rng = np.random.default_rng(3)
    x = torch.from_numpy(rng.normal(size=(7, 3))).requires_grad_(True)
    y = torch.from_numpy(rng.normal(size=(11, 3)))
    dirs = _dirs(3, 5, 7)
    sliced_wasserstein(x, y, dirs).backward()
    num = torch.zeros_like(x)
    h = 1e-6
    for i in range(7):
        for j in range(3):
            xp, xm = x.detach().clone(), x.detach().clone()
            xp[i, j] += h
            xm[i, j] -= h
            num[i, j] = (sliced_wasserstein(xp, y, dirs) - sliced_wasserstein(xm, y, dirs)) / (2 * h)
    assert torch.allclose(x.grad, num, atol=1e-7)


def test_zero_for_a_reordering_of_the_target_only():
    rng = np.random.default_rng(4)
    y = torch.from_numpy(rng.normal(size=(30, 6)))
    dirs = _dirs(6, 16, 1)
    assert float(sliced_wasserstein(y[torch.randperm(30)], y, dirs)) == pytest.approx(0.0, abs=1e-24)
    assert float(sliced_wasserstein(y + 0.1, y, dirs)) > 1e-3


def test_descent_reaches_the_targets_proportions():
    """The target: 1/4 yellow, 3/4 blue. Start: every sample the same grey-blue, nearer the blue. Nearest-colour
    matching would send them all to blue; the distribution term must turn a quarter of them yellow."""
    yellow, blue = np.array([0.95, 0.85, 0.2]), np.array([0.1, 0.2, 0.6])
    y = torch.from_numpy(np.vstack([np.tile(yellow, (100, 1)), np.tile(blue, (300, 1))]))
    rng = np.random.default_rng(5)
    x = torch.from_numpy(np.array([0.3, 0.35, 0.5]) + 0.01 * rng.normal(size=(200, 3))).requires_grad_(True)
    fn = SlicedWasserstein(y, count=32, seed=9)
    opt = torch.optim.Adam([x], lr=0.01)
    for _ in range(600):
        opt.zero_grad()
        fn(x).backward()
        opt.step()
    xs = x.detach().numpy()
    near_yellow = np.linalg.norm(xs - yellow, axis=1) < np.linalg.norm(xs - blue, axis=1)
    assert near_yellow.mean() == pytest.approx(0.25, abs=0.03)
    assert np.linalg.norm(xs[near_yellow].mean(0) - yellow) < 0.05
    assert np.linalg.norm(xs[~near_yellow].mean(0) - blue) < 0.05


def test_draws_move_per_call_and_resume():
    y = torch.from_numpy(np.random.default_rng(6).normal(size=(40, 4)))
    x = y[:20] * 0.5
    a, b = SlicedWasserstein(y, 8, seed=3), SlicedWasserstein(y, 8, seed=3)
    first, second = float(a(x)), float(a(x))
    assert first != second  # new directions each call
    b.calls = 1  # a resumed run: the counter restored
    assert float(b(x)) == second
    # divided by the target's spread: scaling both sets leaves the value unchanged
    assert float(SlicedWasserstein(y * 10, 8, seed=3)(x * 10)) == pytest.approx(first, rel=1e-9)


@pytest.mark.parametrize("hw,scale", [((24, 32), 1.0), ((37, 50), 0.5), ((378, 504), 0.5), ((10, 14), 1.0)])
def test_cell_average_has_the_feature_grid(hw, scale):
    """cell_average's grid is the grid of the features VGG gives for an image of that size (random weights: only
    the shapes matter); at scale 1 a cell is the mean of its 4x4 pixel block."""
    net = VGG16Features().eval()  # default initialization: only the shapes matter
    h, w = hw
    with torch.no_grad():
        feats = net(torch.rand(1, 3, h, w), scale)  # [1,768,h',w']
    mask = torch.from_numpy(np.random.default_rng(7).random((h, w)))
    cells = VGG16Features.cell_average(mask, scale)
    assert tuple(cells.shape) == tuple(feats.shape[-2:])
    if scale == 1.0 and min(h, w) >= 16:
        blocks = mask.numpy()[:cells.shape[0] * 4, :cells.shape[1] * 4].reshape(cells.shape[0], 4, cells.shape[1], 4)
        assert np.allclose(cells.numpy(), blocks.mean(axis=(1, 3)), atol=1e-12)


def test_the_paintings_subsample_keeps_its_distribution():
    y = torch.from_numpy(np.random.default_rng(8).random((200_000, 3)) ** np.array([1.0, 2.0, 0.5]))
    assert subsample(y, 300_000, 1) is y  # under the limit: every row
    a, b = subsample(y, 65536, 1), subsample(y, 65536, 1)
    assert a.shape == (65536, 3) and torch.equal(a, b) and not torch.equal(a, subsample(y, 65536, 2))
    rows = {tuple(r) for r in y.numpy()}
    assert len({tuple(r) for r in a.numpy()}) == 65536 and all(tuple(r) in rows for r in a.numpy()[:2000])
    q = np.linspace(0.01, 0.99, 99)  # a subset's quantiles are the painting's up to sampling noise (~1/sqrt(n))
    assert np.abs(np.quantile(a.numpy(), q, axis=0) - np.quantile(y.numpy(), q, axis=0)).max() < 0.01
    assert SlicedWasserstein(y, 4, seed=5, max_target=65536).target.shape == (65536, 3)
