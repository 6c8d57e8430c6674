"""Flow guidance on the Gaussians (SPEC §3): the alignment energy of paper eq. 1 and the anisotropy energy,
weighted by target coherence × each Gaussian's blend weight in the view, normalized.

``flow_terms`` runs two Warp kernels (kernels/flow.py) inside one torch autograd Function: the targets (projected
center, bilinear field sample with border padding, coherence, weight; no gradient) and the energies, then one
matrix-vector product for the weighted means: about ten kernel launches per call where the torch-side targets and
weighting took ~60 (the stylize loop is bound by kernel launches). ``flow_targets`` and ``flow_terms_reference`` are
the pure-torch twins (same signatures) the tests compare with."""
import torch
import torch.nn.functional as F
import warp as wp

from .kernels.flow import flow_targets_kernel
from .launch import ct, fast_launch, input_ct, kernels_for, to_warp, warp_on
from .raster import camera_arg, no_grad_camera
from .reference import project_reference
from .types import Camera, Gaussians

COHERENCE_MIN = 1e-3  # below this the painting has no direction to follow at that spot


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


class FlowTermsFn(torch.autograd.Function):
    """(means, quats, log_scales) -> per-Gaussian (align [N], aniso [N]) for fixed targets."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, target, active, cam):
        K = kernels_for(means.dtype)
        n = means.shape[0]
        grads = [torch.zeros_like(t) for t in (means, quats, log_scales)]
        align = torch.zeros(n, dtype=means.dtype, device=means.device)
        aniso = torch.zeros_like(align)
        with warp_on(means.device) as wdev:
            ins = [to_warp(means, K.vec3, grads[0]), to_warp(quats, K.vec4, grads[1]),
                   to_warp(log_scales, K.vec3, grads[2]), to_warp(target, K.vec2),
                   wp.from_torch(active.to(torch.int32).contiguous())]
            outs = [to_warp(align, K.scalar, torch.zeros_like(align)), to_warp(aniso, K.scalar, torch.zeros_like(aniso))]
            tape = wp.Tape()
            with tape:
                wp.launch(K.flow_terms, dim=n, inputs=ins + [camera_arg(K, cam)], outputs=outs, device=wdev)
        ctx.state = (tape, outs, grads, means.device)
        ctx.save_for_backward(means, quats, log_scales)  # autograd's in-place check on the inputs
        return align, aniso

    @staticmethod
    def backward(ctx, g_align, g_aniso):
        tape, outs, grads, device = ctx.state
        ctx.saved_tensors  # noqa: B018 (raises if an input changed in place since the forward)
        ctx.state = None
        for o, g in zip(outs, (g_align, g_aniso)):
            if g is not None:
                wp.to_torch(o.grad).copy_(g)
        with warp_on(device):
            tape.backward()
        return (*grads, None, None, None)


def _combine(align_i, aniso_i, coh, weights, active):
    w = (coh * weights.detach().to(coh) * active).clamp_min(0)  # [N]
    w = w / w.sum().clamp_min(1e-12)
    return (w * align_i).sum(), (w * aniso_i).sum()


class FlowEnergiesFn(torch.autograd.Function):
    """(means, quats, log_scales) -> (alignment, anisotropy) energies [2] of one view: Σ w_i e_i / Σ w_i with the
    targets and weights w_i = coherence x blend weight from the targets kernel (no gradient), e_i from the
    energies kernel. Backward: ∂E/∂e_i = g·w_i/Σw, then the energies kernel's Warp-generated adjoint, launched by
    hand with torch-allocated gradient buffers (as ``raster.project_adjoint``): no wp.Tape and no wp.array per call
    (a fern stylize step spent ~1 ms of host time building them)."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, weights, field, cam):
        K = kernels_for(means.dtype)
        T = flow_targets_kernel({torch.float32: "float32", torch.float64: "float64"}[means.dtype])
        n, dt, dev = means.shape[0], means.dtype, means.device
        e = torch.zeros(4, n, dtype=dt, device=dev)  # align, aniso (written where active), and their gradients
        target = torch.empty(n, 2, dtype=dt, device=dev)
        active = torch.empty(n, dtype=torch.int32, device=dev)
        w = torch.empty(n, dtype=dt, device=dev)
        fld = field if (field.dtype == dt and field.is_contiguous()) else field.to(dt).contiguous()
        wts = weights.detach()
        wts = wts if (wts.dtype == dt and wts.is_contiguous()) else wts.to(dt).contiguous()
        cam_arg = camera_arg(K, cam)
        args = [input_ct(means, K.vec3), input_ct(quats, K.vec4), input_ct(log_scales, K.vec3), ct(target, K.vec2),
                ct(active), cam_arg]
        with warp_on(dev) as wdev:
            fast_launch(T, n, [args[0], args[2], ct(wts), ct(fld), cam_arg, K.scalar(COHERENCE_MIN),
                               args[3], args[4], ct(w)], wdev)
            fast_launch(K.flow_terms, n, args + [ct(e[0]), ct(e[1])], wdev)
        inv = w.sum().clamp_min(1e-12).reciprocal()
        ctx.state = (args, e, w, inv)
        ctx.save_for_backward(means, quats, log_scales)  # autograd's in-place check on the inputs
        return torch.mv(e[:2], w) * inv

    @staticmethod
    def backward(ctx, g):
        args, e, w, inv = ctx.state
        means, quats, log_scales = ctx.saved_tensors  # (raises if an input changed in place since the forward)
        ctx.state = None
        K = kernels_for(means.dtype)
        n = means.shape[0]
        torch.outer(g * inv, w, out=e[2:])  # ∂E/∂align_i, ∂E/∂aniso_i: the adjoint's output gradients
        flat = torch.zeros(10 * n, dtype=means.dtype, device=means.device)  # the three input gradients, one memset
        grads = [flat[:3 * n].view(n, 3), flat[3 * n:7 * n].view(n, 4), flat[7 * n:].view(n, 3)]
        with warp_on(means.device) as wdev:
            fast_launch(K.flow_terms, n, args + [ct(e[0]), ct(e[1])], wdev,
                        adj_args=[ct(grads[0], K.vec3), ct(grads[1], K.vec4), ct(grads[2], K.vec3), None, None]
                        + [no_grad_camera(K), ct(e[2]), ct(e[3])])  # no gradient for the camera
        return (*grads, None, None, None)


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
