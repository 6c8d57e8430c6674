"""The built-in demo scene, its orbit, its rendered photos and the built-in painting."""
import cv2
import numpy as np
import pytest
import torch

from _io_helpers import data_root, rot_from_quat_rodrigues
from tlvg_warp.io.demo import ASSETS, builtin_painting, demo_dataset, demo_scene

MAX_GAUSSIANS = 20_000  # the demo stays small: "tens of thousands at most", here <= 20k
GROUND_TOL = 1e-6  # the floor is built at z = 0 exactly; float32 storage only
OBJECT_INSIDE_MIN = 0.95  # the orbit frames the still life: nearly every object splat is in every view
RENDER_TOL = 1e-3  # Warp float32 vs the float64 torch reference at 32x24; measured ~2e-5
PAINTING_TOL = 0.03  # mean abs difference to a fresh INTER_AREA resize; JPEG q90 costs ~0.01
COARSE = 3.0  # the spacing the stylize e2e test uses
# mean abs difference of the coarse scene's photos to the default's at 32x24: the stripes and checkers are
# sampled 3x coarser (measured 0.038-0.046 over 6 views); a hole or a misplaced object costs far more
COARSE_RENDER_TOL = 0.06
COVERAGE_TOL = 0.01  # the fraction of the view the scene covers (measured equal to 3 decimals)


def test_scene_geometry():
    g, cams = demo_scene()
    assert 5_000 < g.num <= MAX_GAUSSIANS and g.sh_degree == 0
    z = g.means[:, 2].numpy()
    assert z.min() > -GROUND_TOL
    ground = np.abs(z) < GROUND_TOL
    assert ground.sum() > 1000 and (~ground).sum() > 3000  # a floor, and objects standing on it
    # every splat is a disc: its thin (third) axis is the smallest; on the floor that axis is world z
    ls = g.log_scales.numpy()
    assert np.all(ls[:, 2] < ls[:, :2].min(1))
    for k in np.flatnonzero(ground)[::500]:
        n = rot_from_quat_rodrigues(g.quats[k].double().numpy())[:, 2]
        assert abs(abs(n[2]) - 1) < 1e-5
    # the orbit: 24 cameras at 160x120, above the floor, each seeing the objects in front of it
    assert len(cams) == 24 and all((c.width, c.height) == (160, 120) for c in cams)
    obj = g.means[~torch.from_numpy(ground)].double().numpy()
    for c in cams:
        assert c.center[2].item() > 0.5
        w2c = c.world_to_camera.numpy()
        p = obj @ w2c[:3, :3].T + w2c[:3, 3]
        u, v = c.fx * p[:, 0] / p[:, 2] + c.cx, c.fy * p[:, 1] / p[:, 2] + c.cy
        inside = (p[:, 2] > 0) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        assert inside.mean() > OBJECT_INSIDE_MIN, (c.name, inside.mean())
    # distinct textures: the object splats span many colors, not one
    rgb = (g.sh[~torch.from_numpy(ground), 0] * 0.28209479177387814 + 0.5).numpy()
    assert len(np.unique(np.round(rgb * 4), axis=0)) >= 6


def test_scene_deterministic():
    a, _ = demo_scene(0)
    b, _ = demo_scene(0)
    c, _ = demo_scene(1)
    assert torch.equal(a.sh, b.sh) and torch.equal(a.means, b.means) and not torch.equal(a.sh, c.sh)


def test_demo_photos_match_reference_renderer():
    from tlvg_warp.reference import render_reference

    ds = demo_dataset(width=32, height=24)
    assert len(ds) == 24 and ds.names == sorted(ds.names) and ds.points[0].shape[1] == 3
    img = ds.image(5)
    assert tuple(img.shape) == (24, 32, 3) and img.dtype == torch.float32 and ds.image(5) is img  # cached
    ref = render_reference(ds.gaussians.to(dtype=torch.float64), ds.cameras[5], background=ds.background)
    assert (ref.color.float() - img).abs().max().item() < RENDER_TOL
    assert (img < 0.9).any(dim=2).float().mean().item() > 0.5  # mostly scene, not background
    test = demo_dataset(width=32, height=24, split="test")
    assert test.names == ["view_000", "view_008", "view_016"]


def test_coarse_scene_is_the_same_still_life_in_fewer_larger_discs():
    g1, _ = demo_scene()
    g3, _ = demo_scene(spacing=COARSE)
    assert 8 < g1.num / g3.num < 10  # surfaces sampled 3x sparser: ~1/9 the Gaussians
    disc = lambda g: g.log_scales[:, :2].exp().median().item()  # noqa: E731  in-plane scale
    assert disc(g3) / disc(g1) == pytest.approx(COARSE, rel=0.02)
    for f in (lambda m: m.min(0).values, lambda m: m.max(0).values):  # the same extent
        assert torch.allclose(f(g3.means), f(g1.means), atol=0.01)
    ls = g3.log_scales.numpy()
    assert np.all(ls[:, 2] < ls[:, :2].min(1))  # still flat discs
    with pytest.raises(ValueError):
        demo_scene(spacing=0)


def test_coarse_scene_photos_match_the_default_scene():
    fine, coarse = demo_dataset(n_views=6, width=32, height=24), demo_dataset(n_views=6, width=32, height=24,
                                                                               spacing=COARSE)
    for i in range(6):
        a, b = fine.image(i), coarse.image(i)
        assert (a - b).abs().mean().item() < COARSE_RENDER_TOL, i
        cover = lambda img: (img < 0.9).any(dim=2).float().mean().item()  # noqa: E731  not white background
        assert cover(b) == pytest.approx(cover(a), abs=COVERAGE_TOL), i  # no holes in the larger discs


def test_builtin_painting():
    f = ASSETS / "starry_night.jpg"
    assert f.stat().st_size < 100_000
    p = builtin_painting()
    assert p.dtype == torch.float32 and p.shape[0] == 256 and p.shape[2] == 3 and 0 <= p.min() and p.max() <= 1
    assert p.shape[1] == 410  # 1024x640 source at height 256
    root = data_root()
    if root is not None and (root / "styles" / "starry_night.jpg").is_file():
        src = cv2.imread(str(root / "styles" / "starry_night.jpg"))[:, :, ::-1].astype(np.float32) / 255
        ref = cv2.resize(src, (p.shape[1], 256), interpolation=cv2.INTER_AREA)
        assert np.abs(ref - p.numpy()).mean() < PAINTING_TOL


def test_demo_photos_through_images_equal_one_by_one():
    """``Dataset.images()`` (what stylize's setup calls) on the demo, whose photos are Warp renders: every view
    equals a fresh dataset's ``image(i)`` taken one at a time. Catches the demo decoded in the thread pool:
    concurrent Warp launches share their recorded launch descriptors (it crashed the CLI demo once)."""
    a, b = demo_dataset(n_views=6, width=32, height=24), demo_dataset(n_views=6, width=32, height=24)
    got = a.images()
    assert len(got) == len(b.cameras) == 6
    for i, img in enumerate(got):
        assert torch.equal(img, b.image(i))
