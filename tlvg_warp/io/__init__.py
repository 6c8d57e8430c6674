"""Scene I/O: Gaussian PLY / .splat files, posed-photo datasets (COLMAP, LLFF, Blender, INRIA) and the
built-in demo scene. Submodules import lazily so ``import tlvg_warp.io`` stays cheap."""


def __getattr__(name):
    if name in ("load_ply", "save_ply", "save_splat", "load_splat"):
        from . import ply
        return getattr(ply, name)
    if name in ("load_dataset", "Dataset"):
        from . import datasets
        return getattr(datasets, name)
    if name in ("demo_scene", "demo_dataset", "builtin_painting"):
        from . import demo
        return getattr(demo, name)
    raise AttributeError(name)
