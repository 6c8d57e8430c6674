"""The same rasterizer on a CUDA device (skipped without one): CUDA results against the CPU float64 oracle."""
import pytest
import torch

from tlvg_warp import render
from tlvg_warp.reference import render_reference

from test_raster import F32_TOL, F64_TOL, FIELDS, assert_close, camera, leafs, loss_grads, random_scene, upstream

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.parametrize("dtype,tol", [(torch.float64, F64_TOL), (torch.float32, F32_TOL)])
def test_cuda_matches_cpu_reference(dtype, tol):
    g = random_scene(400, 3, seed=21)
    cam = camera(70, 45)
    gc = leafs(g.to("cuda", dtype))
    out = render(gc, cam, background=[0.2, 0.1, 0.3], return_weights=True)
    gr = leafs(g)
    ref = render_reference(gr, cam, background=[0.2, 0.1, 0.3], return_weights=True)
    for k in ("color", "alpha", "depth", "weights"):
        assert_close(getattr(out, k).cpu().double(), getattr(ref, k), tol, k)
    ups = upstream(ref)
    ga = loss_grads(gc, out, [u.to("cuda", dtype) for u in ups])
    gb = loss_grads(gr, ref, ups)
    for name, a, b in zip(FIELDS + ("means2d",), ga, gb):
        assert_close(a.cpu().double(), b, tol * 10 if dtype == torch.float32 else tol, f"d/d{name}")


@pytest.mark.parametrize("n", [1500, 3000])
def test_cuda_batches_and_early_stop(n):
    """Tiles holding several shared-memory batches (>256 Gaussians each) and pixels that saturate mid-batch:
    the batched GPU blending against the float64 oracle, image and gradients."""
    g = random_scene(n, 1, seed=n, spread=0.08, log_scale=-1.5, opacity_shift=1.0)
    cam = camera(40, 36)
    gc = leafs(g.to("cuda"))
    out = render(gc, cam, background=[0.1, 0.2, 0.3])
    gr = leafs(g)
    ref = render_reference(gr, cam, background=[0.1, 0.2, 0.3])
    assert (ref.alpha > 1 - 2e-4).float().mean() > 0.15  # many pixels stop early (T < T_MIN)
    for k in ("color", "alpha", "depth"):
        assert_close(getattr(out, k).cpu(), getattr(ref, k), F64_TOL, k)
    ups = upstream(ref)
    ga = loss_grads(gc, out, [u.to("cuda") for u in ups])
    gb = loss_grads(gr, ref, ups)
    for name, a, b in zip(FIELDS + ("means2d",), ga, gb):
        assert_close(a.cpu(), b, F64_TOL, f"d/d{name}")
