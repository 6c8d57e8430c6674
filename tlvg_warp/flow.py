"""Flow guidance on the Gaussians (SPEC §3): the alignment energy of paper eq. 1 and the anisotropy energy,
weighted by target coherence × each Gaussian's blend weight in the view, normalized.

``flow_terms`` runs two Warp kernels (kernels/flow.py) inside one torch autograd Function (``FlowEnergiesFn`` of
tlvg_warp.autograd, re-exported here with ``FlowTermsFn``): the targets (projected center, bilinear field sample with
border padding, coherence, weight; no gradient) and the energies, then one matrix-vector product for the weighted
means: about ten kernel launches per call where the torch-side targets and weighting took ~60 (the stylize loop is
bound by kernel launches). ``flow_targets`` and ``flow_terms_reference`` are the pure-torch twins (same signatures)
the tests compare with."""
import torch
import torch.nn.functional as F

from .autograd import FlowEnergiesFn, FlowTermsFn  # noqa: F401 (re-exported: they lived here)
from .kernels.flow import COHERENCE_MIN
from .reference import project_reference
from .types import Camera, Gaussians


def flow_targets(g: Gaussians, cam: Camera, field: torch.Tensor):
    """Per Gaussian: target (cos 2θ, sin 2θ) at its projected center, the field's coherence there, and
    where the term applies. ``field`` is the view's doubled-angle field [H, W, ≥2] (c·cos 2θ, c·sin 2θ, ...)."""
    with torch.no_grad():
        R = cam.R.to(g.means)
        p = g.means @ R.T + cam.t.to(g.means)  # [N, 3]
        z = p[:, 2]
        zs = torch.where(z > cam.near, z, torch.ones_like(z))
        u = cam.fx * p[:, 0] / zs + cam.cx
        v = cam.fy * p[:, 1] / zs + cam.cy
        # grid_sample with align_corners=False puts pixel centers at +0.5, as the rasterizer does
        grid = torch.stack([2 * u / cam.width - 1, 2 * v / cam.height - 1], -1)[None, :, None]  # [1, N, 1, 2]
        f = field[..., :2].permute(2, 0, 1)[None].to(g.means)  # [1, 2, H, W]
        vec = F.grid_sample(f, grid, mode="bilinear", align_corners=False, padding_mode="border")[0, :, :, 0].T
        coh = vec.norm(dim=1)  # [N] averaging disagreeing directions lowers the coherence, as it should
        target = vec / coh.clamp_min(1e-12)[:, None]
        inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height) & (z > cam.near)
        active = inside & (coh > COHERENCE_MIN) & torch.isfinite(g.means).all(1) & torch.isfinite(g.log_scales).all(1)
    return target, torch.where(active, coh, torch.zeros_like(coh)), active


def _combine(align_i, aniso_i, coh, weights, active):
    w = (coh * weights.detach().to(coh) * active).clamp_min(0)  # [N]
    w = w / w.sum().clamp_min(1e-12)
    return (w * align_i).sum(), (w * aniso_i).sum()


def flow_terms(g: Gaussians, cam: Camera, field: torch.Tensor, weights: torch.Tensor):
    """(alignment energy, anisotropy energy) of ``g`` in view ``cam`` against the view's target ``field``
    [H, W, ≥2]; ``weights`` [N] is Σ αT per Gaussian from ``render(..., return_weights=True)``."""
    e = FlowEnergiesFn.apply(g.means, g.quats, g.log_scales, weights, field, cam)
    return e[0], e[1]


def flow_terms_unfused(g: Gaussians, cam: Camera, field: torch.Tensor, weights: torch.Tensor):
    """``flow_terms`` as it was before the fused version: torch targets, per-Gaussian Warp energies, torch weighting
    (kept for the tests and the loss microbenchmark)."""
    target, coh, active = flow_targets(g, cam, field)
    align_i, aniso_i = FlowTermsFn.apply(g.means, g.quats, g.log_scales, target.contiguous(), active, cam)
    return _combine(align_i, aniso_i, coh, weights, active)


def flow_terms_reference(g: Gaussians, cam: Camera, field: torch.Tensor, weights: torch.Tensor):
    """Pure-torch twin of ``flow_terms``: eigen-decomposes Σ2D explicitly instead of the doubled-angle form."""
    target, coh, active = flow_targets(g, cam, field)
    cov = project_reference(g, cam).cov2d  # [N, 3] zero where culled
    S = torch.stack([cov[:, 0], cov[:, 1], cov[:, 1], cov[:, 2]], -1).reshape(-1, 2, 2)
    S = torch.where(active[:, None, None], S, torch.eye(2, dtype=S.dtype, device=S.device) * torch.tensor([2.0, 1.0]).to(S))
    evals, evecs = torch.linalg.eigh(S)  # ascending
    major = evecs[:, :, 1]  # [N, 2]
    theta = 0.5 * torch.atan2(target[:, 1], target[:, 0])
    t = torch.stack([torch.cos(theta), torch.sin(theta)], -1)
    n = torch.stack([-t[:, 1], t[:, 0]], -1)
    align_i = 1 - (major * t).sum(1).abs()
    quad = lambda x: torch.einsum("ni,nij,nj->n", x, S, x)  # noqa: E731
    aniso_i = quad(n) / quad(t) + evals[:, 0] / evals[:, 1]
    zero = torch.zeros_like(align_i)
    return _combine(torch.where(active, align_i, zero), torch.where(active, aniso_i, zero), coh, weights, active)
