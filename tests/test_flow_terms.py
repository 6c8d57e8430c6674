"""Flow alignment and anisotropy energies (Warp kernel) against their torch twin with an explicit
eigen-decomposition, and closed-form cases."""
import math

import torch

from tlvg_warp import Camera, Gaussians
from tlvg_warp.flow import flow_terms, flow_terms_reference, flow_terms_unfused

from test_raster import assert_close, camera, leafs, random_scene

# float64 on both sides; the kernel's ISO_EPS regularizer (1e-12) is the only difference
F64_TOL = 1e-6


def constant_field(theta, cam, coherence=1.0):
    f = torch.tensor([coherence * math.cos(2 * theta), coherence * math.sin(2 * theta)], dtype=torch.float64)
    return f.expand(cam.height, cam.width, 2).contiguous()


def swirl_field(cam):
    jj, ii = torch.meshgrid(torch.arange(cam.width, dtype=torch.float64), torch.arange(cam.height, dtype=torch.float64),
                            indexing="xy")
    theta = torch.atan2(ii - cam.height / 2, jj - cam.width / 2) + math.pi / 2  # circles around the center
    c = torch.linspace(0.2, 1.0, cam.width, dtype=torch.float64).expand(cam.height, -1)
    return torch.stack([c * torch.cos(2 * theta), c * torch.sin(2 * theta)], -1)


