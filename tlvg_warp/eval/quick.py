"""Quick gauges for the stability suite (eval/stability.py): NOT a ruler for ranking methods (they score a run
against its own stored target field and drop pixels that fail the depth test); `evaluate` uses eval/metrics.py.

Original notes:

Multi-view consistency: view i's pixels (alpha > 0.5) are lifted with its rendered expected depth, moved
into view j with the known poses, projected, and tested against view j's own rendered depth (a pixel whose
reprojected depth differs from what j sees there by more than DEPTH_REL_TOL is occluded in j, or off a
silhouette, and is left out). The stylized color of j is sampled bilinearly at the reprojected point and
the masked RMSE against view i's color is the consistency error (0 = perfectly consistent).

Style distance (FAST and Gram in VGG relu3 space vs the painting), content distance (relu3 MSE vs the
un-stylized render of the same view), flow-alignment score per view against the painting's stroke field
mapped "canvas" onto the view (or the run's stored target field), Gaussian count and bytes.
All per-pixel work is vectorized torch / numpy.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..losses.stroke_field import flow_alignment_score, map_field_canvas, stroke_field
from ..losses.style import content_loss, fast_loss, gram_loss
from ..losses.vgg import flatten_feats, resize_style
from ..renderer import render
from ..types import Camera

ALPHA_MIN = 0.5  # a pixel is "covered" (has a surface to reproject) when its alpha is at least this
# Relative depth tolerance of the occlusion test. Expected depth blends a few Gaussians across the surface
# thickness; on the demo scene (discs ~0.6 x spacing, thin ~0.12 x spacing, views 2.6 m away) neighbouring
# views agree to < 1 %, while an occluder in front of a surface differs by far more than 3 % (10 cm at 3 m).
DEPTH_REL_TOL = 0.03
SHORT_K, LONG_K = 1, 5  # SPEC §4: view pairs (i, i+1) and (i, i+5)


def _t(x, dtype=torch.float64):
    return x.detach().to(dtype) if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x), dtype=dtype)


def pixel_grid(h: int, w: int, dtype=torch.float64, device="cpu"):
    """Pixel-center coordinates (u = col + 0.5, v = row + 0.5), each [H,W] (SPEC §1)."""
    v, u = torch.meshgrid(torch.arange(h, dtype=dtype, device=device) + 0.5,
                          torch.arange(w, dtype=dtype, device=device) + 0.5, indexing="ij")
    return u, v


def reproject(depth_i, cam_i: Camera, cam_j: Camera):
    """Lift every pixel of view i with its z-depth [H,W] and project it into view j.
    Returns (u_j [H,W], v_j [H,W], z_j [H,W]) in view j's pixel coordinates (pixel centers at +0.5)."""
    d = _t(depth_i)
    u, v = pixel_grid(cam_i.height, cam_i.width, device=d.device)
    x = torch.stack([(u - cam_i.cx) / cam_i.fx * d, (v - cam_i.cy) / cam_i.fy * d, d], -1)  # [H,W,3] camera i
    Ri, ti = cam_i.R.to(d), cam_i.t.to(d)
    Rj, tj = cam_j.R.to(d), cam_j.t.to(d)
    world = (x - ti) @ Ri  # R^T (x - t), row vectors
    xj = world @ Rj.T + tj
    z = xj[..., 2]
    zs = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    return cam_j.fx * xj[..., 0] / zs + cam_j.cx, cam_j.fy * xj[..., 1] / zs + cam_j.cy, z


def _sample(img, u, v, mode):
    """Sample an [H,W] or [H,W,C] image at pixel coordinates u, v [H',W'] (bilinear or nearest)."""
    x = _t(img)
    chw = x.unsqueeze(0) if x.dim() == 2 else x.permute(2, 0, 1)
    h, w = chw.shape[-2:]
    grid = torch.stack([2.0 * u / w - 1.0, 2.0 * v / h - 1.0], -1).unsqueeze(0).to(chw)  # align_corners=False
    out = F.grid_sample(chw.unsqueeze(0), grid, mode=mode, padding_mode="border", align_corners=False)[0]
    return out[0] if x.dim() == 2 else out.permute(1, 2, 0)


