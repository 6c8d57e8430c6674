"""The stroke hinge (loss.w_stroke): luminance contrast across the target stroke field asked for up to the painting's,
contrast along it held to the painting's.
- a sinusoidal grating: the energies against a float64 OpenCV oracle written here (its own blur, Scharr and
  projection on (cos θ, sin θ), not the doubled-angle formula) and against the grating's closed form; rotating the
  field by 90° swaps them;
- the torch energies against the numpy/OpenCV painting target on a real painting (../shared/data's Starry Night,
  else the packaged one), at its own height and resized;
- gradcheck in float64, the hinge's zero region, and gradient steps on an image raising across over along;
- field_terms (the orientation and stroke terms from one gradient pass, the call the phase graphs on CUDA): its
  values and gradient those of the two separate functions, an entry 0 where its term is off; on CUDA the replayed
  graph the eager call's for renders, fields and weights that change between calls;
- the relative form (loss.stroke_contrast: log): energies of log(Y + eps) against the OpenCV oracle on its log,
  a dark grating counting more than the same step on a light one, the painting's target in the same form,
  gradcheck, and field_terms' second gradient pass;
- the Stylize phase: computed and logged when weighted, never called at weight 0, the log form passed through."""
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from _demo_helpers import StubFeatures, demo_stylize_inputs
from _io_helpers import data_root
from tlvg_warp.losses import (field_terms, flow_alignment_score_torch, painting_stroke_energies, resize_style,
                              stroke_energies, stroke_field, stroke_hinge)
from tlvg_warp.losses.stroke_field import STROKE_LOG_EPS
from tlvg_warp.losses.graphs import GraphedFn

LUMA = np.array([0.299, 0.587, 0.114])
ORACLE_TOL = 1e-4  # relative: the same float64 arithmetic in another order (measured ~1e-12)
GRATING = dict(h=96, w=96, period=12.0, deg=30.0, amp=0.2)
BORDER = 8  # the grating ends at the image edge; reflect-101 padding bends the gradients within ~5 px of it
ASSETS = Path(__file__).resolve().parents[1] / "tlvg_warp" / "assets"


def grating(h, w, period, deg, amp):
    """Grey [h,w,3] float64: Y = 0.5 + amp·sin(2π(x cos α + y sin α)/period); its stripes run along α + 90°."""
    a = math.radians(deg)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    y = 0.5 + amp * np.sin(2 * np.pi * (xx * math.cos(a) + yy * math.sin(a)) / period)
    return np.repeat(y[..., None], 3, -1)


def const_field(h, w, theta, c=1.0):
    return torch.tensor([c * math.cos(2 * theta), c * math.sin(2 * theta)], dtype=torch.float64).expand(h, w, 2)


def interior(h, w):
    m = np.zeros((h, w, 1))
    m[BORDER:-BORDER, BORDER:-BORDER] = 1
    return m


def oracle(img, theta, weight, log_eps=None):
    """(E_across, E_along) by OpenCV in float64: σ 1 blur (9 taps) and Scharr, reflect-101, the gradient projected
    on v = (cos θ, sin θ) and on its normal, weighted means with ``weight`` [H,W]; of log(Y + log_eps) if given."""
    y = img @ LUMA
    y = y if log_eps is None else np.log(y + log_eps)
    y = cv2.GaussianBlur(y, (9, 9), 1.0, borderType=cv2.BORDER_REFLECT_101)
    gx = cv2.Scharr(y, cv2.CV_64F, 1, 0, borderType=cv2.BORDER_REFLECT_101)
    gy = cv2.Scharr(y, cv2.CV_64F, 0, 1, borderType=cv2.BORDER_REFLECT_101)
    along = (gx * math.cos(theta) + gy * math.sin(theta)) ** 2
    across = (-gx * math.sin(theta) + gy * math.cos(theta)) ** 2
    return (weight * across).sum() / weight.sum(), (weight * along).sum() / weight.sum()


