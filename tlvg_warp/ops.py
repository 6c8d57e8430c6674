"""The raster layer's torch side, by its former single-module name: an index of what moved to

- ``tlvg_warp.launch``: Warp's runtime (initialization, kernel sets, devices and streams, array descriptors,
  recorded launches, sort and scan) and every use of Warp's private API;
- ``tlvg_warp.raster``: the pipeline's stages (camera struct, projection, binning, blending);
- ``tlvg_warp.autograd``: the autograd Functions ``ShadeFn`` and ``RasterizeFn`` (and the flow energies'
  ``FlowEnergiesFn`` and ``FlowTermsFn``, which tlvg_warp.flow re-exports).

The package imports from those modules; this one re-exports their public names for code written against it.
Module-level settings (``raster.SCAN_INT32_LIMIT``) are read where they live: set them there."""
from .autograd import RasterizeFn, ShadeFn
from .launch import (NO_DRIVER, canonical, ct, ct_at, cuda_driver_present, fast_launch, inclusive_scan_at, init_warp,
                     input_ct, kernels_for, sort_pairs, sort_pairs_at, to_warp, warp_array_ctype, warp_on, wdevice,
                     without_lines)
from .raster import (TILE, DepthOrder, Projected, Projection, bin_tiles, binning_inputs, blend, camera_arg,
                     camera_values, capture_binning, count_intersections, kernel_vec3, no_grad_camera, packed_zeros,
                     project, project_adjoint, tile_grid, warp_padded)

__all__ = ["NO_DRIVER", "TILE", "DepthOrder", "Projected", "Projection", "RasterizeFn", "ShadeFn", "bin_tiles",
           "binning_inputs", "blend", "camera_arg", "camera_values", "canonical", "capture_binning",
           "count_intersections", "ct", "ct_at", "cuda_driver_present", "fast_launch", "inclusive_scan_at",
           "init_warp", "input_ct", "kernel_vec3", "kernels_for", "no_grad_camera", "packed_zeros", "project",
           "project_adjoint", "sort_pairs", "sort_pairs_at", "tile_grid", "to_warp", "warp_array_ctype", "warp_on",
           "warp_padded", "wdevice", "without_lines"]
