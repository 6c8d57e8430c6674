"""Scene fitting: trainable parameters and Adam (optim), adaptive density control (density),
initialization (init) and the reconstruction loop (reconstruct)."""
from .density import DensityConfig, DensityControl
from .init import initialize, knn_distances, knn_scale, scene_extent
from .optim import (GaussianOptimizer, GaussianParams, LearningRates, footprint_normals, quat_to_rotmat,
                    tangential_hook)
from .reconstruct import FitDiverged, FitState, ReconstructConfig, fit_scene, load_config

__all__ = ["DensityConfig", "DensityControl", "initialize", "knn_distances", "knn_scale", "scene_extent",
           "GaussianOptimizer", "GaussianParams", "LearningRates", "footprint_normals", "quat_to_rotmat",
           "tangential_hook", "FitDiverged", "FitState", "ReconstructConfig", "fit_scene", "load_config"]