def grating_energy(h, w, period, deg, amp):
    """The grating's mean squared gradient in closed form: a plane wave through the discrete σ 1 Gaussian
    (response Ĝ(kx)Ĝ(ky)) and Scharr (2 sin kx (10 + 6 cos ky) on x, its transpose on y), averaged over a phase (½)."""
    a = math.radians(deg)
    kx, ky = 2 * math.pi / period * math.cos(a), 2 * math.pi / period * math.sin(a)
    g, j = cv2.getGaussianKernel(9, 1.0, cv2.CV_64F).ravel(), np.arange(-4, 5)
    gain = (g * np.cos(kx * j)).sum() * (g * np.cos(ky * j)).sum()
    sx = 2 * math.sin(kx) * (10 + 6 * math.cos(ky))
    sy = 2 * math.sin(ky) * (10 + 6 * math.cos(kx))
    return 0.5 * (amp * gain) ** 2 * (sx * sx + sy * sy)


# --- 1. closed form ------------------------------------------------------------------------------------------------
def test_grating_contrast_is_across_a_field_along_its_stripes():
    h, w, deg = GRATING["h"], GRATING["w"], GRATING["deg"]
    img = grating(**GRATING)
    t = torch.from_numpy(img)
    along_stripes = math.radians(deg + 90.0)
    for weight in (None, interior(h, w)):
        wt = None if weight is None else torch.from_numpy(weight)
        ea, el = stroke_energies(t, const_field(h, w, along_stripes), wt)
        oa, ol = oracle(img, along_stripes, np.ones((h, w)) if weight is None else weight[..., 0])
        assert float(ea) == pytest.approx(oa, rel=ORACLE_TOL)
        assert float(el) == pytest.approx(ol, rel=ORACLE_TOL, abs=1e-12)
        # the whole image: the padding bends the stripes near the edges (~1% of the energy measured)
        assert float(el) < (0.02 if weight is None else 1e-4) * float(ea)
        # the field rotated by 90° (across the stripes): the two swap
        ra, rl = stroke_energies(t, const_field(h, w, math.radians(deg)), wt)
        assert (float(ra), float(rl)) == pytest.approx((float(el), float(ea)), rel=1e-9, abs=1e-12)
    # away from the border, the energy is the plane wave's (the window holds a non-whole number of periods: 1e-2)
    assert float(ea) == pytest.approx(grating_energy(**GRATING), rel=1e-2)


