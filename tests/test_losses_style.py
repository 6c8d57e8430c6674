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
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    cos = (a * b).sum(1) / np.maximum(den, 1e-300)  # a dead (all-zero) channel has cosine 0, as torch's
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


# ----------------------------------------------------------------------------- the cheaper FAST
def ill_conditioned(seed=11, c=40, nc=120, ns=90):
    """ReLU-like features with what relu3 features have: dead channels (all zero), an exact duplicate, an exact
    linear combination and a near-collinear pair (A's live spectrum then spans ~10 decades)."""
    rng = np.random.default_rng(seed)
    f = np.abs(rng.standard_normal((c, nc + ns)))
    f[3] = f[17] = 0
    f[5] = f[4]
    f[9] = 0.5 * f[10] + 0.5 * f[11]
    f[8] = f[7] + 1e-4 * np.abs(rng.standard_normal(nc + ns))
    return f[:, :nc], f[:, nc:]


def rel(x, y):
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return np.linalg.norm(x - y) / np.linalg.norm(y)


# cholesky64 (the default for float32 features) against the float64 LU oracle. Well-conditioned: round-off only.
# Ill-conditioned: its Jacobi ridge (1e-10 of each channel's diagonal, there for a safe float64 Cholesky) shifts
# the eigen-directions near 1e-9 by a few percent of their share; measured 2.4e-3 (float64 in) and 3.8e-3
# (float32 in), where the reference code's LU of the float32-formed A (the loop before the cheaper FAST) is off by 4e-2.
CHOL64_TOL_WELL = 1e-7
CHOL64_TOL_ILL = 1e-2


def test_fast_solves_against_float64_oracle():
    a, s = feats(20, 30, 200), feats(21, 30, 150)
    _, b_np, _ = fast_numpy(a, s)
    at, st = torch.from_numpy(a), torch.from_numpy(s)
    assert rel(fast_target(at, st, solve="cholesky64").numpy(), b_np) < CHOL64_TOL_WELL
    assert rel(fast_target(at, st, solve="lu64").numpy(), b_np) < ORACLE_TOL * 10
    assert rel(fast_target(at, st).numpy(), b_np) < ORACLE_TOL * 10  # auto: float64 in -> the oracle's LU
    a, s = ill_conditioned()
    _, b_np, _ = fast_numpy(a, s)
    errs = {}
    for dt in (torch.float64, torch.float32):
        at, st = torch.from_numpy(a).to(dt), torch.from_numpy(s).to(dt)
        for solve in ("cholesky64", "lu64", "cholesky32"):
            errs[solve, dt] = rel(fast_target(at, st, solve=solve).double().numpy(), b_np)
    assert errs["cholesky64", torch.float64] < CHOL64_TOL_ILL and errs["cholesky64", torch.float32] < CHOL64_TOL_ILL
    # on float32 features the new default is closer to the float64 answer than the old float64 LU was
    assert errs["cholesky64", torch.float32] < errs["lu64", torch.float32]
    assert errs["cholesky32", torch.float32] < 0.1  # opt-in: a larger ridge, a few percent
    # the loss's gradient (b fixed) follows b: cholesky64 with float32 features vs the oracle's b
    x = torch.from_numpy(a).float().requires_grad_(True)
    fast_loss(x, torch.from_numpy(s).float()).backward()
    y = torch.from_numpy(a).float().requires_grad_(True)
    (1 - torch.nn.functional.cosine_similarity(y, torch.from_numpy(b_np).float(), dim=1)).mean().backward()
    assert rel(x.grad.numpy(), y.grad.numpy()) < 2 * CHOL64_TOL_ILL


def test_fast_solve_fallback_is_identity_and_bad_solve_name():
    a, s = torch.from_numpy(feats(22, 6, 30)), torch.from_numpy(feats(23, 6, 20))
    P, ok = style_mod.fast_projection(a, s)
    assert bool(ok) and P.shape == (6, 6)
    a_nan = a.clone()
    a_nan[0, 0] = float("nan")
    P, ok = style_mod.fast_projection(a_nan, s, solve="cholesky64")
    assert not bool(ok)  # decided on the device; fast_target then returns a itself (the reference code's fallback)
    b = fast_target(a_nan, s, solve="cholesky64")
    assert torch.equal(torch.isnan(b), torch.isnan(a_nan)) and torch.equal(b[1:], a_nan[1:])
    with pytest.raises(ValueError, match="solve"):
        fast_loss(a, s, solve="float16")


