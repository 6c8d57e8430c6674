"""Style and content losses on VGG feature matrices [C, N] (channels x pixels, pixels row-major).

FAST (ABC-GS reference code, SPEC §3), NNFM (ARF), Gram, content MSE, and the render->style cell match the
"matched" stroke-field mapping reuses. Similarity matrices are built in row chunks so a ~100k x 20k match
never materializes at once.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

K_CROSS = 5  # FAST's mutual top-k (reference code)
RIDGE = 1e-12  # FAST's A + 1e-12*I (reference code)
SIM_BUDGET = 1 << 25  # elements per similarity chunk: 32M floats = 128 MB in float32


def match_dtype(t: torch.Tensor) -> torch.dtype:
    """The cosine similarities only rank candidates for the top-k match, so on CUDA they are computed in
    float16 (tensor cores; ~10x the float32 matmul, which bounded the stylize loop): unit vectors keep every
    product in range and a rank flips only between cells whose cosines differ by under ~1e-3. CPU keeps the
    input dtype (no fast half matmul there)."""
    return torch.float16 if t.is_cuda else t.dtype


def _unit(f: torch.Tensor) -> torch.Tensor:
    return F.normalize(f, p=2, dim=0)  # unit columns [C, N]


def _chunks(n_rows: int, n_cols: int):
    step = max(1, SIM_BUDGET // max(1, n_cols))
    for i0 in range(0, n_rows, step):
        yield i0, min(n_rows, i0 + step)


@torch.no_grad()
def _topk_both(a: torch.Tensor, s: torch.Tensor, k: int, need_cols: bool = True):
    """Cosine top-k in both directions, one chunked pass over render rows.
    Returns idx_r [Nc,kr] (best style cells per render cell) and idx_c [kc,Ns] (best render cells per
    style cell, or None)."""
    an, sn = _unit(a).to(match_dtype(a)), _unit(s).to(match_dtype(a))  # [C,Nc], [C,Ns]
    nc, ns = an.shape[1], sn.shape[1]
    kr, kc = min(k, ns), min(k, nc)
    idx_r = torch.empty(nc, kr, dtype=torch.long, device=a.device)
    best_v = best_i = None  # running column top-k: [kc, Ns]
    for i0, i1 in _chunks(nc, ns):
        sim = an[:, i0:i1].T @ sn  # [m, Ns]
        idx_r[i0:i1] = sim.topk(kr, dim=1).indices
        if need_cols:
            v, i = sim.topk(min(kc, i1 - i0), dim=0)  # [k', Ns]
            i = i + i0
            if best_v is not None:
                v, i = torch.cat([best_v, v]), torch.cat([best_i, i])
                v, j = v.topk(min(kc, v.shape[0]), dim=0)
                i = i.gather(0, j)
            best_v, best_i = v, i
    return idx_r, best_i


DENSE_UNION_MAX = 1 << 28  # flat U entries up to which a byte mask beats sorting (256 MB at most)


def _union_keys(keys: torch.Tensor, n: int) -> torch.Tensor:
    """Sorted unique values of ``keys`` in [0, n): a byte mask and its nonzero entries (linear time) when
    the mask is affordable, else torch.unique (a sort; 0.25 s per call on the CPU demo's 32k keys)."""
    if n > DENSE_UNION_MAX:
        return torch.unique(keys)
    mask = torch.zeros(n, dtype=torch.bool, device=keys.device)
    mask[keys] = True
    return mask.nonzero().squeeze(1)


@torch.no_grad()
def fast_target(a: torch.Tensor, s: torch.Tensor, k: int = K_CROSS, idx=None) -> torch.Tensor:
    """FAST's projected target b = Pᵀa [C,Nc] (no gradient). U = union of the top-k style cells of every
    render cell and the top-k render cells of every style cell, U /= sum(U); A = a·diag(U1)·aᵀ + 1e-12·I;
    B = a·U·sᵀ; P = solve(A, B) (in float64: dead ReLU channels make A singular but for the ridge)."""
    nc, ns = a.shape[1], s.shape[1]
    idx_r, idx_c = idx if idx is not None else _topk_both(a, s, k)
    rows = torch.cat([torch.arange(nc, device=a.device).repeat_interleave(idx_r.shape[1]),
                      idx_c.reshape(-1)])
    cols = torch.cat([idx_r.reshape(-1), torch.arange(ns, device=a.device).repeat(idx_c.shape[0])])
    key = _union_keys(rows * ns + cols, nc * ns)  # an entry set by both passes counts once
    rows, cols = key // ns, key % ns
    n = float(key.numel())
    u1 = torch.bincount(rows, minlength=nc).to(a.dtype) / n  # [Nc] row sums of U
    u = torch.sparse_coo_tensor(torch.stack([rows, cols]), torch.full_like(rows, 1, dtype=a.dtype) / n,
                                (nc, ns), is_coalesced=True, check_invariants=False)  # keys unique+sorted
    us = torch.sparse.mm(u, s.T.contiguous())  # U·sᵀ [Nc,C]
    if nc < a.shape[0]:
        b, ok = _fast_target_low_rank(a, u1, us)
    else:
        A = (a * u1) @ a.T  # [C,C]
        A64 = A.double() + RIDGE * torch.eye(A.shape[0], dtype=torch.float64, device=a.device)
        P, info = torch.linalg.solve_ex(A64, (a @ us).double())  # P = A⁻¹B, B = a·U·sᵀ [C,C]
        b, ok = P.to(a.dtype).T @ a, (info == 0) & torch.isfinite(P).all()
    # the reference code falls back to the identity map when the solve fails; chosen on the device, since a
    # Python `if` here would stall the stylize loop on a host sync every iteration
    return torch.where(ok, b, a)  # [C,Nc]


def _fast_target_low_rank(a: torch.Tensor, u1: torch.Tensor, us: torch.Tensor):
    """b = Pᵀa with fewer render cells than channels, from an Nc x Nc system instead of C x C: A = a·D·aᵀ + εI
    (D = diag(U1)) gives A⁻¹a = a·(D·G + εI)⁻¹ with G = aᵀa (push-through identity), so
    b = Bᵀ·A⁻¹·a = (U·sᵀ)ᵀ·G·(D·G + εI)⁻¹ = (U·sᵀ)ᵀ·Yᵀ with Y = (G·D + εI)⁻¹·G. Same value in exact
    arithmetic; (C/Nc)³ less work (the CPU demo: 768 channels, 70 cells)."""
    a64 = a.double()
    G = a64.T @ a64  # [Nc,Nc]
    M = G * u1.double()[None, :] + RIDGE * torch.eye(G.shape[0], dtype=torch.float64, device=a.device)  # G·D + εI
    Y, info = torch.linalg.solve_ex(M, G)  # [Nc,Nc]
    b = us.double().T @ Y.T  # [C,Nc]
    return b.to(a.dtype), (info == 0) & torch.isfinite(b).all()


def fast_loss(render_feats: torch.Tensor, style_feats: torch.Tensor, k: int = K_CROSS,
              return_match: bool = False):
    """FAST style loss: mean over channels of 1 − cos(a[c,:], b[c,:]) (cosine along the pixel axis) with
    b = fast_target(a, s) held constant; the gradient flows through a only.
    ``return_match`` also returns idx [Nc,k] (top-k style cells per render cell, for the stroke field)."""
    a, s = render_feats, style_feats.to(render_feats)
    idx = _topk_both(a.detach(), s.detach(), k)
    b = fast_target(a.detach(), s.detach(), k, idx=idx)
    loss = (1.0 - F.cosine_similarity(a, b, dim=1)).mean()
    return (loss, idx[0]) if return_match else loss


@torch.no_grad()
def match_style_cells(render_feats: torch.Tensor, style_feats: torch.Tensor, k: int = K_CROSS):
    """For each render cell its k most cosine-similar style cells: idx [Nc,k] and weights w [Nc,k].
    Weights are uniform (1/k), as FAST's U weighs every match equally."""
    idx, _ = _topk_both(render_feats, style_feats.to(render_feats), k, need_cols=False)
    w = torch.full(idx.shape, 1.0 / idx.shape[1], dtype=render_feats.dtype, device=idx.device)
    return idx, w


def nnfm_loss(render_feats: torch.Tensor, style_feats: torch.Tensor) -> torch.Tensor:
    """ARF's NNFM: mean over render cells of min over style cells of the cosine distance 1 − cos.
    The nearest neighbour is found without gradient; the distance to it carries the gradient."""
    a, s = render_feats, style_feats.to(render_feats)
    nn_idx = match_style_cells(a.detach(), s.detach(), 1)[0][:, 0]  # [Nc]
    return (1.0 - F.cosine_similarity(a, s[:, nn_idx], dim=0)).mean()


def gram(f: torch.Tensor) -> torch.Tensor:
    return f @ f.T / f.shape[1]  # [C,C], normalized by the pixel count so image sizes compare


def gram_loss(render_feats: torch.Tensor, style_feats: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of pixel-normalized Gram matrices."""
    return ((gram(render_feats) - gram(style_feats.to(render_feats))) ** 2).mean()


def content_loss(render_feats: torch.Tensor, photo_feats: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of features (any matching shapes)."""
    return ((render_feats - photo_feats.to(render_feats)) ** 2).mean()
