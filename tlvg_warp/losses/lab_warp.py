"""The Lab chroma statistics loss as two Warp kernels (the stylize loop is bound by the host's kernel
launches; through torch this loss took ~50 launches per step, here ~8).

Forward: one kernel per pixel computes Lab (a, b) and their 2x3 Jacobian with respect to the sRGB input (the same
formulas and branches as color.rgb_to_lab: sRGB gamma with its linear toe, D65 white, the CIE cube root with its
linear segment); torch reduces (a, b) to mean and population standard deviation. Backward: one kernel per pixel
maps the loss gradient through the statistics and the stored Jacobian back to sRGB. The kernels are
kernels/lab.py's."""
import torch

from ..kernels.lab import lab_kernels
from ..launch import ct, fast_launch, init_warp, warp_on


def _kernels(dtype: torch.dtype):
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"Lab kernels take float32 or float64, got {dtype}")
    init_warp()
    return lab_kernels("float32" if dtype == torch.float32 else "float64")


def lab_ab_jacobian(rgb: torch.Tensor) -> torch.Tensor:
    """[N,8] per pixel of rgb [...,3]: (a, b, ∂a/∂rgb, ∂b/∂rgb), no autograd."""
    x = rgb.detach().reshape(-1, 3)
    x = x if x.is_contiguous() else x.contiguous()
    K = _kernels(x.dtype)
    out = torch.empty(x.shape[0], 8, dtype=x.dtype, device=x.device)
    if x.shape[0]:
        with warp_on(x.device) as wdev:
            fast_launch(K.forward, x.shape[0], [ct(x, K.vec3), ct(out, K.vec8)], wdev)
    return out


def chroma_stats_of(out: torch.Tensor) -> torch.Tensor:
    """[4] = (μ_a, μ_b, σ_a, σ_b) (population σ) of ``lab_ab_jacobian``'s output."""
    sd, mu = torch.std_mean(out[:, :2], dim=0, correction=0)
    return torch.cat([mu, sd])


class LabChromaLossFn(torch.autograd.Function):
    """½(‖Δμ_ab‖₁ + ‖Δσ_ab‖₁) of an sRGB render [...,3] against target statistics [4] (constant)."""

    @staticmethod
    def forward(ctx, rgb, target_stats):
        out = lab_ab_jacobian(rgb)
        stats = chroma_stats_of(out)
        t = target_stats.to(stats).reshape(4).contiguous()
        ctx.save_for_backward(out, stats, t)
        ctx.shape = rgb.shape
        return 0.5 * torch.linalg.vector_norm(stats - t, ord=1)

    @staticmethod
    def backward(ctx, g):
        out, stats, t = ctx.saved_tensors
        K = _kernels(out.dtype)
        n = out.shape[0]
        grad = torch.empty(n, 3, dtype=out.dtype, device=out.device)
        gs = g.reshape(1).to(out.dtype).contiguous()
        if n:
            with warp_on(out.device) as wdev:
                fast_launch(K.backward, n, [ct(out, K.vec8), ct(stats), ct(t), ct(gs), n, ct(grad, K.vec3)], wdev)
        return grad.reshape(ctx.shape), None
