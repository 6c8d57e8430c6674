"""benchmarks/gsplat_trainer.py, the pieces that run without gsplat (CPU): our camera as gsplat's viewmat and K
projects every point where our renderer puts it, and the minimal gsplat trainer follows our loop's view order, SH
and learning-rate schedules and our densify steps. The module is loaded by path; it must not import gsplat."""
import dataclasses
import math
import sys

import pytest
import torch
from _bench_helpers import load_benchmark

from tlvg_warp import Camera, Gaussians, render
from tlvg_warp.reference import project_reference
from tlvg_warp.train.density import DensityControl, DensityStrategy
from tlvg_warp.train.loop import Fit, LoopSettings, Phase, Run
from tlvg_warp.train.optim import GaussianParams
from tlvg_warp.train.reconstruct import ReconstructConfig, split_views
from tlvg_warp.train.session import optimizer

SUBPIXEL_TOL = 1e-9  # pixels, float64: the two projections are the same arithmetic


@pytest.fixture(scope="module")
def bench():
    had_gsplat = "gsplat" in sys.modules
    mod = load_benchmark("gsplat_trainer.py")
    assert had_gsplat or "gsplat" not in sys.modules, "the benchmark imports gsplat at module level"
    return mod


def off_center_camera() -> Camera:
    """A tilted camera, fx != fy, principal point far from the image center (and cx != cy)."""
    cam = Camera.look_at((0.7, -2.5, 0.9), (0.1, 0.2, 0.0), (0.0, 0.0, 1.0), width=64, height=48)
    return dataclasses.replace(cam, fx=70.0, fy=55.0, cx=23.3, cy=29.1)


def back_project(cam: Camera, uv: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """World points [P,3] that our camera sees at pixel positions uv [P,2] and depths z [P]."""
    pc = torch.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], 1)
    return (pc - cam.t) @ cam.R  # R^T (pc - t)