def test_nearest_cell_is_the_float64_argmax(monkeypatch):
    """The k = 1 match (NNFM, the field match) against numpy's float64 argmax of the cosines, whole and in row chunks,
    with and without the column pass. A painting with cells repeated gives ties up to the product's rounding: there
    either copy is right, and its cosine is the maximum (catches argmax over the wrong axis or a chunk's offset)."""
    a, s = feats(30, 6, 23), feats(31, 6, 17)
    s = np.concatenate([s, s[:, 4:9]], 1)  # columns 17..21 repeat 4..8
    an, sn = a / np.linalg.norm(a, axis=0), s / np.linalg.norm(s, axis=0)
    sim = an.T @ sn
    def original(i):  # a copy's original column
        return np.where(i >= 17, i - 13, i)

    want = original(np.argmax(sim, 1))
    assert np.isin(want, np.arange(4, 9)).any()  # some render cells' nearest is a repeated one
    for budget in (1 << 25, 40):
        monkeypatch.setattr(style_mod, "SIM_BUDGET", budget)
        for need_cols in (False, True):
            idx_r, _ = style_mod._topk_both(torch.from_numpy(a), style_mod.StyleFeatures(torch.from_numpy(s)), 1,
                                            need_cols=need_cols)
            got = idx_r[:, 0].numpy()
            assert idx_r.shape == (23, 1) and np.array_equal(original(got), want)
            assert np.allclose(sim[np.arange(23), got], sim.max(1), rtol=0, atol=1e-12)


@pytest.mark.parametrize("two", [False, True])
def test_padded_painting_columns_change_no_match(monkeypatch, two):
    """The painting's unit columns padded to a multiple of 8 (as on CUDA, forced here): the padding cells never win,
    whatever the cosines' sign (features with negative entries make every real cosine negative for some render
    cells, where a padding cell's 0 would beat them), whole and in row chunks; the column pass is unchanged."""
    g = np.random.default_rng(5)
    a, s = g.normal(size=(6, 40)), np.abs(g.normal(size=(6, 21))) + 0.1  # 21 painting cells: 3 padding columns
    a[:, :5] = -np.abs(a[:, :5])  # render cells 0-4 point away from every (positive) painting cell
    an, sn = a / np.linalg.norm(a, axis=0), s / np.linalg.norm(s, axis=0)
    sim = an.T @ sn
    assert (sim.max(1) < 0).any()  # a 0 would win there
    monkeypatch.setattr(style_mod, "PAD_COLUMNS", True)
    monkeypatch.setattr(style_mod, "TWO_PRODUCTS", two)
    st = style_mod.StyleFeatures(torch.from_numpy(s))
    for budget in (1 << 25, 50):
        monkeypatch.setattr(style_mod, "SIM_BUDGET", budget)
        for k in (1, 3):
            idx_r, idx_c = style_mod._topk_both(torch.from_numpy(a), st, k, need_cols=two)
            assert int(idx_r.max()) < 21
            np.testing.assert_array_equal(idx_r.numpy(), np.argsort(-sim, 1, kind="stable")[:, :k])
            if two:
                np.testing.assert_array_equal(np.sort(idx_c.numpy(), 1), np.sort(np.argsort(-sim.T, 1)[:, :k], 1))
    assert st.unit(torch.float64, 8).shape == (6, 24) and float(st.unit(torch.float64, 8)[:, 21:].abs().sum()) == 0


def _dense_union(idx_r, idx_c, nc: int, ns: int) -> np.ndarray:
    """FAST's U built densely [Nc,Ns]: 1 where a render cell's row pass or a style cell's column pass picked the pair."""
    U = np.zeros((nc, ns))
    U[np.arange(nc)[:, None], idx_r.numpy()] = 1
    U[idx_c.numpy(), np.arange(ns)[:, None]] = 1
    return U


def test_topk_both_and_union_against_dense_brute_force(monkeypatch):
    a, s = feats(24, 7, 29), feats(25, 7, 41)  # 29 render cells: padded to 32 in the column product
    an, sn = a / np.linalg.norm(a, axis=0), s / np.linalg.norm(s, axis=0)
    sim = an.T @ sn
    # one product or chunks of it; the CUDA layout (a second, transposed product over padded cells) or the CPU's
    for budget, two in ((1 << 25, False), (50, False), (1 << 25, True), (50, True)):
        monkeypatch.setattr(style_mod, "SIM_BUDGET", budget)
        monkeypatch.setattr(style_mod, "TWO_PRODUCTS", two)
        st = style_mod.StyleFeatures(torch.from_numpy(s))
        idx_r, idx_c = style_mod._topk_both(torch.from_numpy(a), st, 5)
        assert np.array_equal(np.sort(idx_r.numpy(), 1), np.sort(np.argsort(-sim, 1)[:, :5], 1))
        assert np.array_equal(np.sort(idx_c.numpy(), 1), np.sort(np.argsort(-sim.T, 1)[:, :5], 1))
        keep, u1, us = style_mod._fast_union(idx_r, idx_c, a.shape[1], st)
        U = _dense_union(idx_r, idx_c, 29, 41)
        assert float(keep.sum()) + 29 * 5 == U.sum()
        assert np.allclose(u1.numpy(), U.sum(1), atol=1e-12) and np.allclose(us.numpy(), U @ s.T, atol=1e-12)


