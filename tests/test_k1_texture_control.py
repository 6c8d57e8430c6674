"""benchmarks/k1_texture_control.py's texture: a luminance offset fixed to each Gaussian. Oracles: the band-0
colour formula (colour = SH_C0 * dc + 0.5) read back for the offsets' statistics, and the renderer's linearity in
the colours (where nothing clamps) for what the views show."""
import torch

from _bench_helpers import load_benchmark
from test_raster import camera, random_scene
from tlvg_warp import render
from tlvg_warp.types import SH_C0

control = load_benchmark("k1_texture_control.py")


def _colour(g):  # [N,3] band-0 colour
    return SH_C0 * g.sh[:, 0] + 0.5


def test_offsets_are_one_luminance_step_per_gaussian_with_the_amplitude_as_spread():
    g = random_scene(20000, degree=1, seed=4)
    j = control.jittered(g, 0.2, seed=7)
    d = _colour(j) - _colour(g)  # [N,3]
    assert torch.allclose(d[:, 0], d[:, 1], atol=1e-12) and torch.allclose(d[:, 0], d[:, 2], atol=1e-12)
    assert abs(float(d[:, 0].std()) - 0.2) < 0.2 * 0.03  # N(0, 0.2^2): the spread within 3% at 20,000 samples
    assert abs(float(d[:, 0].mean())) < 3 * 0.2 / 20000 ** 0.5
    assert torch.equal(j.sh[:, 1:], g.sh[:, 1:])  # higher bands, geometry and opacity untouched
    for f in ("means", "quats", "log_scales", "opacity_logits"):
        assert torch.equal(getattr(j, f), getattr(g, f))
    assert torch.equal(control.jittered(g, 0.2, seed=7).sh, j.sh)  # fixed by the seed ...
    assert not torch.equal(control.jittered(g, 0.2, seed=8).sh, j.sh)  # ... and a new seed, a new texture
    assert torch.equal(control.jittered(g, 0.0).sh, g.sh)


def test_the_views_show_the_same_offsets_scaled_by_the_amplitude():
    # the render is linear in the Gaussians' colours where none clamps: the same z at twice the amplitude moves
    # every pixel twice as far, and equally on R, G and B (a texture fixed to the Gaussians, not to the view)
    g = random_scene(60, degree=0, seed=2)
    bg = torch.zeros(3, dtype=torch.float64)
    with torch.no_grad():
        _check_views(g, bg)


def _check_views(g, bg):
    for cam in (camera(), camera(eye=(1.5, -2.5, 0.8))):
        base = render(g, cam, bg).color
        one = render(control.jittered(g, 0.02, seed=5), cam, bg).color - base
        two = render(control.jittered(g, 0.04, seed=5), cam, bg).color - base
        assert float(one.abs().max()) > 1e-3  # the texture shows
        assert torch.allclose(two, 2 * one, atol=1e-6)
        assert torch.allclose(one[..., 0], one[..., 1], atol=1e-6)
        assert torch.allclose(one[..., 0], one[..., 2], atol=1e-6)


def test_grey_and_the_thin_share_by_hand():
    g = random_scene(50, degree=1, seed=3)
    gg = control.grey(g)
    assert torch.allclose(_colour(gg), torch.full((50, 3), 0.5, dtype=torch.float64)) and not gg.sh[:, 1:].any()
    # two views: 4 and 2 covered pixels in the un-stylized scene, of which 2 and 2 under 0.95 in the views
    import numpy as np
    from types import SimpleNamespace
    base = [{"alpha": np.array([[1.0, 1.0], [1.0, 1.0]])}, {"alpha": np.array([[1.0, 0.2], [0.6, 0.0]])}]
    views = [{"alpha": np.array([[0.94, 1.0], [0.96, 0.2]])}, {"alpha": np.array([[0.5, 0.1], [0.9, 0.1]])}]
    # view 1: (0,0) 0.94 and (1,1) 0.2 are under 0.95: 2 of 4; view 2: (0,0) 0.5 and (1,0) 0.9: 2 of 2
    assert control.thin_share(views, SimpleNamespace(base=base)) == 4 / 6
