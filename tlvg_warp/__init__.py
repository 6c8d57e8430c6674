"""tlvg_warp: flow-guided 3D Gaussian Splatting stylization ("Thinking Like Van Gogh") on NVIDIA Warp."""
import os as _os

# Running from a source tree without installing (e.g. PYTHONPATH=repo on the GPU machine): the top-level
# kernels/ folder is the subpackage tlvg_warp.kernels (pyproject maps it when installed).
_root = _os.path.dirname(_os.path.dirname(_os.path.abspath(__file__)))
if _os.path.isfile(_os.path.join(_root, "kernels", "__init__.py")) and _root not in __path__:
    __path__.append(_root)

from .errors import InputError  # noqa: E402
from .types import Camera, Gaussians  # noqa: E402

__all__ = ["Camera", "Gaussians", "InputError", "render", "RenderOutput", "load_ply", "save_ply", "load_dataset"]


def __getattr__(name):  # lazy: importing the package must not initialize Warp
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