def gsplat_project(viewmat: torch.Tensor, K: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """gsplat's pinhole projection (gsplat/cuda/_torch_impl.py, _world_to_cam then _persp_proj): [P,3] -> [P,2]."""
    pc = pts @ viewmat[:3, :3].T + viewmat[:3, 3]
    return (pc / pc[:, 2:3]) @ K[:2].T  # (fx x/z + cx, fy y/z + cy)


def tiny_gaussians(pts: torch.Tensor, scale: float = 1e-4) -> Gaussians:
    return Gaussians.from_colors(pts, torch.ones(pts.shape[0], 3, dtype=pts.dtype), scale, opacity=0.99)


def sample_points(cam: Camera, n: int = 12, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    uv = torch.rand(n, 2, generator=gen, dtype=torch.float64) * torch.tensor([cam.width - 4.0, cam.height - 4.0]) + 2
    return back_project(cam, uv, 1.5 + 2.5 * torch.rand(n, generator=gen, dtype=torch.float64))


def projection_gap(cam: Camera, viewmat, K, pts) -> float:
    """Largest distance (pixels) between gsplat's projection with (viewmat, K) and our renderer's screen means."""
    ours = project_reference(tiny_gaussians(pts), cam)
    assert bool((ours.radii > 0).all())
    return float((gsplat_project(viewmat, K, pts) - ours.means2d).norm(dim=1).max())


def test_viewmat_and_K_project_like_our_renderer(bench):
    cam = off_center_camera()
    pts = sample_points(cam)
    viewmat, K = bench.gsplat_camera(cam, torch.float64)
    assert viewmat.shape == (4, 4) and K.shape == (3, 3)
    assert projection_gap(cam, viewmat, K, pts) < SUBPIXEL_TOL
    # the check itself sees the usual mistakes
    W, H = cam.width, cam.height
    wrong_pp = [(W / 2, H / 2), (cam.cx - 0.5, cam.cy - 0.5), (cam.cy, cam.cx)]
    for cx, cy in wrong_pp:
        Kw = K.clone()
        Kw[0, 2], Kw[1, 2] = cx, cy
        assert projection_gap(cam, viewmat, Kw, pts) > 0.4, (cx, cy)
    assert projection_gap(cam, viewmat.T.contiguous(), K, pts) > 1.0


def test_points_land_on_the_pixel_our_renderer_lights(bench):
    """End to end: a tiny opaque Gaussian rendered by our (Warp) renderer is brightest in the pixel that gsplat's
    projection with the helper's viewmat and K puts its point in (pixel (j, i) spans [j, j+1) x [i, i+1) on both)."""
    cam = off_center_camera()
    uv = torch.tensor([[9.3, 7.35], [40.3, 20.4], [55.35, 41.3]], dtype=torch.float64)  # 0.2 px or less from a center
    pts = back_project(cam, uv, torch.tensor([1.7, 2.9, 3.6], dtype=torch.float64))
    viewmat, K = bench.gsplat_camera(cam)  # float32, as the trainer passes them
    pix = gsplat_project(viewmat.double(), K.double(), pts).floor().long()  # [P,2] (j, i)
    for p, (j, i) in zip(pts, pix.tolist()):
        img = render(tiny_gaussians(p[None].float()), cam, (0.0, 0.0, 0.0)).color.sum(-1)  # [H,W]
        assert float(img.detach().max()) > 0.3
        assert divmod(int(img.detach().argmax()), cam.width) == (i, j)


def test_view_order_is_the_loops(bench):
    train_idx, _ = split_views(20, 8)
    run = Run(None, None, DensityStrategy(), [Phase("fit", 100)], [None] * 20, LoopSettings(), device="cpu", seed=3,
              view_ids=train_idx)
    order = bench.ViewOrder(train_idx, 3)
    assert [order.next() for _ in range(3 * len(train_idx) + 5)] == \
        [run.next_batch(run.phases[0])[0][0] for _ in range(3 * len(train_idx) + 5)]


def test_sh_and_xyz_learning_rate_follow_ours(bench):
    cfg = ReconstructConfig(iterations=3000)
    fit = Fit("fit", cfg.iterations, [], sh=(0, cfg.sh_increase_every, cfg.sh_degree))
    g = tiny_gaussians(torch.zeros(2, 3)).with_sh_degree(3)
    opt, extent = optimizer(GaussianParams(g, 3), cfg, 2.5), 2.5
    lr = bench.means_lr(cfg, extent, cfg.iterations)
    for step in (1, 2, 999, 1000, 1001, 2000, 2999, 3000):
        assert bench.sh_degree_at(step, cfg) == fit.sh_degree(step)
        assert lr(step) == pytest.approx(opt.set_step(step), rel=1e-12)


def gsplat_refines(kw: dict, step: int) -> bool:
    """DefaultStrategy.step_post_backward's refine condition (gsplat 1.5.3), for the step the trainer passes."""
    return (step < kw["refine_stop_iter"] and step > kw["refine_start_iter"] and step % kw["refine_every"] == 0
            and step % kw["reset_every"] >= kw["pause_refine_after_reset"])


@pytest.mark.parametrize("iterations, overrides", [(7000, {}), (30000, {}), (1200, {"start": 0, "interval": 50}),
                                                    (9000, {"until": 4000, "opacity_reset_interval": 3000})])
def test_gsplat_refines_at_our_densify_steps(bench, iterations, overrides):
    d = dataclasses.replace(ReconstructConfig().density, **overrides)
    kw = bench.gsplat_strategy_kwargs(d, iterations)
    dc = DensityControl(d, 0)
    ours = [s for s in range(1, iterations + 1) if dc.is_densify_step(s, iterations)]
    assert ours and ours == [s for s in range(1, iterations + 1) if gsplat_refines(kw, s)]
    if not d.opacity_reset_interval:  # no resets: neither side prunes by size during the run
        assert kw["reset_every"] > iterations and kw["refine_scale2d_stop_iter"] == 0
    assert kw["prune_scale3d"] == (d.max_world_size or math.inf)
    assert (kw["prune_opa"], kw["grow_grad2d"], kw["grow_scale3d"]) == (d.min_opacity, d.grad_threshold,
                                                                       d.percent_dense)
