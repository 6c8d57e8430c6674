"""The built-in demo scene as stylization inputs, shared by the loop and stylize tests."""
from __future__ import annotations

import torch


def demo_stylize_inputs(views: int, width: int, height: int, every: int = 1, **demo_kw):
    """(dataset, StylizeInputs) of the demo: ``views`` cameras at width x height, every ``every``-th Gaussian,
    the demo's photos, the built-in painting and the dataset's background."""
    from tlvg_warp.io.demo import builtin_painting, demo_dataset
    from tlvg_warp.stylize import StylizeInputs

    ds = demo_dataset(n_views=views, width=width, height=height, **demo_kw)
    g = ds.gaussians if every == 1 else ds.gaussians.subset(torch.arange(0, ds.gaussians.num, every))
    inp = StylizeInputs(g, list(ds.cameras), list(ds.names), [ds.image(i) for i in range(views)],
                        builtin_painting(), tuple(ds.background))
    return ds, inp
