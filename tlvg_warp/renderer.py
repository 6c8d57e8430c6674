"""The public rasterizer: ``render(gaussians, camera, background=None) -> RenderOutput`` (SPEC §2)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .errors import InputError
from .types import Camera, Gaussians


@dataclass
class RenderOutput:
    color: torch.Tensor  # [H, W, 3]
    alpha: torch.Tensor  # [H, W]
    depth: torch.Tensor | None  # [H, W] expected depth Σ zαT / alpha, 0 where alpha is 0 (None: depth=False)
    radii: torch.Tensor  # [N] int32 screen radius in pixels, 0 = culled
    means2d: torch.Tensor  # [N, 2] zero probe (read-only broadcast); after backward its .grad is dL/d(screen mean)
    weights: torch.Tensor | None = None  # [N] Σ_pixels αT per Gaussian (when asked for)

    @property
    def visible(self) -> torch.Tensor:  # [N] bool
        return self.radii > 0


def check_inputs(g: Gaussians, cam: Camera, background) -> tuple:
    if not isinstance(g, Gaussians):
        raise InputError(f"render expects Gaussians, got {type(g).__name__}")
    if not isinstance(cam, Camera):
        raise InputError(f"render expects a Camera, got {type(cam).__name__}")
    g.validate()  # tensors may have been swapped since construction
    if not all(math.isfinite(v) for row in cam.world_to_camera.tolist() for v in row):
        raise InputError("camera world_to_camera has non-finite values")
    if cam.width <= 0 or cam.height <= 0:
        raise InputError(f"camera image size must be positive, got {cam.width}x{cam.height}")
    if background is None:
        return (0.0, 0.0, 0.0)
    if type(background) in (tuple, list) and all(type(v) in (float, int) for v in background):
        vals = [float(v) for v in background]  # the training loops' case: no tensor round trip
    else:
        vals = torch.as_tensor(background, dtype=torch.float64).detach().flatten().cpu().tolist()
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise InputError(f"background must be 3 finite values, got {background!r}")
    return tuple(vals)


_zero_pairs: dict = {}


def _zero_pair(dtype, device) -> torch.Tensor:
    """A [1, 2] zero per (dtype, device), kept: the probe is a fresh leaf view of it per render (no allocation)."""
    key = (dtype, device)
    z = _zero_pairs.get(key)
    if z is None:
        z = _zero_pairs[key] = torch.zeros(1, 2, dtype=dtype, device=device)
    return z


def render(g: Gaussians, cam: Camera, background=None, *, sh_degree: int | None = None,
           return_weights: bool = False, all_tiles: bool = False, depth: bool = True, budget=None,
           budget_key=None) -> RenderOutput:
    """Rasterize ``g`` into ``cam`` on the device of ``g``'s tensors, differentiably.

    sh_degree: evaluate SH only up to this degree (default: all stored coefficients).
    return_weights: also return Σ αT per Gaussian (costs one atomic add per contribution).
    all_tiles: bin every visible Gaussian into every tile (the brute-force check of the binning).
    depth: also blend the expected depth (default); False skips it (``RenderOutput.depth`` is None), which
    saves a little blending time when a caller reads only color and alpha.
    budget, budget_key: a ``raster.IntersectionBudget`` and the view's key in it: the key buffers are sized from
    the view's last render instead of reading this one's count back (a training loop's renders; no host wait)."""
    # lazy: these import Warp, which this module does not need
    from .autograd import RasterizeFn, ShadeFn
    from .launch import kernels_for
    from .raster import camera_arg

    bg = check_inputs(g, cam, background)
    degree = g.sh_degree if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= g.sh_degree:
        raise InputError(f"sh_degree {degree} is outside 0..{g.sh_degree} (the stored degree)")
    # a stride-0 broadcast zero: an [N, 2] leaf that owns 2 scalars; its .grad is the [N, 2] gradient
    probe = _zero_pair(g.dtype, g.device).expand(g.num, 2).detach().requires_grad_(True)
    settings = {"background": bg, "weights": bool(return_weights), "all_tiles": bool(all_tiles),
                "depth": bool(depth), "budget": budget, "budget_key": budget_key}
    cam_arg = camera_arg(kernels_for(g.dtype), cam)  # the kernels' camera struct, built once for both ops
    colors = ShadeFn.apply(g.means, g.sh, cam_arg, degree)  # [N, 3]
    color, alpha, depth, radii, weights = RasterizeFn.apply(
        g.means, g.quats, g.log_scales, g.opacity_logits, colors, probe, cam, cam_arg, settings)
    return RenderOutput(color, alpha, depth, radii, probe, weights)
