"""The built-in demo scene as stylization inputs, shared by the loop and stylize tests."""
from __future__ import annotations

import torch
import torch.nn.functional as F


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


class StubFeatures(torch.nn.Module):
    """A feature network with closed-form features, for tests whose property does not depend on what VGG computes:
    4x4 average pooling of the image (3 'channels'). ``calls`` keeps the images it saw."""

    is_random, source = True, "stub"

    def __init__(self):
        super().__init__()
        self.calls = []

    def forward(self, img, scale=1.0):
        x = img.permute(2, 0, 1).unsqueeze(0) if img.dim() == 3 else img
        self.calls.append(x.detach())
        return F.avg_pool2d(x.float(), 4)

    def features_of(self, images, scale=1.0):  # one batched pass, as VGG16Features.features_of
        f = self(torch.stack([im.permute(2, 0, 1) for im in images]), scale)
        return [fi.reshape(3, -1) for fi in f]