def test_cosine_distance_backward_matches_autograd_and_dead_rows():
    gen = torch.Generator().manual_seed(0)
    x0 = torch.rand(6, 9, generator=gen, dtype=torch.float64)
    y = torch.rand(6, 9, generator=gen, dtype=torch.float64)
    x0[2] = 0  # a dead channel: cosine 0, gradient ŷ/eps as torch's (the ReLU's mask zeroes it upstream)
    for dim in (0, 1):
        x1, x2 = x0.clone().requires_grad_(True), x0.clone().requires_grad_(True)
        l1 = style_mod.cosine_distance_to_fixed(x1, y, dim=dim)
        l2 = (1 - torch.nn.functional.cosine_similarity(x2, y, dim=dim)).mean()
        l1.backward()
        l2.backward()
        assert abs(l1.item() - l2.item()) < 1e-14
        assert torch.allclose(x1.grad, x2.grad, rtol=1e-12, atol=1e-12)
    # finite differences of the hand-written backward away from the dead row
    x = torch.rand(4, 7, generator=gen, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: style_mod.cosine_distance_to_fixed(t, y[:4, :7], dim=1), (x,))


def test_layered_gram_against_outer_products_and_finite_differences():
    """gram_layers: per block of rows (a layer), ||G - G_p|| / ||G_p|| (Frobenius) with G the mean of the cells' outer
    products, averaged over the three blocks; a block's scale does not change its share (the loss is scale-free per
    layer), and the analytic gradient agrees with finite differences (float64)."""
    a, s = feats(31, 6, 12), feats(32, 6, 20)

    def oracle(a, s):
        out = []
        for b in range(3):
            x, y = a[2 * b:2 * b + 2], s[2 * b:2 * b + 2]
            gx = sum(np.outer(x[:, i], x[:, i]) for i in range(x.shape[1])) / x.shape[1]
            gy = sum(np.outer(y[:, i], y[:, i]) for i in range(y.shape[1])) / y.shape[1]
            out.append(np.sqrt(((gx - gy) ** 2).sum() / (gy ** 2).sum()))
        return float(np.mean(out))

    fn = style_mod.StyleLoss(torch.from_numpy(s), "gram_layers")
    assert abs(fn(torch.from_numpy(a)).item() - oracle(a, s)) < ORACLE_TOL
    scaled_a, scaled_s = a.copy(), s.copy()
    scaled_a[4:] *= 50.0
    scaled_s[4:] *= 50.0  # one layer's features 50x larger in both: the same loss
    assert abs(style_mod.StyleLoss(torch.from_numpy(scaled_s), "gram_layers")(torch.from_numpy(scaled_a)).item()
               - oracle(a, s)) < ORACLE_TOL
    x = torch.from_numpy(a).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: fn(t), (x,))


def test_style_features_precomputed_give_the_same_losses():
    a, s = torch.from_numpy(feats(26, 8, 40)), torch.from_numpy(feats(27, 8, 33))
    st = style_mod.StyleFeatures(s)
    assert abs(fast_loss(a, st).item() - fast_loss(a, s).item()) < 1e-14
    assert abs(nnfm_loss(a, st).item() - nnfm_loss(a, s).item()) < 1e-14
    assert abs(gram_loss(a, st).item() - gram_loss(a, s).item()) < 1e-14
    for kind, fn in (("fast", fast_loss), ("nnfm", nnfm_loss), ("gram", gram_loss)):
        assert abs(style_mod.StyleLoss(st, kind)(a).item() - fn(a, s).item()) < 1e-14
    assert st.like(a.float()).dtype == torch.float32 and st.like(a) is st


