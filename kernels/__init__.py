"""Warp kernels only (installed as ``tlvg_warp.kernels``); the torch side that launches them lives in
tlvg_warp.launch, tlvg_warp.raster and tlvg_warp.autograd. Kernels of one scalar type share one Warp module, built
once per process."""
import functools
import os
from types import SimpleNamespace

import warp as wp

# Minimum resident 256-thread blocks per SM asked of the blending (forward, backward) kernels through
# __launch_bounds__ (0: the compiler's choice), which caps their registers at 65536 / (256 · blocks). The
# backward's 3: 2% faster (A/B on a trained splat, two runs), same registers.
BLEND_MIN_BLOCKS = (0, 3)


@functools.lru_cache(maxsize=None)
def raster_kernels(scalar_name: str) -> SimpleNamespace:
    """All differentiable-pipeline kernels for ``"float32"`` or ``"float64"``."""
    from . import binning
    from .blend import make_blend
    from .camera import camera_struct
    from .flow import make_flow_terms
    from .projection import make_projection, module_name
    from .sh import make_sh

    scalar = {"float32": wp.float32, "float64": wp.float64}[scalar_name]
    if scalar == wp.float32 and os.environ.get("TLVG_WARP_FAST_MATH", "1") != "0":
        # CUDA fast math (approximate exp/div/sqrt, ~2 ulp, as gsplat builds with): float32 only, the float64
        # module stays the exact oracle; TLVG_WARP_FAST_MATH=0 turns it off. No effect on the CPU.
        wp.set_module_options({"fast_math": True}, module_name(scalar))
    camera = camera_struct(scalar_name)
    project, ewa_cov2d = make_projection(scalar, camera)
    sh_color, sh_backward, sh_coeff_grad = make_sh(scalar, module_name(scalar), camera)
    flow_terms = make_flow_terms(scalar, module_name(scalar), ewa_cov2d, camera)
    forward, backward, forward_cpu, backward_cpu = make_blend(scalar, module_name(scalar), BLEND_MIN_BLOCKS)
    return SimpleNamespace(
        scalar=scalar,
        vec2=wp.types.vector(2, scalar),
        vec3=wp.types.vector(3, scalar),
        vec4=wp.types.vector(4, scalar),
        mat33=wp.types.matrix((3, 3), scalar),
        camera=camera,  # the camera struct type the projection, SH and flow kernels take
        project=project,
        sh_color=sh_color,
        sh_backward=sh_backward,
        sh_coeff_grad=sh_coeff_grad,
        flow_terms=flow_terms,
        blend_forward=forward,
        blend_backward=backward,
        blend_forward_cpu=forward_cpu,  # the same walks, one pixel at a time (raster.blend picks them on the CPU)
        blend_backward_cpu=backward_cpu,
        count_tiles=binning.count_tiles_kernel,
        emit_keys=binning.emit_keys_kernel,
        depth_rank=binning.depth_rank_kernel,
        tile_ranges=binning.tile_ranges_kernel,
    )