def consistency(color_i, depth_i, alpha_i, cam_i: Camera, color_j, depth_j, alpha_j, cam_j: Camera,
                rel_tol: float = DEPTH_REL_TOL, return_mask: bool = False):
    """Masked RMSE of view i's colors against view j's colors at the reprojected points.

    Valid pixels: covered in i (alpha >= ALPHA_MIN), in front of camera j, inside view j (pixel centers
    between the first and last pixel center, so bilinear sampling never reads the border), covered in j
    at the nearest pixel, and passing the depth test |z_j − D_j| <= rel_tol · z_j (nearest-pixel depth: a
    bilinear depth would blend across an occlusion edge). Returns {"rmse", "valid", "covered"}:
    rmse None when no pixel is valid; valid/covered pixel counts."""
    ci, cj = _t(color_i), _t(color_j)
    ai, aj, dj = _t(alpha_i), _t(alpha_j), _t(depth_j)
    uj, vj, zj = reproject(depth_i, cam_i, cam_j)
    covered = ai >= ALPHA_MIN
    inside = (uj >= 0.5) & (uj <= cam_j.width - 0.5) & (vj >= 0.5) & (vj <= cam_j.height - 0.5)
    mask = covered & (zj > cam_j.near) & inside
    d_near = _sample(dj, uj, vj, "nearest")
    a_near = _sample(aj, uj, vj, "nearest")
    mask &= (a_near >= ALPHA_MIN) & ((zj - d_near).abs() <= rel_tol * zj.abs())
    n = int(mask.sum())
    out = {"rmse": None, "valid": n, "covered": int(covered.sum())}
    if n:
        cs = _sample(cj, uj, vj, "bilinear")
        out["rmse"] = float(((cs - ci)[mask] ** 2).mean().sqrt())
    if return_mask:
        out["mask"] = mask
    return out


def multiview_consistency(views, ks=(SHORT_K, LONG_K), rel_tol: float = DEPTH_REL_TOL) -> dict:
    """views: list of dicts {"color","depth","alpha","camera"} in capture order. For each k, the mean over
    pairs (i, i+k) of the masked RMSE, weighted by valid pixel count (so a pair that barely overlaps counts
    little); None when no pair has a valid pixel. Returns {"k1": {...}, "k5": {...}}."""
    out = {}
    for k in ks:
        pairs = []
        for i in range(len(views) - k):
            a, b = views[i], views[i + k]
            r = consistency(a["color"], a["depth"], a["alpha"], a["camera"],
                            b["color"], b["depth"], b["alpha"], b["camera"], rel_tol)
            pairs.append({"i": i, "j": i + k, **r})
        good = [p for p in pairs if p["rmse"] is not None]
        n = sum(p["valid"] for p in good)
        rmse = math.sqrt(sum(p["rmse"] ** 2 * p["valid"] for p in good) / n) if n else None
        out[f"k{k}"] = {"rmse": rmse, "pairs": len(pairs), "valid_pixels": n, "per_pair": pairs}
    return out


# ---------------------------------------------------------------- VGG-space distances
def style_target_feats(net, painting) -> torch.Tensor:
    """The painting's relu3 features [C, Ns] (resized to height 256, SPEC §3)."""
    p = painting.detach().cpu().numpy() if isinstance(painting, torch.Tensor) else np.asarray(painting)
    dev = next(net.parameters()).device
    with torch.no_grad():
        return flatten_feats(net(torch.from_numpy(resize_style(p)).to(dev), 1.0))


