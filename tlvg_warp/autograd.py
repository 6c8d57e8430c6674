"""The raster layer's torch autograd Functions: ``ShadeFn`` (SH colours) and ``RasterizeFn`` (projection, binning,
blending), over the stages of ``raster`` launched through ``launch``, and the flow energies on the Gaussians
(``FlowEnergiesFn``, fused, and ``FlowTermsFn``, per Gaussian; tlvg_warp.flow calls them). Gradients: the blending
and SH backwards are hand-written; the projection's adjoint is Warp-generated, launched by hand with the
torch-allocated gradient buffers as its adjoint arguments (``raster.project_adjoint``): no wp.Tape and no wp.array
per render."""
from __future__ import annotations

import torch
import warp as wp

from .kernels.flow import COHERENCE_MIN, flow_targets_kernel
from .launch import ct, ct_at, fast_launch, input_ct, kernels_for, to_warp, warp_on
from .raster import (blend, blend_backward, camera_arg, count_intersections, no_grad_camera, packed_zeros, project,
                     project_adjoint, zero_upstream)


class ShadeFn(torch.autograd.Function):
    """(means, sh) -> colors [N, 3] = max(SH up to ``degree`` (view direction from the camera center) + 0.5, 0),
    for every Gaussian (a culled one's color is never blended).

    Its own op, before the raster op (gsplat's stage split): autograd runs its backward after the raster op's,
    when the image gradient and the raster state are gone, so the SH coefficients' gradient (48 floats a Gaussian at
    degree 3, the largest buffer of a backward) never coexists with them. Backward by hand: the direction part of
    dL/dmeans and the coefficient gradients (Warp's generated adjoint would add atomically per coefficient read)."""

    @staticmethod
    def forward(ctx, means, sh, cam_arg, degree: int):
        K = kernels_for(means.dtype)
        device, n = means.device, means.shape[0]
        colors = torch.empty(n, 3, dtype=means.dtype, device=device)
        with warp_on(device) as wdev:
            fast_launch(K.sh_color, 3 * n, [input_ct(means, K.vec3), input_ct(sh, None), cam_arg, (degree + 1) ** 2,
                                            ct(colors.view(-1))], wdev)
        ctx.save_for_backward(means, sh)
        ctx.cam_arg, ctx.degree = cam_arg, degree
        return colors

    @staticmethod
    def backward(ctx, g_colors):
        means, sh = ctx.saved_tensors
        K = kernels_for(means.dtype)
        device, n = means.device, means.shape[0]
        n_coeffs = (ctx.degree + 1) ** 2
        g_means = torch.empty_like(means)  # sh_backward stores every row (0 where dL/dcolor is 0)
        g_rgb = torch.empty(n, 3, dtype=means.dtype, device=device)  # dL/d(SH sum), the clamp applied
        g_sh = torch.empty_like(sh) if n_coeffs == sh.shape[1] else torch.zeros_like(sh)  # degree < stored: rest 0
        with warp_on(device) as wdev:
            m = input_ct(means, K.vec3)
            rgb = ct(g_rgb, K.vec3)
            fast_launch(K.sh_backward, n, [m, input_ct(sh, K.vec3), ctx.cam_arg, ctx.degree,
                                           ct(g_colors.contiguous(), K.vec3), rgb, ct(g_means, K.vec3)], wdev)
            fast_launch(K.sh_coeff_grad, n * n_coeffs, [m, ctx.cam_arg, n_coeffs, rgb, ct(g_sh, K.vec3)], wdev)
        return g_means, g_sh, None, None


