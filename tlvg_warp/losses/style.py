"""Style and content losses on VGG feature matrices [C, N] (channels x pixels, pixels row-major).

FAST (ABC-GS reference code, SPEC §3), NNFM (ARF), Gram, content MSE, and the render->style cell match the
"matched" stroke-field mapping reuses. Similarity matrices are built in row chunks so a ~100k x 20k match
never materializes at once.

Per-call cost (the stylize loop is bound by the host's kernel launches): nothing here reads a value
back to the host (no ``.item()``, no data-dependent shapes, no sparse tensors), the painting's side is
computed once (:class:`StyleFeatures`), and :class:`StyleLoss` adds an optional per-view cache of the FAST
projection (``key``/``refresh_every``).
"""
from __future__ import annotations

from contextlib import contextmanager

import torch
import torch.nn.functional as F

K_CROSS = 5  # FAST's mutual top-k (reference code)
RIDGE = 1e-12  # FAST's A + 1e-12*I (reference code)
# FAST's solve. A = a·diag(U1)·aᵀ is a Gram matrix of highly correlated relu3 channels: on fern x Starry
# Night with the pretrained backbone 83 channels are dead and the live spectrum spans 12 decades. Measured against
# a float64 LU of the float64 A (rel. error of the target b / of the loss's gradient):
#   lu64 of the float32 A (the reference code, the loop before):  4e-5 / 1.4e-4,   2.30 ms on the GPU
#   cholesky64: A in float64, scaled to unit diagonal (Jacobi) + RIDGE64·I, Cholesky:  ~1e-5 / 1e-4, 1.2 ms
#   cholesky32: the same in float32: fails (info > 0: rounding exceeds a 1e-7 ridge) on bf16 features of the
#     same view; a ridge that always holds (1e-5) moves the gradient by 2-3%:       0.9 ms -> opt-in only.
# RIDGE64 covers the worst-case Cholesky rounding n·eps·λmax (768 x 1.1e-16 x 768 = 6.5e-11 on a unit diagonal).
RIDGE64 = 1e-10
RIDGE32 = 1e-5
EPS_COS = 1e-8  # F.cosine_similarity's eps: a (dead) all-zero row has cosine 0
SIM_BUDGET = 1 << 25  # elements per similarity chunk on the CPU: 32M floats = 128 MB in float32
SIM_BUDGET_CUDA = 1 << 28  # on CUDA (float16): at most 512 MB a chunk. Each row chunk reads all of the painting's
# features again, so small chunks made a large match bound by those reads: a 4 MP view's 62,000 cells against the
# painting's 300,000 (460 MB of features) took 560 chunks at 32M elements, 70 at this budget (docs/performance.md)
SIM_ROWS_CUDA = 2048  # on CUDA a chunk holds this many render cells (or SIM_BUDGET elements, if more), up to
# SIM_BUDGET_CUDA: the painting's features are re-read once per 2048 rows at most (the product writes 8x what it
# reads again), and a 1007x755 view's 11,800 cells against the painting's 57,000 take 224 MB chunks instead of 512 MB
# (a stylize step's peak 3,804 -> 3,225 MiB, 14.9 -> 15.2 ms; at 2 and 4 MP the cap rules, as before)
TWO_PRODUCTS = None  # the match's column pass from a second product: None = on CUDA only (tests force either)
PAD_COLUMNS = None  # the row pass's painting operand padded to a multiple of 8 cells: None = on CUDA only (tests
# force it). A float16 product whose leading dimension is not a multiple of 8 elements falls back to an unaligned
# GEMM: at 4 MP the painting's 299,636 cells ran an sm75 "align1" kernel, 174 of a step's 227 ms of GPU time
SOLVES = ("auto", "cholesky64", "lu64", "cholesky32")


def match_dtype(t: torch.Tensor) -> torch.dtype:
    """The cosine similarities only rank candidates for the top-k match, so on CUDA they are computed in
    float16 (tensor cores; ~10x the float32 matmul, which bounded the stylize loop): unit vectors keep every
    product in range and a rank flips only between cells whose cosines differ by under ~1e-3. CPU keeps the
    input dtype (no fast half matmul there)."""
    return torch.float16 if t.is_cuda else t.dtype


def _unit(f: torch.Tensor) -> torch.Tensor:
    return F.normalize(f, p=2, dim=0)  # unit columns [C, N]