def test_style_loss_cache_refresh_every_one_equals_no_cache():
    s = torch.from_numpy(feats(28, 8, 33))
    plain, cached = style_mod.StyleLoss(s), style_mod.StyleLoss(s, refresh_every=1)
    for step in range(6):
        a0 = torch.from_numpy(feats(100 + step, 8, 40))
        x1, x2 = a0.clone().requires_grad_(True), a0.clone().requires_grad_(True)
        l1, l2 = plain(x1), cached(x2, key=step % 2)
        l1.backward()
        l2.backward()
        assert l1.item() == l2.item() and torch.equal(x1.grad, x2.grad)
        assert l1.item() == fast_loss(a0, s).item()
    assert cached.refreshes == 6 and not cached._cache


def test_style_loss_cache_reuses_the_projection_per_key():
    s = torch.from_numpy(feats(29, 8, 33))
    loss = style_mod.StyleLoss(s, refresh_every=3)
    seen = {}
    for call in range(7):
        for key in ("v0", "v1"):
            a = torch.from_numpy(feats(200 + 10 * call + (key == "v1"), 8, 40))
            if call % 3 == 0:  # refresh: the match and the solve of these features
                seen[key] = style_mod.fast_projection(a, s)
                assert loss(a, key=key).item() == fast_loss(a, s).item()
            else:  # the key's last projection applied to the current features
                P, ok = seen[key]
                want = style_mod.cosine_distance_to_fixed(a, torch.where(ok, P.T @ a, a), dim=1)
                got = loss(a, key=key)
                assert got.item() == want.item() and got.item() != fast_loss(a, s).item()
    assert loss.refreshes == 2 * 3  # calls 0, 3, 6 of each key
    assert loss.match_of("v0").shape == (40, 5)
    # no key: nothing cached; reset() drops the cache
    a = torch.from_numpy(feats(300, 8, 40))
    assert loss(a).item() == fast_loss(a, s).item() and loss.refreshes == 7
    loss.reset()
    assert loss.match_of("v0") is None
    nn = style_mod.StyleLoss(s, "nnfm", refresh_every=2)
    assert nn(a, key=0).item() == nnfm_loss(a, s).item()
    b = torch.from_numpy(feats(301, 8, 40))
    nn_a = match_style_cells(a, s, 1)[0][:, 0]  # the second call of key 0 keeps the first call's neighbours
    assert nn(b, key=0).item() == style_mod.cosine_distance_to_fixed(b, s[:, nn_a], dim=0).item()
    assert nn.refreshes == 1
    with pytest.raises(ValueError):
        style_mod.StyleLoss(s, refresh_every=0)


def test_style_loss_match_cache_redoes_the_solve():
    s = torch.from_numpy(feats(30, 8, 33))
    loss = style_mod.StyleLoss(s, refresh_every=2, cache="match")
    a0, a1 = torch.from_numpy(feats(400, 8, 40)), torch.from_numpy(feats(401, 8, 40))
    assert loss(a0, key=0).item() == fast_loss(a0, s).item()
    idx0 = style_mod._topk_both(a0, style_mod.StyleFeatures(s), 5)
    P, ok = style_mod.fast_projection(a1, s, idx=idx0)  # a0's match, a1's own A, B and solve
    want = style_mod.cosine_distance_to_fixed(a1, torch.where(ok, P.T @ a1, a1), dim=1)
    assert loss(a1, key=0).item() == want.item() and loss.refreshes == 1
    with pytest.raises(ValueError, match="cache"):
        style_mod.StyleLoss(s, cache="all")


@pytest.mark.parametrize("cache", ["projection", "match"])
def test_style_loss_state_dict_resumes_the_cache(cache):
    """A StyleLoss rebuilt from another's state_dict (a resumed stylization) gives, call for call, what the
    original gives: it reuses the saved matches until their refresh is due. Catches a resume that drops the
    cache (the restored loss would refresh at once and equal fast_loss) or forgets the per-key call counts
    (it would refresh one call early or late)."""
    s = torch.from_numpy(feats(31, 8, 33))
    a_loss = style_mod.StyleLoss(s, refresh_every=3, cache=cache)
    for call in range(4):  # key 0: refreshed at call 0 and 3; key 1: at call 0
        a_loss(torch.from_numpy(feats(500 + call, 8, 40)), key=0)
        if call < 2:
            a_loss(torch.from_numpy(feats(600 + call, 8, 40)), key=1)
    sd = a_loss.state_dict()
    b_loss = style_mod.StyleLoss(s, refresh_every=3, cache=cache)
    b_loss.load_state_dict(sd)
    assert b_loss.refreshes == a_loss.refreshes == 3
    for call in range(4):
        for key in (0, 1):
            x = torch.from_numpy(feats(700 + 10 * call + key, 8, 40))
            want, got = a_loss(x, key=key).item(), b_loss(x, key=key).item()
            assert got == want
            if (key, call) in ((0, 0), (0, 1), (1, 0)):  # reused matches: not FAST of these features
                assert got != fast_loss(x, s).item()
    assert b_loss.refreshes == a_loss.refreshes