def test_weight_is_coherence_times_coverage():
    """A half-coherent field counts half: two halves of the image with different stripe directions and c = 1 / c = 0
    give the first half's energies alone; the coverage mask multiplies in the same way."""
    h, w = 48, 64
    rng = np.random.default_rng(3)
    img = torch.from_numpy(rng.random((h, w, 3)))
    th = rng.uniform(-math.pi / 2, math.pi / 2, (h, w))
    c = np.where(np.arange(w)[None, :] < w // 2, 1.0, 0.0) * np.ones((h, 1))
    d = torch.from_numpy(np.stack([c * np.cos(2 * th), c * np.sin(2 * th)], -1))
    cov = torch.from_numpy(np.where(np.arange(h)[:, None, None] < h // 3, 0.0, 1.0) * np.ones((1, w, 1)))
    ea, el = stroke_energies(img, d, cov)
    wts = c * cov[..., 0].numpy()
    y = cv2.GaussianBlur(img.numpy() @ LUMA, (9, 9), 1.0, borderType=cv2.BORDER_REFLECT_101)
    gx = cv2.Scharr(y, cv2.CV_64F, 1, 0, borderType=cv2.BORDER_REFLECT_101)
    gy = cv2.Scharr(y, cv2.CV_64F, 0, 1, borderType=cv2.BORDER_REFLECT_101)
    along = (gx * np.cos(th) + gy * np.sin(th)) ** 2
    across = gx * gx + gy * gy - along
    oa, ol = (wts * across).sum() / wts.sum(), (wts * along).sum() / wts.sum()
    assert (float(ea), float(el)) == pytest.approx((oa, ol), rel=ORACLE_TOL)
    # zero coverage everywhere: no pixel counts, finite zeros (no NaN)
    za, zl = stroke_energies(img, d, torch.zeros(h, w, 1, dtype=torch.float64))
    assert float(za) == 0.0 and float(zl) == 0.0


# --- 2. torch against the painting's numpy/OpenCV target -------------------------------------------------------------
def _painting():
    root = data_root()
    path = root / "styles" / "starry_night.jpg" if root is not None else None
    if path is None or not path.is_file():
        path = ASSETS / "starry_night.jpg"  # the packaged copy (256 rows) when ../shared/data is not there
    im = cv2.imread(str(path), cv2.IMREAD_COLOR)[:, :, ::-1].astype(np.float32) / 255
    return resize_style(im, 256)  # [256,w,3]: the working size


@pytest.mark.parametrize("view_h", [256, 128, 378])
def test_painting_targets_equal_the_torch_energies_on_the_same_field(view_h):
    p = _painting()
    t_across, t_along = painting_stroke_energies(p, view_h)
    q = resize_style(p, view_h)  # what the target measures: the painting at the views' height
    assert q.shape[0] == view_h
    _, c, d = stroke_field(q)
    for dtype, tol in ((torch.float64, ORACLE_TOL), (torch.float32, ORACLE_TOL)):
        ea, el = stroke_energies(torch.from_numpy(q).to(dtype), torch.from_numpy(d), None)
        assert ea.dtype == dtype
        assert (float(ea), float(el)) == pytest.approx((t_across, t_along), rel=tol), dtype
    # the premise the term rests on: a painting's contrast runs across its strokes
    assert t_across > 3 * t_along > 0


# --- 3. gradients ---------------------------------------------------------------------------------------------------
def _random_case(seed, h=12, w=12):
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    th = (torch.rand(h, w, generator=g, dtype=torch.float64) - 0.5) * math.pi
    c = torch.rand(h, w, generator=g, dtype=torch.float64)
    c[0, :3] = 0.0  # pixels with no stroke direction: the safe 1/|d|
    d = torch.stack([c * torch.cos(2 * th), c * torch.sin(2 * th)], -1)
    cov = torch.rand(h, w, 1, generator=g, dtype=torch.float64)
    return img, d, cov


def test_gradcheck_of_the_hinge_through_the_energies():
    img, d, cov = _random_case(0)
    ea, el = (float(v) for v in stroke_energies(img, d, cov))
    targets = (2.0 * ea, 0.5 * el)  # both halves of the hinge active
    assert float(stroke_hinge(*stroke_energies(img, d, cov), *targets)) == pytest.approx(0.25 + 1.0, rel=1e-12)
    x = img.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda im: stroke_hinge(*stroke_energies(im, d, cov), *targets), (x,))
    assert torch.autograd.gradcheck(lambda im: torch.stack(stroke_energies(im, d, cov)), (x,))
    assert torch.autograd.gradcheck(lambda im: torch.stack(stroke_energies(im, d, None)), (x,))


def test_hinge_is_zero_where_across_and_along_meet_their_targets():
    img, d, cov = _random_case(1)
    ea, el = stroke_energies(img, d, cov)
    x = img.clone().requires_grad_()
    for targets in ((0.5 * float(ea), 2.0 * float(el)), (float(ea), float(el))):  # inside, and on the edge
        x.grad = None
        h = stroke_hinge(*stroke_energies(x, d, cov), *targets)
        h.backward()
        assert float(h.detach()) == 0.0 and torch.count_nonzero(x.grad) == 0, targets
    # each half alone: across short of its target, along over its target
    assert float(stroke_hinge(ea, el, 2.0 * float(ea), 2.0 * float(el))) == pytest.approx(0.25, rel=1e-12)
    assert float(stroke_hinge(ea, el, 0.5 * float(ea), 0.5 * float(el))) == pytest.approx(1.0, rel=1e-12)


def test_bounded_along_half_stays_below_one_where_the_ratio_grows():
    """along="bounded": (1 - T_along/E_along)^2 while E_along is above T_along, in [0, 1) however far it goes (the
    ratio form grows as (E_along/T_along - 1)^2); the across half and the zero region are the ratio form's."""
    img, d, cov = _random_case(2)
    ea, el = stroke_energies(img, d, cov)
    for k, ratio, bounded in ((0.5, 1.0, 0.25), (0.01, 99.0 ** 2, 0.99 ** 2)):  # E_along = T_along / k
        t = (0.5 * float(ea), k * float(el))  # the across half inactive
        assert float(stroke_hinge(ea, el, *t)) == pytest.approx(ratio, rel=1e-9)
        assert float(stroke_hinge(ea, el, *t, along="bounded")) == pytest.approx(bounded, rel=1e-9)
    assert float(stroke_hinge(ea, el, 0.5 * float(ea), 2.0 * float(el), along="bounded")) == 0.0
    assert float(stroke_hinge(ea, el, 2.0 * float(ea), 2.0 * float(el), along="bounded")) == pytest.approx(0.25, rel=1e-12)
    x = img.clone().requires_grad_()
    targets = (2.0 * float(ea), 0.5 * float(el))  # both halves active
    assert torch.autograd.gradcheck(lambda im: stroke_hinge(*stroke_energies(im, d, cov), *targets, along="bounded"),
                                    (x,))
    with pytest.raises(ValueError, match="along"):
        stroke_hinge(ea, el, *targets, along="linear")


# --- 3a. the relative (log) form -----------------------------------------------------------------------------------
def test_log_form_reads_contrast_relative_to_the_tone():
    """Energies of log(Y + eps) equal the OpenCV oracle's on its own log; the same grating step (amplitude 0.05) on a
    dark ground (Y 0.1) counts ((0.75 + eps)/(0.1 + eps))² ~ 21x one on a light ground (Y 0.75) in the log form and
    the same in the linear form (a version that ignored log_eps, or took the log after the blur, fails)."""
    h, w, deg = GRATING["h"], GRATING["w"], GRATING["deg"]
    field, wt = const_field(h, w, math.radians(deg + 90.0)), interior(h, w)
    got = {}
    for ground in (0.1, 0.75):
        img = grating(**{**GRATING, "amp": 0.05}) - 0.5 + ground
        for eps in (None, STROKE_LOG_EPS):
            ea, el = stroke_energies(torch.from_numpy(img), field, torch.from_numpy(wt), log_eps=eps)
            oa, ol = oracle(img, math.radians(deg + 90.0), wt[..., 0], log_eps=eps)
            assert (float(ea), float(el)) == pytest.approx((oa, ol), rel=ORACLE_TOL, abs=1e-12)
            got[ground, eps] = float(ea)
    assert got[0.1, None] == pytest.approx(got[0.75, None], rel=1e-9)
    ratio = got[0.1, STROKE_LOG_EPS] / got[0.75, STROKE_LOG_EPS]
    assert ratio == pytest.approx(((0.75 + STROKE_LOG_EPS) / (0.1 + STROKE_LOG_EPS)) ** 2, rel=0.15)


def test_log_form_painting_target_and_gradient():
    """The painting's target in the log form equals the torch energies of log luminance on its own field (float64);
    the hinge through the log energies passes gradcheck; field_terms with stroke_log_eps gives the orientation term of
    linear luminance and the hinge of log luminance, values and gradient."""
    q = resize_style(_painting(), 128)
    t_across, t_along = painting_stroke_energies(q, 128, log_eps=STROKE_LOG_EPS)
    _, _, dq = stroke_field(q)
    ea, el = stroke_energies(torch.from_numpy(q).double(), torch.from_numpy(dq), None, log_eps=STROKE_LOG_EPS)
    assert (float(ea), float(el)) == pytest.approx((t_across, t_along), rel=ORACLE_TOL)
    assert (t_across, t_along) != pytest.approx(painting_stroke_energies(q, 128), rel=0.05)
    img, d, cov = _random_case(4)
    ea, el = (float(v) for v in stroke_energies(img, d, cov, log_eps=STROKE_LOG_EPS))
    targets = (2.0 * ea, 0.5 * el)
    x = img.clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda im: stroke_hinge(*stroke_energies(im, d, cov, log_eps=STROKE_LOG_EPS), *targets), (x,))
    x = img.clone().requires_grad_()
    v = field_terms(x, d, cov, stroke_target=targets, stroke_log_eps=STROKE_LOG_EPS)
    (0.7 * v[0] + 1.3 * v[1]).backward()
    y = img.clone().requires_grad_()
    o = 1.0 - flow_alignment_score_torch(y, d)
    hinge = stroke_hinge(*stroke_energies(y, d, cov, log_eps=STROKE_LOG_EPS), *targets)
    (0.7 * o + 1.3 * hinge).backward()
    got, want = v.detach().tolist(), [float(o.detach()), float(hinge.detach())]
    assert got == pytest.approx(want, rel=1e-12)
    assert float(hinge) == pytest.approx(0.25 + 1.0, rel=1e-12)
    assert torch.allclose(x.grad, y.grad, rtol=1e-10, atol=1e-14)


# --- 3b. the two field terms from one gradient pass --------------------------------------------------------------
def test_field_terms_are_the_separate_terms_from_one_pass():
    """[1 - flow alignment score, stroke hinge]: each entry, and the gradient of any mix of them, equal to the
    separate functions' (a version that blurred twice, swapped the entries, or dropped the coverage weight fails);
    an entry is exactly 0 (and adds no gradient) where its term is off."""
    img, d, cov = _random_case(3, 14, 17)
    ea, el = stroke_energies(img, d, cov)
    targets = (2.0 * float(ea), 0.5 * float(el))  # both halves active
    for along in ("ratio", "bounded"):
        x = img.clone().requires_grad_()
        v = field_terms(x, d, cov, stroke_target=targets, along=along)
        (0.7 * v[0] + 1.3 * v[1]).backward()
        y = img.clone().requires_grad_()
        o = 1.0 - flow_alignment_score_torch(y, d)
        h = stroke_hinge(*stroke_energies(y, d, cov), *targets, along=along)
        (0.7 * o + 1.3 * h).backward()
        assert v.shape == (2,) and float(v[0]) == pytest.approx(float(o), rel=1e-12)
        assert float(v[1]) == pytest.approx(float(h), rel=1e-12) and float(h) > 0.1
        assert torch.allclose(x.grad, y.grad, rtol=1e-10, atol=1e-14)
    x = img.clone().requires_grad_()
    only_stroke = field_terms(x, d, cov, orient=False, stroke_target=targets)
    only_stroke[0].backward()
    assert float(only_stroke[0]) == 0.0 and not x.grad.any()
    assert float(field_terms(img, d, cov)[1]) == 0.0  # no target: the stroke entry is off


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
@pytest.mark.parametrize("log_eps, interior", [(None, False), (STROKE_LOG_EPS, False), (None, True)])
def test_field_terms_as_a_cuda_graph_match_eager(log_eps, interior):
    """The phase's call replayed as CUDA graphs gives the eager values and image gradient for renders, fields and
    coverage that change between calls (a graph that kept its first field or coverage fails), one graph per shape;
    with the log form's second gradient pass too, and with the hinge over the eroded coverage."""
    from functools import partial

    from tlvg_warp.losses.stroke_field import gradient_reach, interior_weight

    dev = torch.device("cuda")
    fn = partial(field_terms, stroke_target=(0.05, 0.01) if log_eps is None else (50.0, 1.0), along="ratio",
                 stroke_log_eps=log_eps)
    graphed = GraphedFn(fn)
    for k, (h, w) in enumerate(((40, 56), (40, 56), (40, 56), (32, 30))):
        img, d, cov = (t.float().to(dev) for t in _random_case(10 + k, h, w))
        cov = interior_weight(cov, gradient_reach()) if interior else cov
        out = []
        for f in (fn, graphed):
            x = img.clone().requires_grad_(True)
            v = f(x, d, cov)
            (0.5 * v[0] + 2.0 * v[1]).backward()
            out.append((v.detach().clone(), x.grad))
        (v0, g0), (v1, g1) = out
        assert float(v0[1]) > 0 and torch.allclose(v0, v1, rtol=1e-5, atol=1e-6)
        assert torch.allclose(g0, g1, rtol=1e-4, atol=1e-4 * g0.abs().max())
    assert len(graphed.graphs) == 2


# --- 4. the gradient's direction -------------------------------------------------------------------------------------
def test_descent_raises_contrast_across_over_along():
    """From a flat grey with a little noise (as much contrast along a 120° field as across it), descending the hinge
    puts stripes along the field: E_across/E_along rises and the hinge falls, at the first step and after a few."""
    h = w = 32
    d = const_field(h, w, math.radians(120.0))
    g = torch.Generator().manual_seed(0)
    x = (0.5 + 0.02 * torch.randn(h, w, 1, generator=g, dtype=torch.float64)).expand(h, w, 3).clone()
    ea, el = (float(v) for v in stroke_energies(x, d))
    assert 0.5 < ea / el < 2.0  # the premise: no direction yet
    targets = (10.0 * ea, el)  # ten times the contrast across, no more along: the along half starts at its edge

    def state(im):
        a, b = stroke_energies(im, d)
        return float(stroke_hinge(a, b, *targets)), float(a / b)

    h0, r0 = state(x)
    # one plain gradient step
    xg = x.clone().requires_grad_()
    stroke_hinge(*stroke_energies(xg, d), *targets).backward()
    h1, r1 = state(x - 1e-3 * xg.grad / xg.grad.abs().max())
    assert h1 < h0 and r1 > r0
    # a few Adam steps
    xs = x.clone().requires_grad_()
    opt = torch.optim.Adam([xs], lr=5e-3)
    for _ in range(10):
        opt.zero_grad()
        stroke_hinge(*stroke_energies(xs, d), *targets).backward()
        opt.step()
    hn, rn = state(xs.detach())
    assert hn < 0.1 * h0 and rn > 5 * r0


# --- 5. the Stylize phase --------------------------------------------------------------------------------------------
W, H, VIEWS, SUBSAMPLE = 32, 24, 4, 8


@pytest.fixture(scope="module")
def demo():
    return demo_stylize_inputs(VIEWS, W, H, SUBSAMPLE)[1]


def _stylize_run(inp, **over):
    from tlvg_warp.distributed import Dist
    from tlvg_warp.stylize.config import config_from_dict
    from tlvg_warp.stylize.pipeline import build_run, prepare

    net = StubFeatures()
    cfg = config_from_dict({"iterations": 8, "device": "cpu", "style_height": 64, "vgg_scale": 1.0, "log_every": 1,
                            "background": list(inp.background), **over}).validate()
    tg = prepare(inp, cfg, net, torch.device("cpu"), inp.background)
    return build_run(inp, cfg, tg, net, torch.device("cpu"), Dist(), None), cfg, tg


def _counting(monkeypatch):
    import tlvg_warp.losses as L

    calls, real = [], L.field_terms

    def counted(*a, **k):  # the calls that compute the stroke hinge
        if k.get("stroke_target") is not None:
            calls.append(a[0].shape)
        return real(*a, **k)
    monkeypatch.setattr(L, "field_terms", counted)
    return calls


def test_stylize_logs_the_stroke_term_when_weighted(demo, monkeypatch):
    from tlvg_warp.train.loop import train

    calls = _counting(monkeypatch)
    run, cfg, tg = _stylize_run(demo, **{"loss.w_stroke": 0.5, "loss.strength": 2.0})
    sty = run.phase("stylize")
    assert sty.weights(0)["stroke"] == 4.0  # w_stroke x strength cubed, as the detail hinge
    view_h = int(np.median([c.height for c in run.cams]))
    # a target across far above any render keeps the hinge active (~1), the along half at 0
    sty.stroke_target = (1e3, 1e3)
    train(run, progress=False)
    rows = [r for r in run.log if r["phase"] == "stylize"]
    assert len(rows) == sty.steps > 0 and len(calls) == sty.steps
    assert all(0.5 < r["stroke"] <= 1.0 for r in rows)  # logged, and active: (1 - E_across/1e3)^2
    assert all(r["stroke"] == 0 for r in run.log if r["phase"] != "stylize")
    # the target setup computes: the painting's own energies at the views' height
    run2, _, tg2 = _stylize_run(demo, **{"loss.w_stroke": 0.5})
    sty2 = run2.phase("stylize")
    sty2.setup(run2)
    assert sty2.stroke_target == pytest.approx(painting_stroke_energies(tg2.style_work.numpy(), view_h), rel=1e-12)
    assert all(isinstance(v, float) for v in sty2.stroke_target)


def test_along_none_is_the_across_half_alone():
    """along="none": relu(1 - E_across/T_across)^2 and nothing for contrast along the field, however far E_along is
    above T_along (closed form); an unknown form is refused."""
    img, d, cov = _random_case(3)
    ea, el = stroke_energies(img, d, cov)
    for ka, kl in ((2.0, 0.01), (0.5, 0.01), (4.0, 1e-6)):  # the along half far above its target each time
        across = max(0.0, 1.0 - 1.0 / ka) ** 2  # T_across = ka x E_across
        assert float(stroke_hinge(ea, el, ka * float(ea), kl * float(el), along="none")) == pytest.approx(across,
                                                                                                        rel=1e-12)
        assert float(stroke_hinge(ea, el, ka * float(ea), kl * float(el), along="bounded")) > across + 0.9
    with pytest.raises(ValueError, match="along must be"):
        stroke_hinge(ea, el, 1.0, 1.0, along="across")


def test_stylize_passes_the_along_form_to_the_hinge(demo, monkeypatch):
    """loss.stroke_along reaches the hinge: with the targets far below the render's energies the along half is
    (E_along/T_along - 1)^2 >> 1 in the ratio form, under 1 in the bounded form and absent with none; the across half
    is 0."""
    from tlvg_warp.train.loop import train

    logged = {}
    for form in ("ratio", "bounded", "none"):
        run, cfg, _ = _stylize_run(demo, **{"loss.w_stroke": 0.5, "loss.stroke_along": form})
        assert cfg.loss.stroke_along == form
        run.phase("stylize").stroke_target = (1e-9, 1e-6)
        train(run, progress=False)
        logged[form] = [r["stroke"] for r in run.log if r["phase"] == "stylize"]
    assert all(v > 10.0 for v in logged["ratio"])
    assert all(0.5 < v < 1.0 for v in logged["bounded"])
    assert all(v == 0.0 for v in logged["none"])  # the across half met (its target far below), the along half gone


def test_stylize_passes_the_log_form_to_the_hinge(demo, monkeypatch):
    """loss.stroke_contrast: log reaches the target (the painting's log energies) and every hinge call."""
    import tlvg_warp.losses as L
    from tlvg_warp.train.loop import train

    seen, real = [], L.field_terms

    def spy(*a, **k):
        seen.append(k.get("stroke_log_eps"))
        return real(*a, **k)
    monkeypatch.setattr(L, "field_terms", spy)
    run, cfg, tg = _stylize_run(demo, **{"loss.w_stroke": 0.5, "loss.stroke_contrast": "log"})
    sty = run.phase("stylize")
    train(run, progress=False)
    view_h = int(np.median([c.height for c in run.cams]))
    assert sty.stroke_target == pytest.approx(
        painting_stroke_energies(tg.style_work.numpy(), view_h, log_eps=STROKE_LOG_EPS), rel=1e-12)
    assert len(seen) == sty.steps > 0 and set(seen) == {STROKE_LOG_EPS}
    linear, _, _ = _stylize_run(demo, **{"loss.w_stroke": 0.5})
    assert linear.phase("stylize").stroke_log_eps is None


def test_stylize_never_computes_the_stroke_term_at_weight_zero(demo, monkeypatch):
    from tlvg_warp.train.loop import train

    calls = _counting(monkeypatch)
    run, cfg, _ = _stylize_run(demo)
    assert cfg.loss.w_stroke == 0.0  # off by default
    sty = run.phase("stylize")
    train(run, progress=False)
    assert not sty.on["stroke"] and sty.stroke_target is None and calls == []
    assert all(r["stroke"] == 0 for r in run.log)


def test_interior_weight_is_opencv_erosion_by_the_gradients_reach():
    """interior_weight: the coverage's minimum over a (2r + 1)² square, as cv2.erode computes it (its default border
    does not erode), for a soft coverage and for a disc on an empty background; r = the pre-blur kernel's half-width
    plus Scharr's 1 (an edge moves the gradients that far: a pixel r + 1 away from a step reads none of it)."""
    from tlvg_warp.losses.stroke_field import _ksize, PRE_SIGMA, gradient_reach, interior_weight

    r = gradient_reach()
    assert r == _ksize(PRE_SIGMA) // 2 + 1
    step = np.zeros((40, 40)); step[:, 20:] = 1.0
    y = cv2.GaussianBlur(step, (_ksize(PRE_SIGMA),) * 2, PRE_SIGMA, borderType=cv2.BORDER_REFLECT_101)
    gx = cv2.Scharr(y, cv2.CV_64F, 1, 0, borderType=cv2.BORDER_REFLECT_101)
    assert abs(gx[20, 20 - r]) > 0 and gx[20, 20 - r - 1] == 0.0 and gx[20, 19 + r] > 0 and gx[20, 20 + r] == 0.0
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[:37, :45]
    disc = ((yy - 18) ** 2 + (xx - 20) ** 2 <= 12 ** 2).astype(np.float64)
    for cov in (rng.random((37, 45)), disc):
        got = interior_weight(torch.from_numpy(cov)[..., None], r)[..., 0].numpy()
        want = cv2.erode(cov, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        assert np.array_equal(got, want)
    full = torch.ones(9, 11, 1, dtype=torch.float64)  # a capture: covered everywhere, nothing eroded at the border
    assert torch.equal(interior_weight(full, r), full)


def test_field_terms_interior_weighs_the_eroded_coverage():
    """field_terms over interior_weight(coverage): the hinge of the energies over the coverage eroded as OpenCV
    erodes it (an implementation that kept the coverage, or let the weight reach the orientation term, fails); on a
    bright disc over black the outline alone meets the across half over the coverage, and over the interior it does
    not."""
    from tlvg_warp.losses.stroke_field import gradient_reach, interior_weight

    h, w = 48, 56
    yy, xx = np.mgrid[:h, :w]
    disc = ((yy - 24) ** 2 + (xx - 28) ** 2 <= 18 ** 2).astype(np.float64)
    img = torch.from_numpy(np.repeat(disc[..., None], 3, -1) * 0.8)  # a flat bright disc: contrast at its outline
    th = np.arctan2(yy - 24, xx - 28) + math.pi / 2  # the field runs around the disc: the outline is across it
    d = torch.from_numpy(np.stack([np.cos(2 * th), np.sin(2 * th)], -1))
    cov = torch.from_numpy(disc)[..., None]
    eroded = torch.from_numpy(cv2.erode(disc, np.ones((2 * gradient_reach() + 1,) * 2, np.uint8)))[..., None]
    ea, el = stroke_energies(img, d, cov)
    targets = (0.5 * float(ea), 2.0 * float(el) + 1e-3)  # the along half off
    covered = field_terms(img, d, cov, stroke_target=targets, along="bounded")
    inside = field_terms(img, d, interior_weight(cov, gradient_reach()), stroke_target=targets, along="bounded")
    want = stroke_hinge(*stroke_energies(img, d, eroded), *targets, along="bounded")
    assert float(covered[1]) == pytest.approx(0.0, abs=1e-12)  # the outline meets the across target
    assert float(inside[1]) == pytest.approx(float(want), rel=1e-12) and float(inside[1]) > 0.9  # a flat interior
    assert float(inside[0]) == float(covered[0])  # the orientation term is untouched


def test_stylize_passes_the_interior_choice_to_the_hinge(demo, monkeypatch):
    """loss.stroke_where reaches the stroke hinge: every call that computes it during a run gets a view's coverage
    as it is (covered) or that coverage eroded as cv2.erode erodes it (interior), made once per run; other values are
    refused by the config."""
    import tlvg_warp.losses as L
    from tlvg_warp.losses.stroke_field import gradient_reach
    from tlvg_warp.stylize.config import config_from_dict
    from tlvg_warp.train.loop import train

    seen, real = [], L.field_terms

    def recording(*a, **k):  # the weight of each call that computes the stroke hinge
        if k.get("stroke_target") is not None:
            seen.append(a[2].detach().numpy().copy())
        return real(*a, **k)
    monkeypatch.setattr(L, "field_terms", recording)
    kernel = np.ones((2 * gradient_reach() + 1,) * 2, np.uint8)
    for where in ("covered", "interior"):
        seen.clear()
        run, cfg, tg = _stylize_run(demo, **{"loss.w_stroke": 0.5, "loss.stroke_where": where})
        covs = [c.numpy()[..., 0] for c in tg.coverage]
        want = covs if where == "covered" else [cv2.erode(c, kernel) for c in covs]
        train(run, progress=False)
        assert len(seen) == run.phase("stylize").steps > 0
        assert all(any(np.array_equal(w[..., 0], x) for x in want) for w in seen)
        if where == "interior":  # the demo's views have edges to erode: the two forms differ
            assert not all(any(np.array_equal(w[..., 0], c) for c in covs) for w in seen)
    with pytest.raises(Exception, match="stroke_where"):
        config_from_dict({"loss.stroke_where": "outline"}).validate()
