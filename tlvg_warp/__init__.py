"""tlvg_warp: flow-guided 3D Gaussian Splatting stylization ("Thinking Like Van Gogh") on NVIDIA Warp."""
from .errors import InputError

__all__ = ["Camera", "Gaussians", "InputError", "render", "RenderOutput", "load_ply", "save_ply", "load_dataset"]


def __getattr__(name):  # lazy: importing the package must not initialize Warp, nor import torch (`python -m
    # tlvg_warp` starts CUDA in a thread first: warmup.py)
    if name in ("Camera", "Gaussians"):
        from . import types
        return getattr(types, name)
    if name in ("render", "RenderOutput"):
        from . import renderer
        return getattr(renderer, name)
    if name in ("load_ply", "save_ply", "save_splat", "load_splat"):
        from .io import ply as _p
        return getattr(_p, name)
    if name == "load_dataset":
        from .io.datasets import load_dataset
        return load_dataset
    raise AttributeError(name)
