"""SPEC §4 sanity: known cases lose, on the metric meant to catch them, to a genuine stylization; the flow
alignment metric breaks when its coherence weighting or its pixel correspondence is broken; statistics.

The genuine stylization is the demo scene with every Gaussian recolored from the painting by a planar map of
its position (painting texture attached to the geometry: consistent across views). The cases: the painting
pasted in screen space on every view (sticker), the un-stylized scene, the genuine scene with every Gaussian
3x wider (blurred, and spilling into the empty background), and with half of the Gaussians made transparent (holes)."""
import math

import cv2
import numpy as np
import pytest
import torch

from tlvg_warp.eval import metrics as M
from tlvg_warp.eval import refs as R
from tlvg_warp.io.demo import builtin_painting, demo_scene
from tlvg_warp.losses.stroke_field import stroke_field
from tlvg_warp.stylize.outputs import _fit_painting
from tlvg_warp.types import SH_C0

W, H, N_VIEWS, EVAL_H = 56, 42, 7, 64  # 7 views: 6 pairs at k=1, 2 at k=5
BG = (1.0, 1.0, 1.0)
BLUR_SCALE = 3.0
DROP = 0.5


def _recolor(g, rgb):
    out = g.clone()
    sh = torch.zeros(g.num, 1, 3)
    sh[:, 0] = (torch.as_tensor(rgb, dtype=torch.float32) - 0.5) / SH_C0
    out.sh = sh
    return out


def genuine_stylization(g, painting):
    m = g.means.numpy()
    lo, hi = m.min(0), m.max(0)
    uv = (m[:, :2] - lo[:2]) / (hi[:2] - lo[:2])  # [N,2] planar map of the scene onto the painting
    ph, pw = painting.shape[:2]
    return _recolor(g, painting[(uv[:, 1] * (ph - 1)).astype(int), (uv[:, 0] * (pw - 1)).astype(int)])


@pytest.fixture(scope="module")
def net():
    from tlvg_warp.losses.vgg import load_vgg

    n = load_vgg("hed")
    assert not n.is_random
    return n


@pytest.fixture(scope="module")
def cases(net):
    g, cams = demo_scene(n_views=N_VIEWS, width=W, height=H)
    p = builtin_painting().numpy()
    photos = [v["color"] for v in R.render_views(g, cams, BG)]
    refs = R.build_references(g, cams, BG, p, photos, net, eval_height=EVAL_H)
    gen = genuine_stylization(g, p)
    blur = gen.clone()
    blur.log_scales = gen.log_scales + math.log(BLUR_SCALE)
    holed = gen.clone()
    drop = torch.from_numpy(np.random.default_rng(0).random(g.num) < DROP)
    holed.opacity_logits = torch.where(drop, torch.full_like(g.opacity_logits, -20.0), g.opacity_logits)
    per = {}
    for name, s in (("genuine", gen), ("unstylized", g), ("blurred", blur), ("holed", holed)):
        per[name] = R.score_views(*R.stylized_views(s, refs), refs, net)
    views, a2 = R.stylized_views(g, refs)  # the un-stylized coverage, the painting pasted over every view
    for v in views:
        v["color"] = _fit_painting(p, H, W)
    per["sticker"] = R.score_views(views, a2, refs, net)
    return refs, per


@pytest.mark.parametrize("case,metrics", [
    ("sticker", ("consistency_k1", "consistency_k5", "content")),
    ("unstylized", ("style_gram", "style_nnfm", "stroke_scales", "tone_inside", "colour_inside")),
    ("blurred", ("detail", "detail_inside", "spill")),  # 3x wider splats also paint the empty background
    ("holed", ("holes_1x", "holes_2x", "consistency_k1")),
])
def test_known_cases_lose_to_a_genuine_stylization(cases, case, metrics):
    _, per = cases
    cmp = R.compare(per["genuine"], per[case])
    for k in metrics:
        assert cmp[k]["better"] == "a", (case, k, cmp[k])