def test_matches_torch_twin_values_and_gradients():
    g = random_scene(200, 0, seed=31, log_scale=-2.0)
    g.log_scales.data[:, 0] += 1.0  # elongated, so every footprint has a major axis
    cam = camera(60, 40)
    field = swirl_field(cam)
    weights = torch.rand(200, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    g1, g2 = leafs(g), leafs(g)
    a1, b1 = flow_terms(g1, cam, field, weights)
    a2, b2 = flow_terms_reference(g2, cam, field, weights)
    assert_close(a1, a2, F64_TOL, "alignment energy")
    assert_close(b1, b2, F64_TOL, "anisotropy energy")
    names = ("means", "quats", "log_scales")
    grads1 = torch.autograd.grad(a1 + 0.3 * b1, [getattr(g1, f) for f in names])
    grads2 = torch.autograd.grad(a2 + 0.3 * b2, [getattr(g2, f) for f in names])
    for f, ga, gb in zip(names, grads1, grads2):
        assert_close(ga, gb, F64_TOL, f"d/d{f}")
        assert ga.abs().sum() > 0


def test_closed_form_aligned_and_crossed_strokes():
    # one needle along image x (world x for this camera): aligned with θ = 0, crossed with θ = 90°
    cam = Camera(torch.eye(4), 50.0, 50.0, 20.0, 15.0, 40, 30)
    g = Gaussians(torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
                  torch.log(torch.tensor([[0.2, 0.01, 0.01]], dtype=torch.float64)), torch.zeros(1, dtype=torch.float64),
                  torch.zeros(1, 1, 3, dtype=torch.float64))
    w = torch.ones(1, dtype=torch.float64)
    along, aniso_along = flow_terms(g, cam, constant_field(0.0, cam), w)
    across, aniso_across = flow_terms(g, cam, constant_field(math.pi / 2, cam), w)
    assert along.item() < 1e-5 and abs(across.item() - 1.0) < 1e-5
    # Σ2D = diag(a, c): aniso = c/a + c/a when aligned, a/c + c/a when crossed
    a = (50 * 0.2 / 2) ** 2 + 0.3
    c = (50 * 0.01 / 2) ** 2 + 0.3
    assert abs(aniso_along.item() - 2 * c / a) < 1e-9
    assert abs(aniso_across.item() - (a / c + c / a)) < 1e-9


def test_gradient_descent_turns_a_gaussian_onto_the_stroke():
    cam = Camera(torch.eye(4), 50.0, 50.0, 20.0, 15.0, 40, 30)
    g = Gaussians(torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
                  torch.log(torch.tensor([[0.2, 0.02, 0.02]], dtype=torch.float64)), torch.zeros(1, dtype=torch.float64),
                  torch.zeros(1, 1, 3, dtype=torch.float64))
    g = leafs(g)
    field = constant_field(math.radians(60), cam)
    opt = torch.optim.Adam([g.quats], lr=0.02)
    first = None
    for _ in range(150):
        opt.zero_grad()
        e, _ = flow_terms(g, cam, field, torch.ones(1, dtype=torch.float64))
        first = e.item() if first is None else first
        e.backward()
        opt.step()
    assert first > 0.4 and e.item() < 0.01, (first, e.item())


def test_empty_scene_gives_zero_energy_and_empty_gradients():
    # torch hands empty tensors arbitrary strides; they must still cross to Warp (seen at 1920x1440 when
    # density control had pruned everything)
    g = leafs(random_scene(0, 0))
    cam = camera(20, 10)
    a, b = flow_terms(g, cam, constant_field(0.3, cam), torch.zeros(0, dtype=torch.float64))
    (a + b).backward()
    assert a.item() == 0.0 and b.item() == 0.0 and g.means.grad.shape == (0, 3)


def test_fused_targets_match_the_torch_targets_in_hard_cases():
    """flow_terms (targets, weights and their sum in one Warp kernel) against flow_terms_unfused (the torch
    targets of flow_targets, grid_sample with border padding): a field of another size than the view, Gaussians
    behind the camera, off screen, with NaN scales, on low-coherence spots and with zero blend weight."""
    g = random_scene(300, 0, seed=32, spread=1.5, log_scale=-2.0)
    g.log_scales.data[:, 0] += 1.0
    g.log_scales.data[7] = float("nan")
    cam = camera(60, 40)
    field = swirl_field(camera(45, 31))  # resampled onto the 60 x 40 view
    field[5:12, 3:20] *= 1e-4  # below COHERENCE_MIN
    weights = torch.rand(300, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    weights[::9] = 0
    g1, g2 = leafs(g), leafs(g)
    a1, b1 = flow_terms(g1, cam, field, weights)
    a2, b2 = flow_terms_unfused(g2, cam, field, weights)
    assert_close(a1, a2, 1e-12, "alignment energy")
    assert_close(b1, b2, 1e-12, "anisotropy energy")
    names = ("means", "quats", "log_scales")
    grads1 = torch.autograd.grad(a1 + 0.3 * b1, [getattr(g1, f) for f in names])
    grads2 = torch.autograd.grad(a2 + 0.3 * b2, [getattr(g2, f) for f in names])
    for f, ga, gb in zip(names, grads1, grads2):
        assert_close(ga, gb, 1e-12, f"d/d{f}")
    # float32 (the loop's dtype) against the float64 energies
    g3 = leafs(g.to(dtype=torch.float32))
    a3, b3 = flow_terms(g3, cam, field.float(), weights.float())
    assert abs(a3.item() - a1.item()) < 1e-5 and abs(b3.item() - b1.item()) < 1e-4 * max(1.0, abs(b1.item()))


def test_flow_functions_live_in_autograd_and_stay_importable_from_flow():
    """The flow energies' autograd Functions are tlvg_warp.autograd's (the raster layer's one module of them);
    tlvg_warp.flow re-exports the same objects, and its coherence threshold is the targets kernel's."""
    from tlvg_warp import autograd, flow
    from tlvg_warp.kernels import flow as flow_kernels

    assert flow.FlowEnergiesFn is autograd.FlowEnergiesFn and flow.FlowTermsFn is autograd.FlowTermsFn
    assert autograd.FlowEnergiesFn.__module__ == autograd.FlowTermsFn.__module__ == "tlvg_warp.autograd"
    assert flow.COHERENCE_MIN == autograd.COHERENCE_MIN == flow_kernels.COHERENCE_MIN