def _chunk_rows(n_cols: int, cuda: bool) -> int:
    """Rows of a [rows, n_cols] similarity chunk: SIM_BUDGET elements on the CPU; on CUDA SIM_ROWS_CUDA rows or
    SIM_BUDGET elements, whichever is more, at most SIM_BUDGET_CUDA elements."""
    n_cols = max(1, n_cols)
    if not cuda:
        return max(1, SIM_BUDGET // n_cols)
    return max(1, min(SIM_BUDGET_CUDA // n_cols, max(SIM_ROWS_CUDA, SIM_BUDGET // n_cols)))


def _chunks(n_rows: int, n_cols: int, cuda: bool):
    step = _chunk_rows(n_cols, cuda)
    for i0 in range(0, n_rows, step):
        yield i0, min(n_rows, i0 + step)


class StyleFeatures:
    """The painting's side of the style losses, computed once and reused by every call: the features ``s``
    [C, Ns], their unit columns in the match dtype (``unit``), ``sT`` [Ns, C] (the FAST union gathers its
    rows) and the pixel-normalized Gram matrix (``gram``), each built on first use. Any loss here takes
    either a plain [C, Ns] tensor (everything recomputed per call, as before) or one of these."""

    def __init__(self, feats: torch.Tensor):
        if feats.dim() != 2:
            raise ValueError(f"style features must be [C, Ns], got {tuple(feats.shape)}")
        self.s = feats.detach().contiguous()
        self._unit: dict = {}
        self._unitT: dict = {}
        self._sT = None
        self._gram = None
        self._layer_grams = None
        self._cols = None

    @property
    def shape(self):
        return self.s.shape

    @property
    def dtype(self):
        return self.s.dtype

    @property
    def device(self):
        return self.s.device

    def unit(self, dtype: torch.dtype, pad_to: int = 1) -> torch.Tensor:
        """Unit columns [C, Ns'] in ``dtype``, Ns' = Ns rounded up to a multiple of ``pad_to`` (the extra columns 0:
        a caller that pads must keep them out of its ranking)."""
        u = self._unit.get((dtype, pad_to))
        if u is None:
            n = self.s.shape[1]
            u = torch.zeros(self.s.shape[0], n + (-n) % pad_to, dtype=dtype, device=self.s.device)
            u[:, :n] = _unit(self.s)
            self._unit[(dtype, pad_to)] = u
        return u

    def unitT(self, dtype: torch.dtype) -> torch.Tensor:
        """Unit columns as rows [Ns, C] (the left operand of the column-pass similarity product)."""
        u = self._unitT.get(dtype)
        if u is None:
            u = self._unitT[dtype] = _unit(self.s).T.to(dtype).contiguous()
        return u

    @property
    def cols(self) -> torch.Tensor:
        """arange(Ns) [Ns, 1, 1] on the device (the FAST union's repeat test)."""
        if self._cols is None:
            self._cols = torch.arange(self.s.shape[1], device=self.s.device).view(-1, 1, 1)
        return self._cols

    @property
    def sT(self) -> torch.Tensor:
        if self._sT is None:
            self._sT = self.s.T.contiguous()
        return self._sT

    @property
    def gram(self) -> torch.Tensor:
        if self._gram is None:
            self._gram = gram(self.s)
        return self._gram

    def layer_grams(self, layers: int) -> list:
        """The Gram matrix of each of ``layers`` equal channel blocks of ``s`` (its layers, concatenated)."""
        if self._layer_grams is None or len(self._layer_grams) != layers:
            self._layer_grams = [gram(b) for b in self.s.chunk(layers, dim=0)]
        return self._layer_grams

    def like(self, ref: torch.Tensor) -> "StyleFeatures":
        """This painting on ``ref``'s dtype and device (itself when they already agree)."""
        if self.s.dtype == ref.dtype and self.s.device == ref.device:
            return self
        return StyleFeatures(self.s.to(ref))


def as_style(style, ref: torch.Tensor) -> StyleFeatures:
    """A :class:`StyleFeatures` on ``ref``'s dtype/device from a tensor or a StyleFeatures."""
    if isinstance(style, StyleFeatures):
        return style.like(ref)
    return StyleFeatures(style.detach().to(ref))


@torch.no_grad()
def _topk_both(a: torch.Tensor, s, k: int, need_cols: bool = True):
    """Cosine top-k in both directions. Returns idx_r [Nc,kr] (best style cells per render cell) and idx_c
    [Ns,kc] (best render cells per style cell, or None). ``s``: [C,Ns] or a StyleFeatures (its unit columns
    are reused).

    On CUDA: two products, each top-k along its rows (a top-k down the columns of one product was 2x slower on
    the GPU): sim = âᵀŝ [Nc,Ns] and simᵀ = ŝᵀâ [Ns,Nc']. The unit render features are laid out [Nc', C] with
    Nc' the cell count rounded up to 8, and the painting's unit columns [C, Ns'] likewise (``PAD_COLUMNS``), so
    every operand and output of both float16 products is 16-byte aligned (tensor-core kernels; 0.23 -> 0.05 ms at
    fern size); the padding cells' similarities are set to -inf before their top-k. On the CPU (float32 products
    cost more than a top-k down the columns) one product, its column top-k merged across row chunks. Products are
    made in row chunks (:func:`_chunk_rows`)."""
    st = as_style(s, a)
    mdt = match_dtype(a)
    c, nc = a.shape
    ns = st.shape[1]
    kr, kc = min(k, ns), min(k, nc)
    two = need_cols and (a.is_cuda if TWO_PRODUCTS is None else TWO_PRODUCTS)
    pad = (-nc) % 8 if two else 0
    anT = torch.empty(nc + pad, c, dtype=mdt, device=a.device)
    anT[:nc].copy_(_unit(a).T)  # the padding rows stay unset: only their own (overwritten) outputs see them
    idx_r = torch.empty(nc, kr, dtype=torch.long, device=a.device)
    idx_c = torch.empty(ns, kc, dtype=torch.long, device=a.device) if need_cols else None
    cols_in_rows = need_cols and not two  # the CPU's column top-k reads this product: no padding cells in it
    pad_s = 8 if (a.is_cuda if PAD_COLUMNS is None else PAD_COLUMNS) and not cols_in_rows else 1
    sn = st.unit(mdt, pad_s)  # [C, Ns'], the padding columns 0
    best_v = best_i = None  # CPU: running column top-k over the row chunks [kc', Ns]
    for i0, i1 in _chunks(nc, sn.shape[1], a.is_cuda):
        sim = anT[i0:i1] @ sn  # [m, Ns']
        if sn.shape[1] > ns:
            sim[:, ns:] = float("-inf")  # the padding cells rank last
        # the nearest neighbour alone (NNFM, the field match) is one pass of argmax, where topk's radix select makes
        # several over the same rows; ties go to the first painting cell
        idx_r[i0:i1] = sim.argmax(1, keepdim=True) if kr == 1 else sim.topk(kr, dim=1).indices
        if cols_in_rows:
            v, i = sim.topk(min(kc, i1 - i0), dim=0)  # [k', Ns]
            if i0:
                i = i + i0
            if best_v is not None:
                v, i = torch.cat([best_v, v]), torch.cat([best_i, i])
                v, j = v.topk(min(kc, v.shape[0]), dim=0)
                i = i.gather(0, j)
            best_v, best_i = v, i
    if not need_cols:
        return idx_r, None
    if not two:
        idx_c.copy_(best_i.T)
        return idx_r, idx_c
    snT = st.unitT(mdt)
    for j0, j1 in _chunks(ns, nc + pad, a.is_cuda):
        simT = snT[j0:j1] @ anT.T  # [m, Nc']
        if pad:
            simT[:, nc:] = float("-inf")
        idx_c[j0:j1] = simT.topk(kc, dim=1).indices
    return idx_r, idx_c


@contextmanager
def _deterministic_sums():
    """CUDA's ``index_add_`` sums by atomic adds, in an order that changes from run to run: the sums differ in their
    last bits and Adam turns that into whole steps (two GPU runs of configs/abcgs.yaml drifted apart by 6% of their
    motion in three steps). Inside this block it takes torch's deterministic (sorted) path; the flag is restored."""
    was, warn_only = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(was, warn_only=warn_only)


@torch.no_grad()
def _fast_union(idx_r: torch.Tensor, idx_c: torch.Tensor, nc: int, st: "StyleFeatures"):
    """FAST's U (the union of both top-k passes, each entry once) without building it, and without reading
    anything back to the host. idx_r [Nc,kr], idx_c [Ns,kc] from ``_topk_both``. Returns (keep, u1, us):
    keep [Ns,kc] = 1 where the column pass's entry (idx_c[j,t], j) is not also a row-pass entry,
    u1 [Nc] = row counts of U, us [Nc,C] = U·sᵀ, unnormalized (|U| = Nc·kr + Σ keep; divide by it for
    U /= sum(U)).

    An entry of the column pass is already in the row pass iff j is among idx_r[idx_c[j,t]] (each pass alone
    has no repeats: top-k indices are distinct), so it counts only when it is not."""
    sT = st.sT
    ns, c = sT.shape
    kr, kc = idx_r.shape[1], idx_c.shape[1]
    dup = (idx_r[idx_c] == st.cols).any(-1)  # [Ns,kc]
    keep = 1.0 - dup.to(sT.dtype)
    src = sT.unsqueeze(1).expand(ns, kc, c).reshape(ns * kc, c)
    with _deterministic_sums():
        u1 = torch.full((nc,), float(kr), dtype=sT.dtype, device=sT.device).index_add_(0, idx_c.reshape(-1),
                                                                                        keep.reshape(-1))
        us = F.embedding_bag(idx_r, sT, mode="sum")  # the row pass: Σ_k sᵀ[idx_r[i,k]]  [Nc,C]
        # the column pass, repeats sent to a spare row nc that is dropped
        us = torch.cat([us, us.new_zeros(1, c)]).index_add_(0, torch.where(dup, nc, idx_c).reshape(-1), src)[:nc]
    return keep, u1, us


_eyes: dict = {}


def _eye(like: torch.Tensor) -> torch.Tensor:
    key = (like.shape[0], like.dtype, str(like.device))
    e = _eyes.get(key)
    if e is None:
        e = _eyes[key] = torch.eye(like.shape[0], dtype=like.dtype, device=like.device)
    return e


def _solve_kind(solve: str, a: torch.Tensor) -> str:
    if solve not in SOLVES:
        raise ValueError(f"solve must be one of {SOLVES}, got {solve!r}")
    if solve == "auto":
        return "lu64" if a.dtype == torch.float64 else "cholesky64"
    return solve


@torch.no_grad()
def fast_projection(a: torch.Tensor, s, k: int = K_CROSS, idx=None, solve: str = "auto"):
    """FAST's map P [C,C] (target b = Pᵀa) and ``ok`` (0-dim bool: the solve succeeded), from render features
    a [C,Nc] and style features s ([C,Ns] or a StyleFeatures); ``idx`` = (idx_r, idx_c) from ``_topk_both``.

    P = A⁻¹B with A = a·diag(U1)·aᵀ + ridge and B = a·U·sᵀ. ``solve`` (see RIDGE64 for the measurements):
    "lu64" is the reference code's dense solve (LU of A + 1e-12·I in float64, A formed in a's dtype);
    "cholesky64" forms A in float64, scales it to unit diagonal and factors A + 1e-10·I by Cholesky (half the
    LU's time on the GPU, as accurate); "cholesky32" the same in float32 with a 1e-5 ridge (faster still, but
    the gradient moves by a few percent); "auto": lu64 for float64 input (the tests' oracle), else cholesky64.
    In the Cholesky solves the scale of U cancels (it is not even divided out). With fewer render cells than
    channels the solve is an Nc x Nc system in float64 whatever ``solve`` says (push-through identity:
    P = a·(D·G + εI)⁻¹·U·sᵀ, G = aᵀa, D = diag(U1); (C/Nc)³ less work: the CPU demo has 768 channels and
    70 cells)."""
    st = as_style(s, a)
    nc = a.shape[1]
    idx_r, idx_c = idx if idx is not None else _topk_both(a, st, k)
    keep, u1, us = _fast_union(idx_r, idx_c, nc, st)
    kind = _solve_kind(solve, a)
    if nc < a.shape[0] or kind == "lu64":
        n = keep.sum() + nc * idx_r.shape[1]  # |U|: U /= sum(U) matters here through the absolute ridge
        if nc < a.shape[0]:
            a64 = a.double()
            M = (u1.double() / n)[:, None] * (a64.T @ a64)  # D·G [Nc,Nc]
            M.diagonal().add_(RIDGE)
            X, info = torch.linalg.solve_ex(M, us.double() / n)  # [Nc,C]
            P = a64 @ X
        else:
            A = ((a * (u1 / n)) @ a.T).double()
            A.diagonal().add_(RIDGE)
            P, info = torch.linalg.solve_ex(A, (a @ (us / n)).double())  # P = A⁻¹B, B = a·U·sᵀ [C,C]
    else:
        dt, ridge = (torch.float64, RIDGE64) if kind == "cholesky64" else (torch.float32, RIDGE32)
        ad = a.to(dt)
        A = (ad * u1.to(dt)) @ ad.T  # [C,C]; U's scale 1/n cancels in A⁻¹B
        d = A.diagonal().clamp_min(1e-30).rsqrt()  # a dead channel: its row of A is 0, so is its row of P
        As = A * torch.outer(d, d)
        As.diagonal().add_(ridge)
        L, info = torch.linalg.cholesky_ex(As)
        DB = (a @ us).to(dt) * d[:, None]
        if kind == "cholesky64":  # L⁻¹ once (one triangular solve) and two products: ~0.25 ms less than the two
            Li = torch.linalg.solve_triangular(L, _eye(L), upper=False)  # solves of cholesky_solve on the GPU;
            P = (Li.T @ (Li @ DB)) * d[:, None]  # in float64 as accurate (the float32 inverse is not: float32 keeps them)
        else:
            P = torch.cholesky_solve(DB, L) * d[:, None]
    ok = (info == 0) & torch.isfinite(P.sum())  # a NaN or inf anywhere in P makes its sum non-finite
    return P.to(a.dtype), ok


def _apply_projection(P: torch.Tensor, ok: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    # the reference code falls back to the identity map when the solve fails; chosen on the device, since a
    # Python `if` here would stall the stylize loop on a host sync every iteration
    return torch.where(ok, P.T @ a, a)  # [C,Nc]


@torch.no_grad()
def fast_target(a: torch.Tensor, s, k: int = K_CROSS, idx=None, solve: str = "auto") -> torch.Tensor:
    """FAST's projected target b = Pᵀa [C,Nc] (no gradient). U = union of the top-k style cells of every
    render cell and the top-k render cells of every style cell, U /= sum(U); A = a·diag(U1)·aᵀ + 1e-12·I;
    B = a·U·sᵀ; P = solve(A, B) (see :func:`fast_projection` for ``solve``)."""
    P, ok = fast_projection(a, s, k, idx=idx, solve=solve)
    return _apply_projection(P, ok, a)


class _CosToFixed(torch.autograd.Function):
    """mean over rows (dim=1 layout [R, N]: cosine along N) of 1 − cos(x_r, y_r) for a constant y given
    unit-normalized (ŷ = y / max(|y|, eps)), with a closed-form backward (fewer small kernels than autograd
    through F.cosine_similarity; same values and, for |x_r| > eps, the same gradient):
    ∂/∂x_r = −(1/R)·(ŷ_r/|x_r| − (x_r·ŷ_r)·x_r/|x_r|³); an all-zero row (a dead ReLU channel) gets ŷ_r/eps, as
    torch's does (the ReLU's mask zeroes it)."""

    @staticmethod
    def forward(ctx, x, yhat, dim):
        nx = torch.linalg.vector_norm(x, dim=dim)
        dot = torch.linalg.vecdot(x, yhat, dim=dim)
        inv = nx.clamp_min(EPS_COS).reciprocal()
        ctx.save_for_backward(x, yhat, nx, dot, inv)
        ctx.dim = dim
        return 1.0 - (dot * inv).mean()

    @staticmethod
    def backward(ctx, g):
        x, yhat, nx, dot, inv = ctx.saved_tensors
        scale = g / nx.numel()
        # (an all-zero row has dot = 0, so its second term vanishes whatever inv is)
        c1, c2 = (-scale * inv).unsqueeze(ctx.dim), (scale * dot * inv.pow(3)).unsqueeze(ctx.dim)
        return torch.addcmul(yhat * c1, x, c2), None, None


def cosine_distance_to_fixed(x: torch.Tensor, y: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """mean of 1 − cos(x, y) along ``dim`` with y held constant (the FAST and NNFM losses' last step);
    equals ``(1 - F.cosine_similarity(x, y.detach(), dim)).mean()``."""
    with torch.no_grad():
        yhat = y / torch.linalg.vector_norm(y, dim=dim, keepdim=True).clamp_min(EPS_COS)
    return _CosToFixed.apply(x, yhat.to(x.dtype), dim)


def fast_loss(render_feats: torch.Tensor, style_feats, k: int = K_CROSS, return_match: bool = False,
              solve: str = "auto"):
    """FAST style loss: mean over channels of 1 − cos(a[c,:], b[c,:]) (cosine along the pixel axis) with
    b = fast_target(a, s) held constant; the gradient flows through a only. ``style_feats``: [C,Ns] or a
    :class:`StyleFeatures` (precomputed once per painting).
    ``return_match`` also returns idx [Nc,k] (top-k style cells per render cell, for the stroke field)."""
    a = render_feats
    st = as_style(style_feats, a)
    idx = _topk_both(a.detach(), st, k)
    b = fast_target(a.detach(), st, k, idx=idx, solve=solve)
    loss = cosine_distance_to_fixed(a, b, dim=1)
    return (loss, idx[0]) if return_match else loss


@torch.no_grad()
def match_style_cells(render_feats: torch.Tensor, style_feats, k: int = K_CROSS):
    """For each render cell its k most cosine-similar style cells: idx [Nc,k] and weights w [Nc,k].
    Weights are uniform (1/k), as FAST's U weighs every match equally."""
    idx, _ = _topk_both(render_feats, style_feats, k, need_cols=False)
    w = torch.full(idx.shape, 1.0 / idx.shape[1], dtype=render_feats.dtype, device=idx.device)
    return idx, w


def nnfm_loss(render_feats: torch.Tensor, style_feats) -> torch.Tensor:
    """ARF's NNFM: mean over render cells of min over style cells of the cosine distance 1 − cos.
    The nearest neighbour is found without gradient; the distance to it carries the gradient."""
    a = render_feats
    st = as_style(style_feats, a)
    nn_idx = _topk_both(a.detach(), st, 1, need_cols=False)[0][:, 0]  # [Nc]
    return cosine_distance_to_fixed(a, st.s[:, nn_idx], dim=0)


def gram(f: torch.Tensor) -> torch.Tensor:
    return f @ f.T / f.shape[1]  # [C,C], normalized by the pixel count so image sizes compare


def gram_loss(render_feats: torch.Tensor, style_feats) -> torch.Tensor:
    """Mean squared difference of pixel-normalized Gram matrices."""
    a = render_feats
    gs = as_style(style_feats, a).gram if isinstance(style_feats, StyleFeatures) else gram(style_feats.to(a))
    return F.mse_loss(torch.mm(a, a.T) * (1.0 / a.shape[1]), gs.to(a))


def layered_gram_loss(render_feats: torch.Tensor, style_grams: list) -> torch.Tensor:
    """Mean over the layers concatenated in ``render_feats`` [L*C, N] (L = len(style_grams) equal channel blocks) of
    ‖G − G_p‖_F / ‖G_p‖_F, each G pixel-normalized [C, C]: the evaluation's Gram distance on these layers. Every
    layer counts the same whatever the size of its features, and the distance, not its square, keeps the gradient's
    size from growing with how far the render is (squared, in a CPU look at lego x The Starry Night, the term rose
    to 25 of a 31 loss at the start of stylize at weight 4)."""
    blocks = render_feats.chunk(len(style_grams), dim=0)
    gps = [gp.to(render_feats) for gp in style_grams]
    return torch.stack([(gram(a) - gp).square().sum().add(1e-20).sqrt() / gp.norm().clamp_min(1e-12)
                        for a, gp in zip(blocks, gps)]).mean()  # L (3) layers: no loop over pixels


def content_loss(render_feats: torch.Tensor, photo_feats: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of features (any matching shapes)."""
    return F.mse_loss(render_feats, photo_feats.to(render_feats).detach())


def _moved(x, device):
    """Tensors inside nested dicts / tuples / lists moved to ``device`` (None and other values as they are)."""
    if isinstance(x, torch.Tensor):
        return x if device is None else x.to(device)
    if isinstance(x, dict):
        return {k: _moved(v, device) for k, v in x.items()}
    if isinstance(x, (tuple, list)):
        return type(x)(_moved(v, device) for v in x)
    return x


class StyleLoss:
    """A style loss against one painting, built once per stylization; call it once per step.

        style = StyleLoss(style_feats, kind="fast", refresh_every=1)   # [C,Ns] of the painting
        loss = style(render_feats, key=view_index)                      # [C,Nc] of this step's render

    Everything that depends only on the painting (unit columns, sᵀ, the Gram matrix) is computed once.
    ``kind``: "fast" | "nnfm" | "gram" | "gram_layers" (:func:`layered_gram_loss` over the LAYERS blocks the
    network's feature calls concatenate). ``solve``: FAST's solve (:func:`fast_projection`).

    Match caching (optional; off by default): with ``refresh_every = R > 1`` and a ``key`` per call (the view
    index), FAST's costly part is computed on the first call of a key and then on every R-th call of that key;
    the calls between reuse it. ``cache`` says what is reused: "projection" (the top-k match AND the C x C solve:
    the target is b = Pᵀa of the current features with the key's last P; the cheapest) or "match" (the top-k
    match only: A, B and the solve are redone from the current features). NNFM reuses its nearest neighbours.
    R = 1, or no key, recomputes every call: exactly :func:`fast_loss`. ``match_of(key)`` returns a key's last
    top-k indices [Nc,k] (the stroke field's match); ``reset()`` drops the cache. The reused P is a C x C map,
    valid whatever the render's cell count (density control may change the scene between calls)."""

    KINDS = ("fast", "nnfm", "gram", "gram_layers")
    LAYERS = 3  # the features are three layers of one VGG block, concatenated (relu3_1-3_3 or relu4_1-4_3)
    CACHES = ("projection", "match")

    def __init__(self, style_feats, kind: str = "fast", k: int = K_CROSS, refresh_every: int = 1,
                 solve: str = "auto", cache: str = "projection"):
        if kind not in self.KINDS:
            raise ValueError(f"kind must be one of {self.KINDS}, got {kind!r}")
        if int(refresh_every) != refresh_every or refresh_every < 1:
            raise ValueError(f"refresh_every must be an integer >= 1, got {refresh_every!r}")
        if cache not in self.CACHES:
            raise ValueError(f"cache must be one of {self.CACHES}, got {cache!r}")
        _solve_kind(solve, torch.empty(0))
        self.style = style_feats if isinstance(style_feats, StyleFeatures) else StyleFeatures(style_feats)
        self.kind, self.k, self.refresh_every, self.solve, self.cache = kind, int(k), int(refresh_every), solve, cache
        self._cache: dict = {}  # key -> [calls since refresh, payload dict]
        self.refreshes = 0  # matches computed (a count for logs and tests)

    def reset(self) -> None:
        self._cache.clear()

    def state_dict(self) -> dict:
        """The match cache (on the CPU) and the refresh count: a resumed run reuses what the straight run would."""
        return {"refreshes": self.refreshes,
                "cache": {k: [n, _moved(pay, "cpu")] for k, (n, pay) in self._cache.items()}}

    def load_state_dict(self, sd: dict, device=None) -> None:
        self.refreshes = int(sd.get("refreshes", 0))
        self._cache = {k: [n, _moved(pay, device)] for k, (n, pay) in (sd.get("cache") or {}).items()}

    def match_of(self, key):
        hit = self._cache.get(key)
        return None if hit is None else hit[1]["idx"][0]

    def _cached(self, key, compute) -> dict:
        hit = self._cache.get(key) if key is not None and self.refresh_every > 1 else None
        if hit is not None and hit[0] < self.refresh_every:
            hit[0] += 1
            return hit[1]
        payload = compute()
        self.refreshes += 1
        if key is not None and self.refresh_every > 1:
            self._cache[key] = [1, payload]
        return payload

    def __call__(self, render_feats: torch.Tensor, key=None) -> torch.Tensor:
        a = render_feats
        st = self.style.like(a)
        if self.kind == "gram":
            return gram_loss(a, st)
        if self.kind == "gram_layers":
            return layered_gram_loss(a, st.layer_grams(self.LAYERS))
        ad = a.detach()
        if self.kind == "nnfm":
            idx = self._cached(key, lambda: {"idx": _topk_both(ad, st, 1, need_cols=False)})["idx"]
            return cosine_distance_to_fixed(a, st.s[:, idx[0][:, 0]], dim=0)

        def compute():
            idx = _topk_both(ad, st, self.k)
            if self.cache == "match":
                return {"idx": idx}
            P, ok = fast_projection(ad, st, self.k, idx=idx, solve=self.solve)
            return {"idx": idx, "P": P, "ok": ok}

        got = self._cached(key, compute)
        if "P" in got:
            P, ok = got["P"], got["ok"]
        else:
            P, ok = fast_projection(ad, st, self.k, idx=got["idx"], solve=self.solve)
        with torch.no_grad():
            b = _apply_projection(P, ok, ad)
        return cosine_distance_to_fixed(a, b, dim=1)
