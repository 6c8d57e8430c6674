"""Warp kernels only (installed as ``tlvg_warp.kernels``); the ops that bridge them to torch live in
tlvg_warp.ops. Kernels of one scalar type share one Warp module, built once per process."""
import functools
import os
from types import SimpleNamespace

import warp as wp


def blend_min_blocks() -> tuple[int, int]:
    """Minimum resident 256-thread blocks per SM asked of the blending (forward, backward) kernels through
    __launch_bounds__ (0: the compiler's choice), which caps their registers at 65536 / (256 · blocks):
    ``TLVG_WARP_BLEND_BLOCKS=fwd,bwd`` overrides the default (for A/B runs on the GPU), as
    ``TLVG_WARP_BLEND_SLAB=scalar`` does the shared-memory layout of the blending batches (default "vector") and
    ``TLVG_WARP_BLEND_LOOP=for`` the forward's walk over a batch (default "while") and ``TLVG_WARP_BLEND_WARP=16x2``
    the pixels of one warp (default "8x4")."""
    v = os.environ.get("TLVG_WARP_BLEND_BLOCKS", "")
    if not v:
        return BLEND_MIN_BLOCKS
    f, b = (int(x) for x in v.split(","))
    return f, b


BLEND_MIN_BLOCKS = (0, 3)  # the backward: 2% faster on the H200 (A/B on a trained splat, two runs), same registers


@functools.lru_cache(maxsize=None)
def raster_kernels(scalar_name: str) -> SimpleNamespace:
    """All differentiable-pipeline kernels for ``"float32"`` or ``"float64"``."""
    from . import binning
    from .blend import make_blend
    from .flow import make_flow_terms
    from .projection import make_projection, module_name
    from .sh import make_sh

    scalar = {"float32": wp.float32, "float64": wp.float64}[scalar_name]
    if scalar == wp.float32 and os.environ.get("TLVG_WARP_FAST_MATH", "1") != "0":
        # CUDA fast math (approximate exp/div/sqrt, ~2 ulp, as gsplat builds with): float32 only, the float64
        # module stays the exact oracle; TLVG_WARP_FAST_MATH=0 turns it off. No effect on the CPU.
        wp.set_module_options({"fast_math": True}, module_name(scalar))
    project, ewa_cov2d = make_projection(scalar)
    sh_color, sh_backward, sh_coeff_grad = make_sh(scalar, module_name(scalar))
    flow_terms = make_flow_terms(scalar, module_name(scalar), ewa_cov2d)
    forward, backward = make_blend(scalar, module_name(scalar), blend_min_blocks(),
                                   os.environ.get("TLVG_WARP_BLEND_SLAB", "vector"),
                                   os.environ.get("TLVG_WARP_BLEND_LOOP", "while"),
                                   os.environ.get("TLVG_WARP_BLEND_WARP", "8x4"))
    return SimpleNamespace(
        scalar=scalar,
        vec2=wp.types.vector(2, scalar),
        vec3=wp.types.vector(3, scalar),
        vec4=wp.types.vector(4, scalar),
        mat33=wp.types.matrix((3, 3), scalar),
        project=project,
        sh_color=sh_color,
        sh_backward=sh_backward,
        sh_coeff_grad=sh_coeff_grad,
        flow_terms=flow_terms,
        blend_forward=forward,
        blend_backward=backward,
        count_tiles=binning.count_tiles_kernel,
        emit_keys=binning.emit_keys_kernel,
        depth_rank=binning.depth_rank_kernel,
        tile_ranges=binning.tile_ranges_kernel,
    )
