"""Scene fitting: trainable parameters and Adam (optim), adaptive density control (density), initialization
(init), the one training loop with phases as objects (loop), the frame every run shares (session: device,
checkpoint, run folder, density control, Adam, the Run) and the reconstruction, one Fit phase (reconstruct)."""
from .density import DensityConfig, DensityControl
from .init import initialize, knn_distances, knn_scale, scene_extent
from .loop import Diverged, Fit, LoopSettings, Phase, Run, train
from .optim import (GaussianOptimizer, GaussianParams, LearningRates, footprint_normals, quat_to_rotmat,
                    tangential_hook)
from .reconstruct import FitDiverged, ReconstructConfig, fit_scene, load_config
from .session import Session

__all__ = ["DensityConfig", "DensityControl", "initialize", "knn_distances", "knn_scale", "scene_extent",
           "Diverged", "Fit", "LoopSettings", "Phase", "Run", "train",
           "GaussianOptimizer", "GaussianParams", "LearningRates", "footprint_normals", "quat_to_rotmat",
           "tangential_hook", "FitDiverged", "ReconstructConfig", "fit_scene", "load_config", "Session"]