def test_inside_style_distances_read_the_scene_not_its_empty_background(cases):
    """style_gram_inside and style_nnfm_inside are scored over the feature cells inside the scene: on the demo, whose
    views are about a quarter empty background, each differs from its whole-view figure on every view (scored on the
    whole view, they would equal it), and the un-stylized scene loses both to a genuine stylization."""
    _, per = cases
    for k in ("style_gram", "style_nnfm"):
        assert all(abs(i - w) > 1e-4 for i, w in zip(per["genuine"][k + "_inside"], per["genuine"][k])), k
    cmp = R.compare(per["genuine"], per["unstylized"])
    for k in ("style_gram_inside", "style_nnfm_inside"):
        assert cmp[k]["better"] == "a", (k, cmp[k])


def brushed(color, field, length=6, seed=0):
    """The view painted with strokes along a doubled-angle field [H,W,2]: noise smeared along the field's
    direction at each pixel (a line integral convolution over ±length px) modulates the view's luminance."""
    import cv2

    h, w = color.shape[:2]
    theta = 0.5 * np.arctan2(field[..., 1], field[..., 0])
    noise = np.random.default_rng(seed).random((h, w)).astype(np.float32)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    acc = np.zeros((h, w), np.float32)
    for t in range(-length, length + 1):
        acc += cv2.remap(noise, x + t * np.cos(theta).astype(np.float32), y + t * np.sin(theta).astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    strokes = acc / (2 * length + 1)
    strokes = (strokes - strokes.mean()) / (strokes.std() + 1e-6)
    return np.clip(color * (1.0 + 0.35 * strokes[..., None]), 0, 1).astype(np.float32)


@pytest.mark.parametrize("anchor", ["sticker", "unstylized"])
def test_anchors_lose_flow_alignment_to_strokes_along_the_painting_flow(cases, anchor):
    """The un-stylized scene and the painting pasted on the screen both lose the common-field flow alignment to
    the scene painted with strokes that follow the painting's flow on it (each view brushed along the common
    field). The brushed views are scored as a run would be."""
    refs, per = cases
    views, a2 = R.anchor_views(refs)[M.UNSTYLIZED]
    painted = [{"color": brushed(v["color"], f, seed=i), "alpha": v["alpha"]}
               for i, (v, f) in enumerate(zip(views, refs.fields))]
    fa = [M.flow_alignment(v["color"], f) for v, f in zip(painted, refs.fields)]
    verdict = M.paired(fa, per[anchor]["flow_alignment"], M.METRICS["flow_alignment"])
    assert verdict["better"] == "a", verdict


def test_evaluate_builds_its_anchors_as_the_cases_are_built(cases, net):
    """eval/refs.anchor_views against this file's own construction: the un-stylized anchor is the un-stylized
    scene's render, the sticker the painting center-cropped and resized by the stylize outputs' own crop; scored
    with the same ruler they give the values the cases give (the sticker's coverage is the full view)."""
    refs, per = cases
    anchors = R.anchor_views(refs)
    views, a2 = anchors[M.UNSTYLIZED]
    own = R.render_views(demo_scene(n_views=N_VIEWS, width=W, height=H)[0], refs.cameras, BG)
    for v, o in zip(views, own):
        np.testing.assert_array_equal(v["color"], o["color"])
    sviews, _ = anchors[M.STICKER]
    for v in sviews:
        np.testing.assert_allclose(v["color"], _fit_painting(refs.painting, H, W), atol=1e-6)
        assert v["alpha"].min() == 1.0
    assert R.score_views(views, a2, refs, net) == per["unstylized"]


def test_every_metric_has_the_anchor_it_must_beat_declared():
    per_view = {k for k, m in M.METRICS.items() if m.per_view}
    assert set(M.ANCHOR_TO_BEAT) == per_view
    assert set(M.ANCHOR_TO_BEAT.values()) <= {M.UNSTYLIZED, M.STICKER, None}


def test_every_metric_declares_direction_and_unit():
    for m in M.METRICS.values():
        assert m.unit and m.words and m.direction in ("higher is better", "lower is better")


def test_random_weights_leave_vgg_metrics_not_measured(cases):
    from tlvg_warp.losses.vgg import load_vgg

    refs, _ = cases
    rnd = load_vgg("random")
    per = R.score_views(*R.stylized_views(demo_scene(n_views=N_VIEWS, width=W, height=H)[0], refs), refs, rnd)
    for k, m in M.METRICS.items():
        if m.per_view:
            assert (per[k] is None) == m.pretrained, k


# ---------------------------------------------------------------- flow alignment: the weighting and the pixels
def _stripes(h, w, angle_left, angle_right, period=6.0):
    """Sinusoidal stripes whose stroke direction (along the stripes) is angle_left on the left half and
    angle_right on the right half (radians, pixel axes)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    a = np.where(x < w / 2, angle_left, angle_right)
    phase = (-np.sin(a) * x + np.cos(a) * y) * 2 * np.pi / period  # constant along (cos a, sin a)
    return np.repeat((0.5 + 0.4 * np.sin(phase))[..., None], 3, -1).astype(np.float32)


def _field(h, w, angle_left, c_left, angle_right, c_right):
    x = np.arange(w)[None, :].repeat(h, 0)
    a = np.where(x < w / 2, angle_left, angle_right)
    c = np.where(x < w / 2, c_left, c_right)
    return np.stack([c * np.cos(2 * a), c * np.sin(2 * a)], -1).astype(np.float32)


def check_flow_alignment_orders():
    """The properties the metric must have (a broken metric fails them):
    1. coherence weighting: the target is coherent (c 1) horizontal on the left, nearly direction-less (c 0.05)
       vertical on the right. Horizontal strokes everywhere follow the painting where it has a direction;
       vertical strokes everywhere follow only its noise. The first must win by a wide margin.
    2. same pixel: strokes horizontal left / vertical right against a field horizontal left / vertical right
       score near 1; against the mirrored layout they score near −1."""
    h, w = 48, 96
    target = _field(h, w, 0.0, 1.0, np.pi / 2, 0.05)
    along = M.flow_alignment(_stripes(h, w, 0.0, 0.0), target)
    noise = M.flow_alignment(_stripes(h, w, np.pi / 2, np.pi / 2), target)
    assert along - noise > 1.0, (along, noise)  # weighted: ~0.9 vs ~−0.9; unweighted both ~0
    split = _field(h, w, 0.0, 1.0, np.pi / 2, 1.0)
    same = M.flow_alignment(_stripes(h, w, 0.0, np.pi / 2), split)
    mirrored = M.flow_alignment(_stripes(h, w, np.pi / 2, 0.0), split)
    assert same > 0.8 and mirrored < -0.8, (same, mirrored)


def test_flow_alignment_orders_known_cases():
    check_flow_alignment_orders()


def test_flow_alignment_check_catches_missing_coherence_weighting(monkeypatch):
    unit = lambda d: d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)  # noqa: E731
    real_render, real_field = M.render_field, M.field_at_pixels
    # both fields cut to unit length: every pixel weighs the same, whatever either coherence
    monkeypatch.setattr(M, "render_field", lambda img: unit(real_render(img)))
    monkeypatch.setattr(M, "field_at_pixels", lambda f, h, w: unit(real_field(f, h, w)))
    with pytest.raises(AssertionError):
        check_flow_alignment_orders()


def test_flow_alignment_check_catches_mirrored_sampling(monkeypatch):
    orig = M.field_at_pixels
    monkeypatch.setattr(M, "field_at_pixels", lambda f, h, w: orig(f, h, w)[:, ::-1])
    with pytest.raises(AssertionError):
        check_flow_alignment_orders()


def _stripes_amp(h, w, angle, amp, period=6.0):
    return 0.5 + (_stripes(h, w, angle, angle, period) - 0.5) * (amp / 0.4)


def test_flow_energy_weighs_pixels_by_their_contrast():
    """Strong stripes across the field on the left half, faint stripes (contrast 0.002) along it on the right: by
    contrast the render runs against the field (flow_energy near -1), while the contrast-blind flow_alignment counts
    the faint half nearly as much as the strong one (above -0.6; the strong half's smoothed tensor spills over). Closed form on uniform stripes: +1 along the field, -1 across, and a global contrast
    scale changes nothing."""
    h, w = 48, 96
    field = _field(h, w, 0.0, 1.0, 0.0, 1.0)  # horizontal strokes everywhere
    img = _stripes_amp(h, w, np.pi / 2, 0.4)
    img[:, w // 2:] = _stripes_amp(h, w, 0.0, 0.002)[:, w // 2:]
    assert M.flow_energy(img, field) < -0.95 and M.flow_alignment(img, field) > -0.6, \
        (M.flow_energy(img, field), M.flow_alignment(img, field))
    along, across = _stripes_amp(h, w, 0.0, 0.4), _stripes_amp(h, w, np.pi / 2, 0.4)
    assert M.flow_energy(along, field) > 0.95 and M.flow_energy(across, field) < -0.95
    faint = _stripes_amp(h, w, 0.0, 0.05)
    assert M.flow_energy(faint, field) == pytest.approx(M.flow_energy(along, field), abs=1e-6)
    assert math.isnan(M.flow_energy(np.full((h, w, 3), 0.5, np.float32), field))  # flat: no weight, no number


def test_common_field_follows_the_unstylized_view(cases):
    """The field is built from the un-stylized render: its coherent directions line up with that render's own
    structure (edges of the still life) far better than with a rotated copy of themselves."""
    refs, _ = cases
    f = refs.fields[0]
    rot = np.stack([-f[..., 0], -f[..., 1]], -1)  # every direction turned by 90 degrees
    assert M.flow_alignment(refs.base[0]["color"], f) > M.flow_alignment(refs.base[0]["color"], rot) + 0.5


# ---------------------------------------------------------------- statistics
def test_interval_covers_mean_and_is_deterministic():
    x = np.random.default_rng(3).normal(2.0, 1.0, 40)
    a, b = M.interval(x), M.interval(list(x))
    assert a == b and a["lo"] < x.mean() < a["hi"]
    se = x.std(ddof=1) / math.sqrt(x.size)  # oracle: the normal-approximation interval, ±1.96 se
    assert a["hi"] - a["lo"] == pytest.approx(2 * 1.96 * se, rel=0.2)


def test_grouped_interval_holds_the_spread_between_groups():
    """Runs of three seeds whose means are 0, 1 and 2 (tiny spread within each): the two-stage bootstrap draws
    three seeds with replacement, so its 2.5% / 97.5% points are the all-lowest and all-highest draws (each has
    probability 1/27 > 2.5%): about 0 and 2. Treating the 60 items as independent gives an interval of about
    ±1.96 x 0.82 / sqrt(60) = ±0.21 around 1."""
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal(mu, 1e-3, 20) for mu in (0.0, 1.0, 2.0)])
    groups = np.repeat([0, 1, 2], 20)
    g, naive = M.interval(x, groups=groups), M.interval(x)
    assert g["mean"] == naive["mean"] == pytest.approx(1.0, abs=1e-3)
    assert g["lo"] == pytest.approx(0.0, abs=0.01) and g["hi"] == pytest.approx(2.0, abs=0.01)
    assert naive["hi"] - naive["lo"] == pytest.approx(2 * 1.96 * x.std(ddof=1) / math.sqrt(x.size), rel=0.2)


def test_grouped_interval_without_spread_between_groups_is_the_plain_one():
    """Three seeds drawn from one distribution: seeds add no spread, so the two-stage interval has the width of
    the plain one over all items (the normal-approximation oracle, ±1.96 se)."""
    x = np.random.default_rng(6).normal(0.5, 0.2, 90)
    g = M.interval(x, groups=np.repeat([0, 1, 2], 30))
    se = x.std(ddof=1) / math.sqrt(x.size)
    assert g["hi"] - g["lo"] == pytest.approx(2 * 1.96 * se, rel=0.3)
    # NaN items drop out of both the values and their labels
    y = np.concatenate([x, [np.nan]])
    assert M.interval(y, groups=np.repeat([0, 1, 2, 2], [30, 30, 30, 1])) == g


def test_paired_says_no_difference_when_interval_contains_zero():
    rng = np.random.default_rng(4)
    base = rng.normal(0, 1, 30)
    m = M.METRICS["consistency_k1"]  # lower is better
    assert M.paired(base, base + rng.normal(0, 0.01, 30), m)["better"] == "no difference"
    assert M.paired(base, base + 0.5 + rng.normal(0, 0.01, 30), m)["better"] == "a"
    assert M.paired(base + 0.5, base, m)["better"] == "b"


def _object_on_white(offset, h=60, w=80, seed=4):
    """A textured square object (its luminance offset by ``offset``) on a white background, its alpha [H,W,1]."""
    rng = np.random.default_rng(seed)
    y = np.ones((h, w), np.float32)
    alpha = np.zeros((h, w, 1), np.float32)
    y[15:45, 20:60] = 0.5 + offset + 0.1 * rng.standard_normal((30, 40)).astype(np.float32)
    alpha[15:45, 20:60] = 1.0
    return y, alpha


def test_detail_inside_leaves_out_the_outline_and_keeps_a_covered_view_whole():
    """detail_inside: the blur residual over the un-stylized scene's interior, against a direct OpenCV computation
    over the covered pixels eroded by the kernel's reach (4 sigma); a darker object (a stronger outline, the same texture) moves the
    whole-view detail but not the inside one; a view covered everywhere is measured whole."""
    import cv2

    light, alpha = _object_on_white(0.2)
    dark, _ = _object_on_white(-0.2)
    inside = M.interior(alpha, light.shape)
    r = int(round(4 * M.HF_SIGMA))
    want_mask = np.zeros(light.shape, bool)
    want_mask[15 + r:45 - r, 20 + r:60 - r] = True
    np.testing.assert_array_equal(inside, want_mask)
    res = light - cv2.GaussianBlur(light, (0, 0), M.HF_SIGMA, borderType=cv2.BORDER_REFLECT_101)
    assert M.hf_energy(light, inside) == pytest.approx(float((res[want_mask] ** 2).mean()), rel=1e-6)
    assert M.hf_energy(dark, inside) == pytest.approx(M.hf_energy(light, inside), rel=1e-5)  # texture alone
    assert M.hf_energy(dark) > 1.2 * M.hf_energy(light)  # the whole view counts the stronger outline
    full = M.interior(np.ones((30, 40)), light.shape)  # a capture: every pixel, the image border not eroded
    assert full.all() and M.hf_energy(light, full) == M.hf_energy(light)
    assert M.hf_energy(light, np.zeros(light.shape, bool)) == 0.0  # nothing covered


def test_spill_counts_paint_where_the_scene_was_empty():
    """Oracle: counted by hand on a 4x4 view. The un-stylized scene covers the left half; the run covers the left
    half but one pixel (a hole, not spill), and three pixels of the empty right half (spill 3 of the view's 16):
    alpha exactly 0.5 counts as covered (SPEC §4: alpha >= 0.5), 0.49 does not."""
    base = np.zeros((4, 4), np.float32)
    base[:, :2] = 1.0
    run = base.copy()
    run[0, 0] = 0.2
    run[1, 2] = run[2, 3] = 0.9
    run[3, 3] = 0.5
    run[0, 3] = 0.49
    assert M.spill(run, base) == 3 / 16
    assert M.spill(base, base) == 0.0
    assert M.spill(np.ones((4, 4)), np.ones((4, 4))) == 0.0  # nothing empty (a capture): nothing to spill into
    assert M.spill(np.ones((4, 4)), base) == 0.5  # a sticker over an object scene: all of its empty half


def test_gram_inside_takes_the_cells_inside_the_scene_against_a_float64_oracle():
    """style_gram_inside's matrices: over the feature cells whose area is at least half inside the mask, against a
    numpy float64 Gram of the cells chosen by block means (the map is the mask's size over 4 and 8, so a cell is a
    4x4 or 8x8 block); a mask covering everything gives the whole-view matrices exactly, an empty one falls back
    to them."""
    gen = torch.Generator().manual_seed(3)
    hh, ww = 32, 48
    f = {k: torch.rand(2, 5, hh // s, ww // s, generator=gen) for k, s in zip(M.GRAM_LAYERS, (4, 4, 8, 8))}
    f |= {k: torch.rand(2, 5, hh // 8, ww // 8, generator=gen) for k in ("relu3_1", "relu3_2")}
    mask = np.zeros((hh, ww), bool)
    mask[5:27, 9:40] = True
    got = M._feats_of(f, 1, mask)
    for k, s in zip(M.GRAM_LAYERS, (4, 4, 8, 8)):
        blocks = mask.reshape(hh // s, s, ww // s, s).mean(axis=(1, 3)).reshape(-1) >= 0.5
        a = f[k][1].double().numpy().reshape(5, -1)[:, blocks]
        np.testing.assert_allclose(got["grams_inside"][k].numpy(), a @ a.T / a.shape[1], rtol=1e-6)
        assert not np.allclose(got["grams_inside"][k].numpy(), got["grams"][k].numpy(), rtol=1e-3)
    whole = M._feats_of(f, 1, np.ones((hh, ww), bool))
    empty = M._feats_of(f, 1, np.zeros((hh, ww), bool))
    for k in M.GRAM_LAYERS:
        assert torch.equal(whole["grams_inside"][k], whole["grams"][k])
        assert torch.equal(empty["grams_inside"][k], empty["grams"][k])
    assert M._feats_of(f, 1)["grams_inside"] is None


def test_nnfm_inside_takes_the_relu3_cells_inside_the_scene_against_an_oracle():
    """style_nnfm_inside's features: the relu3 columns of the cells at least half inside the mask (block means of
    the mask at the relu3 map's size, numpy), all of them for a full or an empty mask, none without a mask; and its
    distance is the NNFM of those columns alone, which differs from the whole view's (float64 brute force)."""
    gen = torch.Generator().manual_seed(5)
    hh, ww = 32, 48
    f = {k: torch.rand(1, 4, hh // s, ww // s, generator=gen) for k, s in zip(M.GRAM_LAYERS, (2, 2, 4, 8))}
    f |= {k: torch.rand(1, 4, hh // 4, ww // 4, generator=gen) for k in ("relu3_1", "relu3_2")}
    f["relu3_3"][0, :, :, :6] += 3.0  # the cells left of the object: far from the painting below
    mask = np.zeros((hh, ww), bool)
    mask[3:30, 22:45] = True
    got = M._feats_of(f, 0, mask)
    keep = mask.reshape(hh // 4, 4, ww // 4, 4).mean(axis=(1, 3)).reshape(-1) >= 0.5
    r3 = torch.cat([f["relu3_1"][0], f["relu3_2"][0], f["relu3_3"][0]], 0).reshape(12, -1).double().numpy()
    np.testing.assert_array_equal(got["relu3_inside"].double().numpy(), r3[:, keep])
    assert torch.equal(M._feats_of(f, 0, np.ones((hh, ww), bool))["relu3_inside"], got["relu3"])
    assert torch.equal(M._feats_of(f, 0, np.zeros((hh, ww), bool))["relu3_inside"], got["relu3"])
    assert M._feats_of(f, 0)["relu3_inside"] is None
    painting = torch.rand(12, 30, generator=gen, dtype=torch.float64).numpy()

    def nnfm(a):  # mean over the render's cells of the least 1 - cos to a painting cell
        a, s = a / np.linalg.norm(a, axis=0), painting / np.linalg.norm(painting, axis=0)
        return float((1 - (a.T @ s).max(axis=1)).mean())
    inside = M.style_nnfm(got["relu3_inside"], torch.from_numpy(painting))
    assert inside == pytest.approx(nnfm(r3[:, keep]), abs=1e-6)
    assert abs(inside - M.style_nnfm(got["relu3"], torch.from_numpy(painting))) > 1e-3


def test_an_image_seen_twice_reuses_its_features_only_where_its_masks_agree():
    """vgg_feats_batch's reuse (a sticker is the same image on every view): the same image under two masks gets
    two inside Gram matrices, each the one its own pass gives; under one mask, one pass."""
    from tlvg_warp.losses.vgg import load_vgg

    net = load_vgg("random")
    img = np.random.default_rng(0).random((40, 56, 3), dtype=np.float32)
    a, b = np.zeros((40, 56), bool), np.zeros((40, 56), bool)
    a[:, :28], b[:, 28:] = True, True
    fa, fb, fa2 = M.vgg_feats_batch(net, [img, img, img], [a, b, a])
    assert fa2 is fa  # the same image and mask: reused
    for k in M.GRAM_LAYERS:
        assert torch.equal(fa["grams"][k], fb["grams"][k])
        assert not torch.allclose(fa["grams_inside"][k], fb["grams_inside"][k])
        alone = M.vgg_feats_batch(net, [img], [b])[0]["grams_inside"][k]  # a batch of one: float32 rounding apart
        assert torch.allclose(fb["grams_inside"][k], alone, rtol=1e-4, atol=1e-7)


def test_detail_is_the_views_luma_residual_over_the_paintings():
    """M.detail, the figure `evaluate` reports as detail and detail_inside: a grey view's blur residual energy (in
    float64 OpenCV, over the interior when given) divided by the painting's; a painting without detail gives a
    finite figure, not a division by zero."""
    import cv2

    light, alpha = _object_on_white(0.2)
    view = np.repeat(light[..., None], 3, -1)  # grey: luma is the value itself
    inside = M.interior(alpha, light.shape)
    y = light.astype(np.float64)
    res2 = (y - cv2.GaussianBlur(y, (0, 0), M.HF_SIGMA, borderType=cv2.BORDER_REFLECT_101)) ** 2
    assert M.detail(view, 0.004) == pytest.approx(res2.mean() / 0.004, rel=1e-4)
    assert M.detail(view, 0.004, inside) == pytest.approx(res2[inside].mean() / 0.004, rel=1e-4)
    assert np.isfinite(M.detail(view, 0.0))


def test_tone_distance_is_the_wasserstein_distance_of_luminance_in_closed_form():
    """tone_inside: the 1-D Wasserstein distance between luminance distributions. Closed forms: a grey image against
    itself shifted by c is c away; uniform luminance on [0, a] against [0, b] is |b - a| / 2 away (the percentiles
    differ by q |b - a|, q's mean 1/2 on the symmetric grid); pixels outside the scene do not count."""
    rng = np.random.default_rng(3)
    y = rng.uniform(0.2, 0.6, (60, 80)).astype(np.float32)
    grey = np.repeat(y[..., None], 3, axis=2)  # luma of (y, y, y) is y
    assert M.tone_distance(grey + 0.15, M.tones(grey)) == pytest.approx(0.15, abs=1e-5)
    ramp = np.linspace(0.0, 1.0, 100_001, dtype=np.float64)
    a, b = 0.4, 0.9
    ua = np.repeat((a * ramp)[None, :, None], 3, axis=2).astype(np.float32)
    ub = np.repeat((b * ramp)[None, :, None], 3, axis=2).astype(np.float32)
    assert M.tone_distance(ub, M.tones(ua)) == pytest.approx((b - a) / 2, abs=1e-4)
    inside = np.zeros(y.shape, bool)
    inside[10:50, 20:70] = True
    outside_changed = grey.copy()
    outside_changed[~inside] = 1.0  # a white background around the scene
    ref = M.tones(grey, inside)
    assert M.tone_distance(outside_changed, ref, inside) == pytest.approx(0.0, abs=1e-7)
    assert M.tone_distance(outside_changed, ref) > 0.05  # the whole view would count the background


def test_colour_distance_is_the_sliced_wasserstein_distance_of_lab_chroma():
    """colour_inside: along each direction θ of the Lab a,b plane, the 1-D Wasserstein distance of the projected
    chroma, averaged. Closed form: chroma shifted by (d, 0) is d x mean |cos θ| away. Oracle: SciPy's
    wasserstein_distance of the projections (the percentile grid leaves out 1% at each end, hence the tolerance),
    with OpenCV's Lab conversion computed here independently. Pixels outside the scene do not count."""
    from scipy.stats import wasserstein_distance

    rng = np.random.default_rng(5)
    ab = rng.normal(0.0, 20.0, (200_000, 2))
    angles = np.arange(16) * np.pi / 16
    d = 7.5
    assert np.abs(M.chroma_quantiles(ab + [d, 0.0]) - M.chroma_quantiles(ab)).mean() == pytest.approx(
        d * np.abs(np.cos(angles)).mean(), rel=1e-9)
    view = rng.uniform(0.0, 1.0, (90, 120, 3)).astype(np.float32)
    painting = builtin_painting().numpy().astype(np.float32)
    lab = lambda im: cv2.cvtColor(im, cv2.COLOR_RGB2Lab)[..., 1:].reshape(-1, 2).astype(np.float64)  # noqa: E731
    u = np.stack([np.cos(angles), np.sin(angles)])
    pv, pp = lab(view) @ u, lab(painting) @ u
    oracle = np.mean([wasserstein_distance(pv[:, k], pp[:, k]) for k in range(len(angles))])
    assert M.colour_distance(view, M.colours(painting)) == pytest.approx(oracle, rel=0.03)
    inside = np.zeros(view.shape[:2], bool)
    inside[20:70, 30:100] = True
    changed = view.copy()
    changed[~inside] = (1.0, 0.0, 0.0)  # a red background around the scene
    assert M.colour_distance(changed, M.colours(view, inside), inside) == pytest.approx(0.0, abs=1e-9)
    assert M.colour_distance(changed, M.colours(view, inside)) > 1.0  # the whole view would count it


def test_colour_distance_reads_a_blend_of_two_hues_as_farther_than_the_hues_rearranged():
    """The case the metric was added for: a painting of blue and yellow against a render that blends them into one
    hue (what a smooth colour map gives a uniform floor) and against one that places the same two hues elsewhere.
    The blend is far, the rearrangement is at 0: the distance reads the palette, not where each colour sits."""
    blue, yellow = np.array([0.1, 0.2, 0.7], np.float32), np.array([0.9, 0.8, 0.2], np.float32)
    painting = np.empty((64, 96, 3), np.float32)
    painting[:, :48], painting[:, 48:] = blue, yellow
    stripes = np.empty_like(painting)
    stripes[0::2], stripes[1::2] = yellow, blue  # the same pixels of each hue, in rows
    blend = np.broadcast_to((blue + yellow) / 2, painting.shape).copy()
    ref = M.colours(painting)
    assert M.colour_distance(stripes, ref) == pytest.approx(0.0, abs=1e-9)
    assert M.colour_distance(blend, ref) > 20.0  # Lab units: the two hues' chroma lie about 100 apart


def test_tone_distance_reads_an_image_paler_and_flatter_than_the_painting_as_farther():
    """The case the metric was added for: the painting's own pixels are nearer its tones than a paler, flatter
    copy (contrast halved around a lighter mean), which the Gram distance over texture alone need not see."""
    p = builtin_painting().numpy().astype(np.float32)
    ref = M.tones(p)
    pale = np.clip(0.5 * (p - p.mean()) + p.mean() + 0.2, 0.0, 1.0)
    assert M.tone_distance(p, ref) < 1e-6 < M.tone_distance(pale, ref)
    # at least the gap of the two percentile grids' means (the triangle inequality), here about the lift of 0.2
    assert M.tone_distance(pale, ref) >= abs(M.tones(pale).mean() - ref.mean()) - 1e-9 > 0.1
