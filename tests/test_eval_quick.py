"""Evaluation metrics against closed-form oracles: reprojection of a fronto-parallel plane under a pure
translation (pixel shift fx·tx/Z), occlusion masking on a hand-built two-plane scene, renderer round trip."""
import math

import numpy as np
import torch

from tlvg_warp import Camera, Gaussians
from tlvg_warp.eval import quick as M
from tlvg_warp.types import SH_C0

W, H, F_PX = 64, 48, 50.0
Z = 4.0  # plane depth (m)
TX = 0.3  # camera j moved right by 0.3 m: every pixel shifts left by fx·tx/Z = 3.75 px (non-integer)
SHIFT = F_PX * TX / Z
LAM = 16.0  # texture wavelength (px): bilinear interpolation error ~ (π/λ)²/8 · amplitude ~ 0.2 %
# Bilinear sampling of a sinusoid of wavelength 16 px, amplitude 0.4: error ≤ 0.4·(2π/16)²/8 ≈ 0.008
# per sample, RMS below half that.
INTERP_TOL = 0.008
# Renders of a Gaussian-splat plane at two poses: splat footprints are resampled at different sub-pixel
# phases, which changes colors by a few 1/255 steps at this texture frequency.
RENDER_TOL = 0.03
PERTURB_PX = 3.0  # the perturbed view is off by 3 px: a sinusoid of λ 16 px changes by ~0.4·|2 sin(π·3/16)|


def cam_at(x):
    m = np.eye(4)
    m[0, 3] = -x  # camera center at (x, 0, 0), looking down +z, no rotation
    return Camera(torch.from_numpy(m), F_PX, F_PX, W / 2, H / 2, W, H)


def tex(u, v):
    return torch.stack([0.5 + 0.4 * torch.sin(2 * math.pi * u / LAM) * torch.cos(2 * math.pi * v / (1.5 * LAM)),
                        0.5 + 0.3 * torch.cos(2 * math.pi * (u + v) / LAM), 0.5 + 0 * u], -1)


def test_reproject_matches_closed_form_shift():
    ci, cj = cam_at(0.0), cam_at(TX)
    uj, vj, zj = M.reproject(torch.full((H, W), Z), ci, cj)
    u, v = M.pixel_grid(H, W)
    assert torch.allclose(uj, u - SHIFT, atol=1e-9)
    assert torch.allclose(vj, v, atol=1e-9)
    assert torch.allclose(zj, torch.full_like(zj, Z), atol=1e-12)


def test_consistency_zero_when_consistent_and_positive_when_perturbed():
    ci, cj = cam_at(0.0), cam_at(TX)
    u, v = M.pixel_grid(H, W)
    depth, alpha = torch.full((H, W), Z), torch.ones(H, W)
    img_i = tex(u, v)
    img_j = tex(u + SHIFT, v)  # what camera j sees: the plane point under i's pixel u lies at u − SHIFT in j
    good = M.consistency(img_i, depth, alpha, ci, img_j, depth, alpha, cj)
    # valid pixels: those whose reprojection lands between j's first and last pixel centers
    uj = u - SHIFT
    expect_valid = int(((uj >= 0.5) & (uj <= W - 0.5)).sum())
    assert good["valid"] == expect_valid
    assert good["rmse"] < INTERP_TOL
    bad_j = tex(u + SHIFT + PERTURB_PX, v)
    bad = M.consistency(img_i, depth, alpha, ci, bad_j, depth, alpha, cj)
    # oracle: the RMS difference of the texture and its 3-px shift over the same pixels
    m = (uj >= 0.5) & (uj <= W - 0.5)
    oracle = float(((tex(u, v) - tex(u + PERTURB_PX, v))[m] ** 2).mean().sqrt())
    assert oracle > 0.1
    assert abs(bad["rmse"] - oracle) < INTERP_TOL


def test_occlusion_excludes_exactly_the_occluded_pixels():
    ci, cj = cam_at(0.0), cam_at(TX)
    u, v = M.pixel_grid(H, W)
    FRONT_COLS = 20  # in view j an occluder at depth 2 covers columns 0..19
    depth_i, alpha = torch.full((H, W), Z), torch.ones(H, W)
    img_i = tex(u, v)
    img_j = tex(u + SHIFT, v)
    front = u < FRONT_COLS
    img_j[front] = torch.tensor([1.0, 0.0, 0.0], dtype=img_j.dtype)
    depth_j = torch.where(front, torch.full_like(depth_i, 2.0), depth_i)
    r = M.consistency(img_i, depth_i, alpha, ci, img_j, depth_j, alpha, cj, return_mask=True)
    uj = u - SHIFT
    oracle = (uj >= FRONT_COLS) & (uj <= W - 0.5)  # visible in j: lands behind no occluder, inside the view
    assert torch.equal(r["mask"], oracle)
    assert r["rmse"] < INTERP_TOL
    # without the depth test the occluder's red is compared against the texture: a large error
    r_no = M.consistency(img_i, depth_i, alpha, ci, img_j, depth_j, alpha, cj, rel_tol=math.inf)
    assert r_no["valid"] > r["valid"] and r_no["rmse"] > 0.2


