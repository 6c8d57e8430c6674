"""FAST / NNFM / Gram / content losses against straightforward float64 numpy implementations."""
import numpy as np
import pytest
import torch

from tlvg_warp.losses import content_loss, fast_loss, fast_target, gram_loss, match_style_cells, nnfm_loss
from tlvg_warp.losses import style as style_mod

ORACLE_TOL = 1e-9  # float64 on both sides; the only difference is operation order
FD_TOL = 1e-6  # central differences with h = 1e-6 in float64: truncation ~h², round-off ~1e-10/h


def fast_numpy(a, s, k=5):
    """The reference code's FAST written plainly: dense U by sorting, dense solve."""
    an, sn = a / np.linalg.norm(a, axis=0), s / np.linalg.norm(s, axis=0)
    sim = an.T @ sn  # [Nc, Ns]
    U = np.zeros_like(sim)
    for j in range(sim.shape[1]):  # top-k render rows of each style column
        U[np.argsort(-sim[:, j])[:k], j] = 1
    for i in range(sim.shape[0]):  # top-k style columns of each render row
        U[i, np.argsort(-sim[i])[:k]] = 1
    U /= U.sum()
    A = a @ np.diag(U.sum(1)) @ a.T + 1e-12 * np.eye(a.shape[0])
    B = a @ U @ s.T
    b = np.linalg.solve(A, B).T @ a
    cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return float(np.mean(1 - cos)), b, U


def feats(seed, c, n):
    return np.abs(np.random.default_rng(seed).standard_normal((c, n)))  # ReLU-like, non-negative


# one chunk, and many chunks (column top-k merged across); more channels than render cells takes the
# low-rank solve (an Nc x Nc system) instead of the C x C one
@pytest.mark.parametrize("budget,channels", [(1 << 25, 6), (37, 6), (1 << 25, 40)])
def test_fast_matches_numpy_oracle(monkeypatch, budget, channels):
    monkeypatch.setattr(style_mod, "SIM_BUDGET", budget)
    a, s = feats(0, channels, 30 if channels < 30 else 12), feats(1, channels, 23)
    want, b_np, U = fast_numpy(a, s)
    at = torch.from_numpy(a)
    assert abs(fast_loss(at, torch.from_numpy(s)).item() - want) < ORACLE_TOL
    assert np.abs(fast_target(at, torch.from_numpy(s)).numpy() - b_np).max() < ORACLE_TOL * np.abs(b_np).max()
    assert want > 1e-3  # the test distinguishes something
    # the returned match is each render cell's top-5 style cells, a subset of U's support
    _, idx = fast_loss(at, torch.from_numpy(s), return_match=True)
    assert idx.shape == (a.shape[1], 5) and (U[np.arange(a.shape[1])[:, None], idx.numpy()] > 0).all()


def test_fast_is_zero_when_projection_reproduces_render():
    # C orthonormal clusters of 5 identical cells, in both render and style (style scaled 2x): every cell's
    # mutual top-5 is exactly its own cluster, so A = B/2, P = 2I, b = 2a and cos(a, b) = 1 per channel.
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.standard_normal((4, 4)))
    a = np.repeat(q, 5, axis=1)  # [4, 20]
    assert fast_loss(torch.from_numpy(a), torch.from_numpy(2 * a)).item() < 1e-10
    assert fast_loss(torch.from_numpy(a), torch.from_numpy(feats(4, 4, 20))).item() > 1e-3


def test_fast_gradient_flows_through_a_with_b_fixed():
    a0, s = torch.from_numpy(feats(5, 5, 18)), torch.from_numpy(feats(6, 5, 14))
    b = fast_target(a0, s)  # held constant by the loss (no gradient through the match/projection)

    def f(a):  # the loss with the target frozen
        cos = (a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1))
        return (1 - cos).mean()

    a = a0.clone().requires_grad_(True)
    loss = fast_loss(a, s)
    loss.backward()
    assert abs(loss.item() - f(a0).item()) < 1e-12
    h = 1e-6
    fd = torch.zeros_like(a0)
    for i in range(a0.shape[0]):
        for j in range(a0.shape[1]):
            e = torch.zeros_like(a0)
            e[i, j] = h
            fd[i, j] = (f(a0 + e) - f(a0 - e)) / (2 * h)
    assert (a.grad - fd).abs().max() < FD_TOL
    assert s.grad is None


def test_nnfm_and_match_vs_brute_force():
    a, s = feats(7, 6, 25), feats(8, 6, 31)
    an, sn = a / np.linalg.norm(a, axis=0), s / np.linalg.norm(s, axis=0)
    d = 1 - an.T @ sn  # [Nc, Ns] cosine distances, all pairs
    assert abs(nnfm_loss(torch.from_numpy(a), torch.from_numpy(s)).item() - d.min(1).mean()) < ORACLE_TOL
    idx, w = match_style_cells(torch.from_numpy(a), torch.from_numpy(s), k=3)
    assert np.array_equal(idx.numpy(), np.argsort(d, axis=1)[:, :3])
    assert torch.allclose(w, torch.full((25, 3), 1 / 3, dtype=w.dtype))
    at = torch.from_numpy(a).requires_grad_(True)
    nnfm_loss(at, torch.from_numpy(s)).backward()
    assert torch.isfinite(at.grad).all() and at.grad.abs().sum() > 0


def test_gram_and_content_vs_brute_force():
    a, s = feats(9, 5, 12), feats(10, 5, 20)
    ga = sum(np.outer(a[:, i], a[:, i]) for i in range(12)) / 12
    gs = sum(np.outer(s[:, i], s[:, i]) for i in range(20)) / 20
    assert abs(gram_loss(torch.from_numpy(a), torch.from_numpy(s)).item() - ((ga - gs) ** 2).mean()) < ORACLE_TOL
    b = feats(11, 5, 12)
    assert abs(content_loss(torch.from_numpy(a), torch.from_numpy(b)).item() - ((a - b) ** 2).mean()) < ORACLE_TOL
