"""The camera as one kernel argument: a Warp struct per scalar type (SPEC §1 conventions), passed by value to the
projection, SH and flow kernels in place of their loose camera scalars. Registered with the raster module of its
scalar type (``projection.module_name``); kernels of other modules take it too.
(No ``from __future__ import annotations`` here: Warp reads the struct's annotations as objects.)"""
import functools

import warp as wp

from .projection import module_name


@functools.lru_cache(maxsize=None)
def camera_struct(scalar_name: str):
    """The camera struct type for ``"float32"`` or ``"float64"`` (one per process and scalar type)."""
    scalar = {"float32": wp.float32, "float64": wp.float64}[scalar_name]
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

    class RasterCamera:
        R: mat33  # world -> camera rotation (rows of world_to_camera[:3, :3])
        t: vec3  # world -> camera translation: p = R x + t
        center: vec3  # camera position in world space, -Rᵀ t (the SH view direction starts here)
        fx: scalar
        fy: scalar
        cx: scalar
        cy: scalar
        width: wp.int32  # pixels
        height: wp.int32
        near: scalar  # cull z <= near
        far: scalar  # cull z >= far

    RasterCamera.__qualname__ = RasterCamera.__name__ = f"RasterCamera_{scalar_name}"
    return wp.struct(RasterCamera, module=module_name(scalar))