def vgg_distances(net, stylized, original=None, style_feats=None, scale: float = 0.5) -> dict:
    """FAST and Gram style distance of a stylized view [H,W,3] to the painting features, and content
    distance (relu3 MSE) to the un-stylized render. Render scale 0.5 as in training (SPEC §3); a view too
    small for VGG (under 4 px after scaling) gives None rather than a crash."""
    h, w = stylized.shape[:2]
    s = scale if min(h, w) * scale >= 4 else 1.0
    out = {"style_fast": None, "style_gram": None, "content": None}
    if min(h, w) * s < 4:
        return out
    dev = next(net.parameters()).device
    with torch.no_grad():
        fa = net(_t(stylized, torch.float32).to(dev), s)
        if style_feats is not None:
            a = flatten_feats(fa)
            out["style_fast"] = float(fast_loss(a, style_feats))
            out["style_gram"] = float(gram_loss(a, style_feats))
        if original is not None:
            out["content"] = float(content_loss(fa, net(_t(original, torch.float32).to(dev), s)))
    return out


def painting_field(painting) -> np.ndarray:
    """The painting's doubled-angle stroke field at its VGG working size (height 256), [h,w,2]."""
    p = painting.detach().cpu().numpy() if isinstance(painting, torch.Tensor) else np.asarray(painting)
    return stroke_field(resize_style(p))[2]


def flow_alignment(stylized, painting_doubled=None, target_doubled=None) -> float:
    """Flow-alignment score (SPEC §4) of one view: against the stored target field [H,W,2] when given,
    else the painting's field mapped "canvas" onto the view."""
    h, w = stylized.shape[:2]
    if target_doubled is None:
        target_doubled = map_field_canvas(painting_doubled, h, w)[2]
    return flow_alignment_score(stylized, target_doubled)


def nan_count(*tensors) -> int:
    return int(sum(int((~torch.isfinite(_t(x))).sum()) for x in tensors if x is not None))


def mean_or_none(values):
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else None


# ---------------------------------------------------------------- everything for one scene
def render_views(g, cameras, background=None) -> list[dict]:
    """Render ``g`` from each camera: [{"color","depth","alpha","camera"}] (detached, CPU)."""
    out = []
    with torch.no_grad():
        for cam in cameras:
            r = render(g, cam, background)
            out.append({"color": r.color.detach().cpu(), "depth": r.depth.detach().cpu(),
                        "alpha": r.alpha.detach().cpu(), "camera": cam})
    return out


def scene_metrics(views, painting, net=None, originals=None, targets=None, ks=(SHORT_K, LONG_K),
                  rel_tol: float = DEPTH_REL_TOL, colors=None, style_feats=None) -> dict:
    """All SPEC §4 image metrics of one stylized scene.

    views: render_views() output of the stylized scene; painting [h,w,3] in [0,1]; net: VGG (None skips
    the VGG distances); originals: un-stylized colors per view (content distance); targets: stored target
    doubled-angle fields per view (None entries fall back to the canvas mapping); colors: the images the
    per-view metrics are measured on (default the renders' colors; consistency always uses the renders);
    style_feats: the painting's features when already computed (style_target_feats).
    Returns {"summary": {...}, "per_view": [...], "consistency": {...}}."""
    pd = painting_field(painting)
    sf = style_feats if style_feats is not None or net is None else style_target_feats(net, painting)
    per_view = []
    for n, v in enumerate(views):
        img = v["color"] if colors is None or colors[n] is None else colors[n]
        row = {"flow_alignment": flow_alignment(img, pd, None if targets is None else targets[n]),
               "nan": nan_count(v["color"], v["depth"], v["alpha"])}
        if net is not None:
            row |= vgg_distances(net, img, None if originals is None else originals[n], sf)
        per_view.append(row)
    cons = multiview_consistency(views, ks, rel_tol)
    summary = {k: mean_or_none([r.get(k) for r in per_view])
               for k in ("flow_alignment", "style_fast", "style_gram", "content")}
    for k in ks:
        summary[f"consistency_k{k}"] = cons[f"k{k}"]["rmse"]
    summary["nan"] = sum(r["nan"] for r in per_view)
    return {"summary": summary, "per_view": per_view, "consistency": cons}
