"""The cap on the painting's cells in the style match (``style_max_cells``): the stride is the smallest that fits,
the kept cells are the full grid's at that stride, a nearest-neighbour match over them can only be farther than over
every cell, and ``prepare`` thins the style terms' features while the field match keeps every cell."""
import numpy as np
import pytest
import torch

from _demo_helpers import StubFeatures, demo_stylize_inputs
from tlvg_warp.losses.style import nnfm_loss
from tlvg_warp.stylize.config import config_from_dict
from tlvg_warp.stylize.pipeline import cell_stride, prepare, thin_cells


def _kept(h, w, s):
    return len(range(0, h, s)) * len(range(0, w, s))


@pytest.mark.parametrize("h, w, cap", [(10, 10, 100), (10, 10, 99), (10, 10, 25), (10, 10, 24), (97, 151, 4000),
                                       (306, 490, 65536), (612, 980, 65536), (7, 3, 1), (5, 5, 0)])
def test_the_stride_is_the_smallest_that_fits(h, w, cap):
    s = cell_stride(h, w, cap)
    if cap == 0:
        assert s == 1  # no limit
        return
    assert _kept(h, w, s) <= cap  # fits
    assert s == 1 or _kept(h, w, s - 1) > cap  # and one less would not


def test_thinned_cells_are_the_grid_at_the_stride():
    g = torch.Generator().manual_seed(0)
    f = torch.randn(1, 5, 13, 17, generator=g)
    out = thin_cells(f, 30)  # 13x17 = 221 cells: stride 3 keeps 5 x 6 = 30
    s = cell_stride(13, 17, 30)
    assert s == 3 and out.shape == (5, 30)
    a = f[0].numpy()
    want = np.stack([a[:, i, j] for i in range(0, 13, s) for j in range(0, 17, s)], 1)  # row-major, by hand
    np.testing.assert_array_equal(out.numpy(), want)
    np.testing.assert_array_equal(thin_cells(f, 0).numpy(), a.reshape(5, -1))  # 0: every cell
    np.testing.assert_array_equal(thin_cells(f, 221).numpy(), a.reshape(5, -1))  # a grid that fits: every cell


def test_a_match_over_fewer_cells_is_never_nearer():
    """NNFM is a mean of minima over the painting's cells: over a subset each minimum can only grow."""
    g = torch.Generator().manual_seed(1)
    painting = torch.rand(1, 16, 40, 60, generator=g)
    view = torch.rand(16, 300, generator=g, dtype=torch.float32)
    full = float(nnfm_loss(view, thin_cells(painting, 0)))
    for cap in (1200, 600, 300, 100):
        thinned = float(nnfm_loss(view, thin_cells(painting, cap)))
        assert thinned >= full - 1e-7
    assert float(nnfm_loss(view, thin_cells(painting, 100))) > full + 1e-3  # and strictly, once most cells go


def test_prepare_thins_the_style_terms_features_and_keeps_the_field_matchs():
    inp = demo_stylize_inputs(3, 64, 48, 8)[1]
    cfg = lambda cap: config_from_dict({"iterations": 6, "device": "cpu", "background": [1.0, 1.0, 1.0],  # noqa: E731
                                        "style_height": 0, "stroke_scale": 4.0, "style_max_cells": cap}).validate()
    full = prepare(inp, cfg(0), StubFeatures(), torch.device("cpu"), (1.0, 1.0, 1.0))
    n = full.style_feats.shape[1]
    assert full.match_feats.shape == full.style_feats.shape
    capped = prepare(inp, cfg(n // 3), StubFeatures(), torch.device("cpu"), (1.0, 1.0, 1.0))
    assert capped.style_feats.shape[1] <= n // 3
    assert capped.match_feats.shape == full.match_feats.shape  # the field match sees every cell
    cols = {tuple(c) for c in full.style_feats.T.numpy().round(6)}
    assert all(tuple(c) in cols for c in capped.style_feats.T.numpy().round(6))  # each kept cell is one of the full's