class RasterizeFn(torch.autograd.Function):
    """(means, quats, log_scales, opacity_logits, colors, means2d_probe) -> color, alpha, depth, radii, weights.

    ``colors`` [N, 3] come from ``ShadeFn``; ``means2d_probe`` is a zero tensor whose gradient receives dL/d(screen
    mean) for density control.

    The backward runs the blending backward and the projection's Warp-generated adjoint, on array descriptors (no
    wp.Tape, no wp.array per render). Memory: the binning and per-pixel state (sorted ids, T, last) are dropped
    after the blending backward, before the input gradients are allocated, and the projection when the op returns;
    the backward's peak is ShadeFn's, after all of these are gone. A second backward through the same graph
    (retain_graph, gradcheck) rebuilds what the first freed (projection, binning) from the saved inputs."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, colors, means2d_probe, cam, cam_arg, settings):
        K = kernels_for(means.dtype)
        device, n = means.device, means.shape[0]
        with warp_on(device):
            args = [input_ct(t, ty) for t, ty in zip((means, quats, log_scales, opacity_logits),
                                                      (K.vec3, K.vec4, K.vec3, None))] + [ct(colors, K.vec3)]
            pr = project(K, args, colors, cam_arg, n, means.dtype, device)
            budget, key = settings.get("budget"), settings.get("budget_key")  # (IntersectionBudget, view)
            cap = budget.capacity(key, n) if budget is not None else None
            order = count_intersections(K, pr, cam.width, cam.height, settings["all_tiles"], capacity=cap)
            if budget is not None:
                budget.observe(key, n, order)
            color, alpha, depth, weights, first = blend(K, pr, order, cam, settings)
        ctx.state = {"proj": pr, "blend": first, "n": n, "dtype": means.dtype, "device": device, "args": args,
                     "cam": cam, "cam_arg": cam_arg, "settings": settings}
        # the inputs are read by the adjoints: saving them lets autograd refuse a backward after an in-place
        # change (torch's version counter) instead of returning stale gradients
        ctx.save_for_backward(means, quats, log_scales, opacity_logits, colors)
        ctx.mark_non_differentiable(pr.radii, weights)
        # an output without a gradient (the alpha of a colour loss, the radii) reaches the backward as None, which it
        # reads as kept broadcast zeros: autograd would allocate and memset an [H, W] and an [N] zero per backward
        ctx.set_materialize_grads(False)
        return color, alpha, depth, pr.radii, weights if settings["weights"] else None  # depth None if not asked

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, _g_radii, _g_weights):
        state = ctx.state
        args, cam, cam_arg, settings = (state[k] for k in ("args", "cam", "cam_arg", "settings"))
        n, dtype, device = state["n"], state["dtype"], state["device"]
        K = kernels_for(dtype)
        H, W = cam.height, cam.width
        with warp_on(device) as wdev:
            pr, st = state.pop("proj", None), state.pop("blend", None)
            if pr is None:  # a second backward through the same graph: the first freed the projection and binning
                pr = project(K, args, ctx.saved_tensors[4], cam_arg, n, dtype, device)
                st = blend(K, pr, count_intersections(K, pr, W, H, settings["all_tiles"]), cam, settings)[4]
            # gradient buffers exist only from here on (fresh per call, so a second backward through the same
            # graph, e.g. gradcheck or retain_graph, never sees the first call's sums). What outlives this op (the
            # probe's dL/d(screen mean), dL/dcolor for ShadeFn, dL/dmeans until ShadeFn adds its part) shares one
            # buffer; the geometric gradients go with this op, the other inputs' once autograd has accumulated them
            kept_flat = torch.zeros(8 * n, dtype=dtype, device=device)  # [means2d (N, 2) | color (N, 3) | means (N, 3)]
            geo_flat = torch.zeros(5 * n, dtype=dtype, device=device)  # [conic (N, 3) | opacity (N) | depth (N)]
            ups = [g.contiguous() if g is not None else zero_upstream(shape, dtype, device)
                   for g, shape in ((g_color, (H, W, 3)), (g_alpha, (H, W)), (g_depth, (H, W)))]
            # the blending backward first: the GPU waits on its enqueue, so everything else of the host's part comes
            # after it (the sorted ids, T and last go when this block ends: stream-ordered, safe with it queued)
            blend_backward(K, st, [ct(ups[0], K.vec3), ct(ups[1]), ct(ups[2])], [kept_flat, geo_flat], wdev)
            inputs = ctx.saved_tensors  # (raises if an input changed in place since the forward)
            pouts = pr.outs
            del st, ups, pr
            e = kept_flat.element_size()
            g_means2d, g_rgb = kept_flat[:2 * n].view(n, 2), kept_flat[2 * n:5 * n].view(n, 3)
            grads = [kept_flat[5 * n:].view(n, 3)] + packed_zeros([t.shape for t in inputs[1:4]], dtype, device)
            project_adjoint(K, args, pouts, grads, (ct_at(kept_flat, 0, (n,), e, 2), ct_at(geo_flat, 0, (n,), e, 3),
                                                     ct_at(geo_flat, 4 * n * e, (n,), e),
                                                     ct_at(geo_flat, 3 * n * e, (n,), e)), cam_arg, n, device)
        return (*grads, g_rgb, g_means2d, None, None, None)


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