@pytest.mark.parametrize("before", [False, True])
def test_fast_union_leaves_torch_deterministic_flag_as_it_found_it(before):
    """_fast_union sums through torch's deterministic path (CUDA's atomic index_add_ made abcgs's GPU runs drift
    apart) and must hand the process back its own setting, on or off, warn-only kept: a leaked flag would make every
    later nondeterministic op of a user's process warn or raise. Oracle: the flag read before and after, and the
    union's sums against the dense U of the test above."""
    a, s = feats(24, 7, 29), feats(25, 7, 41)
    st = style_mod.StyleFeatures(torch.from_numpy(s))
    idx_r, idx_c = style_mod._topk_both(torch.from_numpy(a), st, 5)
    was = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(before, warn_only=before)
    try:
        _, _, us = style_mod._fast_union(idx_r, idx_c, a.shape[1], st)
        assert torch.are_deterministic_algorithms_enabled() is before
        assert torch.is_deterministic_algorithms_warn_only_enabled() is before
    finally:
        torch.use_deterministic_algorithms(was[0], warn_only=was[1])
    assert np.allclose(us.numpy(), _dense_union(idx_r, idx_c, 29, 41) @ s.T, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the CUDA chunk budget")
def test_cuda_chunk_budget_changes_no_match(monkeypatch):
    """On CUDA a match in its few large chunks picks what many small chunks pick: the same painting
    cell per render cell, or (a float16 tie) one whose float64 cosine is as high within float16's rounding. 9,003
    painting cells: the product runs on columns padded to 9,008, and no padding cell is picked."""
    g = torch.Generator().manual_seed(3)
    a = torch.rand(64, 3000, generator=g).cuda()
    s = style_mod.StyleFeatures(torch.rand(64, 9003, generator=g).cuda())
    big = style_mod._topk_both(a, s, 1, need_cols=False)[0][:, 0]
    monkeypatch.setattr(style_mod, "SIM_BUDGET_CUDA", 100_000)  # 11 rows a chunk: 273 chunks
    monkeypatch.setattr(style_mod, "SIM_ROWS_CUDA", 1)
    small = style_mod._topk_both(a, s, 1, need_cols=False)[0][:, 0]
    an, sn = torch.nn.functional.normalize(a.double(), dim=0), torch.nn.functional.normalize(s.s.double(), dim=0)
    cos = an.T @ sn  # [3000, 9003]
    rows = torch.arange(3000, device=a.device)
    assert int(big.max()) < 9003 and int(small.max()) < 9003
    assert (big == small).float().mean() > 0.99
    assert torch.allclose(cos[rows, big], cos[rows, small], atol=2e-3, rtol=0)


@pytest.mark.parametrize("n_cols", [1, 9_003, 14_194, 57_000, 131_072, 299_636, 1 << 29])
def test_chunk_rows_bounds(n_cols):
    """A chunk's rows on CUDA: at least SIM_ROWS_CUDA rows or SIM_BUDGET elements (whichever is more), never more
    than SIM_BUDGET_CUDA elements unless one row alone is larger; on the CPU SIM_BUDGET elements. Checked in
    integers against the bounds, not the formula: a rule that dropped the floor (fern's 14,194 painting cells:
    2,363 rows, not 18,911) or the cap (the 4 MP painting: 895 rows, not 2,048) fails."""
    rows = style_mod._chunk_rows(n_cols, cuda=True)
    cap = style_mod.SIM_BUDGET_CUDA
    assert rows >= 1
    assert rows * n_cols <= cap or rows == 1
    floor = max(style_mod.SIM_ROWS_CUDA, style_mod.SIM_BUDGET // n_cols)  # SIM_BUDGET's rows: floor division
    assert rows >= min(floor, max(1, cap // n_cols))
    assert rows <= max(floor, 1)  # no more than the floor asks: the memory the rule saves
    cpu = style_mod._chunk_rows(n_cols, cuda=False)
    assert cpu * n_cols <= style_mod.SIM_BUDGET or cpu == 1
    assert (cpu + 1) * n_cols > style_mod.SIM_BUDGET
    if n_cols == 14_194:
        assert rows == 2_363 and rows * n_cols <= style_mod.SIM_BUDGET  # one 32M chunk's worth, not 512 MB
    if n_cols == 299_636:
        assert rows == cap // n_cols == 895
