"""One Gaussian through the rasterizer's forward and backward. A [1, 3] column slice of a PLY table is
'contiguous' to torch with a stride of 26 on its size-1 dimension; Warp compares strides literally, so the backward
used to fail with a gradient-stride error. Compared with the float64 torch reference."""
import pytest
import torch

from tlvg_warp import Camera, Gaussians, render
from tlvg_warp.io import load_ply, save_ply
from tlvg_warp.reference import render_reference

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def _one(dtype):
    # each field a column slice of one [1, 26] table, as load_ply returns them (strides 26, not 3)
    table = torch.tensor([[0.05, -0.02, 0.1, 1.0, 0.1, -0.2, 0.05, -2.0, -2.3, -2.6, 0.4, 0.2, -0.1, 0.3]
                          + [0.1 * ((-1) ** i) for i in range(12)]], dtype=dtype)
    g = Gaussians(table[:, 0:3], table[:, 3:7], table[:, 7:10], table[:, 10], table[:, 14:26].reshape(1, 4, 3))
    assert g.means.stride() != (3, 1)  # the layout that broke
    return Gaussians(**{f: getattr(g, f).detach().requires_grad_(True) for f in FIELDS})


def _cam():
    return Camera.look_at((0.2, -3.0, 0.3), [0, 0, 0], width=37, height=29, fov_deg=50.0)


def _grads(out, g):
    gen = torch.Generator().manual_seed(3)
    ups = [torch.randn(t.shape, generator=gen, dtype=torch.float64).to(t.dtype) for t in (out.color, out.alpha, out.depth)]
    loss = sum((t * u).sum() for t, u in zip((out.color, out.alpha, out.depth), ups))
    return torch.autograd.grad(loss, [getattr(g, f) for f in FIELDS])


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 2e-4)])
def test_one_gaussian_render_and_backward_match_reference(dtype, tol):
    g = _one(dtype)
    out = render(g, _cam())
    assert out.alpha.max() > 0.1  # it is visible, so the gradients are not trivially zero
    g64 = _one(torch.float64)
    ref = render_reference(g64, _cam())
    for a, b in ((out.color, ref.color), (out.alpha, ref.alpha), (out.depth, ref.depth)):
        torch.testing.assert_close(a.double(), b.detach(), atol=tol, rtol=tol)
    for f, ga, gb in zip(FIELDS, _grads(out, g), _grads(ref, g64)):
        assert gb.abs().max() > 0, f
        assert (ga.double() - gb).abs().max() <= 10 * tol * gb.abs().max(), f


def test_one_gaussian_from_ply_backward(tmp_path):
    src = _one(torch.float32)
    save_ply(Gaussians(**{f: getattr(src, f).detach() for f in FIELDS}), tmp_path / "one.ply")
    g = load_ply(tmp_path / "one.ply")
    for f in FIELDS:
        getattr(g, f).requires_grad_(True)
    out = render(g, _cam())
    (out.color.sum() + out.alpha.sum()).backward()
    assert torch.isfinite(g.means.grad).all() and g.means.grad.abs().sum() > 0
    assert g.sh.grad.shape == (1, 4, 3) and g.sh.grad[0, 0].abs().sum() > 0