def test_uncovered_pixels_are_not_reprojected():
    ci, cj = cam_at(0.0), cam_at(TX)
    u, v = M.pixel_grid(H, W)
    depth, alpha = torch.full((H, W), Z), torch.ones(H, W)
    alpha_i = alpha.clone()
    alpha_i[:, 40:] = 0.3  # below ALPHA_MIN: no surface there
    r = M.consistency(tex(u, v), depth, alpha_i, ci, tex(u + SHIFT, v), depth, alpha, cj, return_mask=True)
    assert not r["mask"][:, 40:].any() and r["covered"] == 40 * H


def plane_scene(dx=0.0):
    """A textured plane of small opaque Gaussians at z = Z facing the cameras (spacing half a pixel)."""
    s = 0.04
    xs = torch.arange(-3.2, 3.2, s, dtype=torch.float64)
    ys = torch.arange(-2.4, 2.4, s, dtype=torch.float64)
    X, Y = torch.meshgrid(xs, ys, indexing="xy")
    X, Y = X.reshape(-1), Y.reshape(-1)
    n = X.numel()
    # texture in plane units: wavelength LAM px at depth Z is LAM·Z/F_PX m; color follows the point, shifted
    # by dx (a "perturbed" scene moves the texture, not the geometry)
    u = (X + dx) * F_PX / Z + W / 2
    v = Y * F_PX / Z + H / 2
    rgb = tex(u, v)
    means = torch.stack([X, Y, torch.full_like(X, Z)], -1)
    quats = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(n, 4).clone()
    ls = torch.log(torch.tensor([s, s, s * 0.1], dtype=torch.float64)).expand(n, 3).clone()
    op = torch.full((n,), math.log(0.95 / 0.05), dtype=torch.float64)
    sh = ((rgb - 0.5) / SH_C0).unsqueeze(1)
    return Gaussians(means.float(), quats.float(), ls.float(), op.float(), sh.float())


def test_rendered_plane_consistent_and_perturbed_view_detected():
    g = plane_scene()
    views = M.render_views(g, [cam_at(0.0), cam_at(TX)])
    a, b = views
    assert torch.allclose(a["depth"][a["alpha"] > 0.5].double(), torch.tensor(Z, dtype=torch.float64), rtol=1e-4)
    good = M.consistency(a["color"], a["depth"], a["alpha"], a["camera"], b["color"], b["depth"], b["alpha"],
                         b["camera"])
    assert good["valid"] > 0.8 * (W - SHIFT) * H
    assert good["rmse"] < RENDER_TOL
    shifted = M.render_views(plane_scene(dx=PERTURB_PX * Z / F_PX), [cam_at(TX)])[0]
    bad = M.consistency(a["color"], a["depth"], a["alpha"], a["camera"], shifted["color"], shifted["depth"],
                        shifted["alpha"], shifted["camera"])
    assert bad["rmse"] > 4 * RENDER_TOL
    mv = M.multiview_consistency([a, b, shifted], ks=(1, 2))
    assert mv["k1"]["pairs"] == 2 and mv["k2"]["pairs"] == 1
    assert abs(mv["k2"]["rmse"] - M.consistency(a["color"], a["depth"], a["alpha"], a["camera"], shifted["color"],
                                                shifted["depth"], shifted["alpha"], shifted["camera"])["rmse"]) < 1e-12


def test_flow_alignment_of_painting_with_itself_is_one():
    from tlvg_warp.io.demo import builtin_painting
    from tlvg_warp.losses.vgg import resize_style

    p = resize_style(builtin_painting().numpy())
    score = M.flow_alignment(p, M.painting_field(p))
    assert abs(score - 1.0) < 1e-5  # Σ|d|² / Σ|d||d| = 1 exactly up to float32 round-off
    # rotated 90°: the render's strokes run across the target's, cos 2(φ−φ*) = −1 where both are coherent
    rot = np.ascontiguousarray(np.rot90(p))
    assert M.flow_alignment(rot, M.painting_field(p)) < 0.2


def test_vgg_distances_zero_for_identical_and_positive_otherwise():
    from tlvg_warp.losses.vgg import load_vgg

    net = load_vgg("random")
    u, v = M.pixel_grid(H, W)
    img = tex(u, v).float()
    sf = M.style_target_feats(net, img.numpy())
    # resize_style brings the "painting" to height 256 while the view is scaled x0.5 to 24 rows: different
    # sizes, so only the content distance (same size, same image) is an exact zero
    d = M.vgg_distances(net, img, img, sf)
    assert d["content"] == 0.0
    other = torch.flip(img, [1])
    d2 = M.vgg_distances(net, other, img, sf)
    assert d2["content"] > 0
    # the painting's own features at the render's size: Gram distance 0 for the same image, not for another
    from tlvg_warp.losses.vgg import flatten_feats

    with torch.no_grad():
        own = flatten_feats(net(img, 0.5))
    assert M.vgg_distances(net, img, img, own)["style_gram"] < 1e-12
    assert M.vgg_distances(net, torch.rand_like(img), img, own)["style_gram"] > 1e-6
    small = M.vgg_distances(net, img[:6, :8], img[:6, :8], sf)  # 8x6: too small at x0.5, measured at x1
    assert small["content"] == 0.0 and small["style_gram"] is not None
    tiny = M.vgg_distances(net, img[:3, :3], img[:3, :3], sf)  # VGG's two 2x2 pools need at least 4 px
    assert tiny == {"style_fast": None, "style_gram": None, "content": None}
