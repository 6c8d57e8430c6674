"""Bridge between torch tensors and the Warp raster kernels: one op per pipeline stage (project, bin,
blend) and the autograd Function that carries them on one Warp tape.

Gradients: Warp generates the projection/SH adjoint; the blending backward is hand-written and registered
on the same tape with ``Tape.record_func``. Every Warp array gets its own torch-allocated grad buffer
(Warp never writes into a torch ``.grad``, which would double count)."""
from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass

import torch
import warp as wp

from .types import Camera

TILE = 16

_initialized = False


def init_warp() -> None:
    global _initialized
    if not _initialized:
        wp.config.quiet = os.environ.get("TLVG_WARP_VERBOSE", "") == ""
        wp.init()
        _initialized = True


def kernels_for(dtype: torch.dtype):
    init_warp()
    from .kernels import raster_kernels

    return raster_kernels({torch.float32: "float32", torch.float64: "float64"}[dtype])


@contextlib.contextmanager
def warp_on(device: torch.device):
    """Run Warp launches on torch's current stream so no extra synchronization is needed."""
    if device.type == "cuda":
        with wp.ScopedStream(wp.stream_from_torch(device)):
            yield wp.device_from_torch(device)
    else:
        yield wp.device_from_torch(device)


def ct(t: torch.Tensor, dtype=None):
    """A bare array descriptor for launches outside the tape (skips building a wp.array: less Python per call)."""
    return wp.from_torch(t.detach(), dtype=dtype, return_ctype=True)


def to_warp(t: torch.Tensor, dtype, grad: torch.Tensor | None = None):
    if t.numel() == 0:  # torch gives empty tensors arbitrary strides, which from_torch rejects
        n = t.shape[0]
        dev = wp.device_from_torch(t.device)
        arr = wp.zeros(n, dtype=dtype, device=dev, requires_grad=grad is not None)
        return arr
    return wp.from_torch(t.detach().contiguous(), dtype=dtype, grad=grad, requires_grad=grad is not None)


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities (torch views of the Warp outputs)."""

    means2d: torch.Tensor  # [N, 2]
    cov2d: torch.Tensor  # [N, 3] (a, b, c) of Σ2D
    conic: torch.Tensor  # [N, 3] (a, b, c) of Σ2D⁻¹
    depth: torch.Tensor  # [N]
    opacity: torch.Tensor  # [N]
    color: torch.Tensor  # [N, 3]
    radii: torch.Tensor  # [N] int32


def camera_args(cam: Camera, K, device: torch.device):
    """(R, t, fx, fy, cx, cy, width, height, near, far) as kernel values (array reads would become atomics in
    the adjoint); ``camera_center`` gives the center."""
    s = K.scalar
    R = cam.R.tolist()
    t = cam.t.tolist()
    return [K.mat33(*[s(v) for row in R for v in row]), K.vec3(*map(s, t)),
            s(cam.fx), s(cam.fy), s(cam.cx), s(cam.cy), cam.width, cam.height, s(cam.near), s(cam.far)]


def camera_center(cam: Camera, K):
    return K.vec3(*map(K.scalar, cam.center.tolist()))


def project(K, wargs, cam: Camera, sh_degree: int, n: int, dtype, device, tape: wp.Tape | None):
    """Launch projection (Warp-generated adjoint) and SH color (hand-written backward, see sh_backward_kernel);
    returns (Projected, warp output arrays)."""
    z = lambda *shape: torch.zeros(*shape, dtype=dtype, device=device)  # noqa: E731
    proj = Projected(z(n, 2), z(n, 3), z(n, 3), z(n), z(n), z(n, 3), torch.zeros(n, dtype=torch.int32, device=device))
    need_grad = tape is not None
    outs = [
        to_warp(proj.means2d, K.vec2, z(n, 2) if need_grad else None),
        to_warp(proj.cov2d, K.vec3),  # binning only: no gradient flows through it
        to_warp(proj.conic, K.vec3, z(n, 3) if need_grad else None),
        to_warp(proj.depth, K.scalar, z(n) if need_grad else None),
        to_warp(proj.opacity, K.scalar, z(n) if need_grad else None),
        to_warp(proj.color, K.vec3, z(n, 3) if need_grad else None),
        wp.from_torch(proj.radii, dtype=wp.int32),
    ]
    wdev = wp.device_from_torch(device)
    w_means, _q, _s, _o, w_sh = wargs
    geometry_outs = outs[:5] + outs[6:]
    with (tape if tape is not None else contextlib.nullcontext()):
        wp.launch(K.project, dim=n, inputs=wargs[:4] + camera_args(cam, K, device), outputs=geometry_outs,
                  device=wdev)
    center = camera_center(cam, K)
    sh_args = [w_means, w_sh, outs[6], center, sh_degree]
    if n:
        wp.launch(K.sh_color, dim=n, inputs=sh_args, outputs=[outs[5]], device=wdev, record_tape=False)
    if tape is not None:
        w_color = outs[5]

        n_coeffs = (sh_degree + 1) ** 2

        def sh_backward():
            if n:  # before the projection adjoint (tape order): its means gradient is a plain store
                g_rgb = torch.empty(n, 3, dtype=dtype, device=device)  # [N, 3]
                basis = torch.empty(n, n_coeffs, dtype=dtype, device=device)  # [N, K]
                wp.launch(K.sh_backward, dim=n, inputs=sh_args + [w_color.grad],
                          outputs=[ct(g_rgb, K.vec3), ct(basis), w_means.grad], device=wdev)
                g_sh = wp.to_torch(w_sh.grad)  # [N, Kmax, 3] the torch buffer behind it; bands above stay 0
                torch.mul(basis[:, :, None], g_rgb[:, None, :], out=g_sh[:, :n_coeffs])

        tape.record_func(backward=sh_backward, arrays=[])
    return proj, outs


def bin_tiles(K, proj: Projected, width: int, height: int, all_tiles: bool = False):
    """Sorted (tile, depth) keys -> per-tile [start, end) ranges and the sorted Gaussian ids."""
    device = proj.depth.device
    wdev = wp.device_from_torch(device)
    n = proj.depth.shape[0]
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    if n == 0:
        return (torch.zeros(tiles_x * tiles_y, 2, dtype=torch.int32, device=device),
                torch.zeros(1, dtype=torch.int32, device=device), tiles_x, tiles_y)
    m2 = ct(proj.means2d.float().contiguous(), wp.vec2)
    radii = ct(proj.radii, wp.int32)
    shape = [ct(proj.cov2d.float().contiguous(), wp.vec3), ct(proj.conic.float().contiguous(), wp.vec3),
             ct(proj.opacity.float().contiguous())]
    counts = torch.empty(n, dtype=torch.int32, device=device)
    wp.launch(K.count_tiles, dim=n, inputs=[m2, radii, *shape, tiles_x, tiles_y, width, height, int(all_tiles)],
              outputs=[ct(counts)], device=wdev)
    ends = torch.cumsum(counts, 0, dtype=torch.int64)
    total = int(ends[-1])  # the one host sync per render: the key buffer size
    ranges = torch.zeros(tiles_x * tiles_y, 2, dtype=torch.int32, device=device)
    if total == 0:
        return ranges, torch.zeros(1, dtype=torch.int32, device=device), tiles_x, tiles_y
    if total >= 2**31:
        raise RuntimeError(f"{total} tile intersections exceed the int32 index range; render at a lower resolution")
    starts = (ends - counts).to(torch.int32)
    keys = torch.empty(2 * total, dtype=torch.int64, device=device)
    ids = torch.empty(2 * total, dtype=torch.int32, device=device)
    depth_bits = proj.depth.float().contiguous().view(torch.int32)  # z > 0: bit order == float order
    wkeys, wids = wp.from_torch(keys), wp.from_torch(ids)
    wp.launch(K.emit_keys, dim=n, inputs=[m2, radii, *shape, ct(depth_bits), ct(starts), ct(counts), tiles_x,
                                          tiles_y, width, height, int(all_tiles)], outputs=[wkeys, wids], device=wdev)
    tile_bits = max(1, (tiles_x * tiles_y).bit_length())  # room for the sentinel tile id
    wp.utils.radix_sort_pairs(wkeys, wids, total, 0, 32 + tile_bits)  # only the bits keys use
    wp.launch(K.tile_ranges, dim=total, inputs=[wkeys, total], outputs=[ct(ranges)], device=wdev)
    return ranges, ids[:total], tiles_x, tiles_y


class RasterizeFn(torch.autograd.Function):
    """(means, quats, log_scales, opacity_logits, sh, means2d_probe) -> color, alpha, depth, radii, weights.

    ``means2d_probe`` is a zero tensor whose gradient receives dL/d(screen mean) for density control."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, sh, means2d_probe, cam, settings):
        K = kernels_for(means.dtype)
        device, dtype, n = means.device, means.dtype, means.shape[0]
        H, W = cam.height, cam.width
        with warp_on(device) as wdev:
            grads = [torch.zeros_like(t) for t in (means, quats, log_scales, opacity_logits, sh)]
            wargs = [to_warp(means, K.vec3, grads[0]), to_warp(quats, K.vec4, grads[1]),
                     to_warp(log_scales, K.vec3, grads[2]), to_warp(opacity_logits, K.scalar, grads[3]),
                     to_warp(sh, K.vec3, grads[4])]
            tape = wp.Tape()
            proj, pouts = project(K, wargs, cam, settings["sh_degree"], n, dtype, device, tape)
            ranges, ids, tiles_x, tiles_y = bin_tiles(K, proj, W, H, settings["all_tiles"])
            color = torch.empty(H, W, 3, dtype=dtype, device=device)
            alpha = torch.empty(H, W, dtype=dtype, device=device)
            depth = torch.empty(H, W, dtype=dtype, device=device)
            T = torch.empty(H, W, dtype=dtype, device=device)
            last = torch.empty(H, W, dtype=torch.int32, device=device)
            weights = torch.zeros(n if settings["weights"] else 1, dtype=dtype, device=device)
            bg = K.vec3(*map(K.scalar, settings["background"]))
            w_means2d, _w_cov2d, w_conic, w_depth, w_opacity, w_color, _w_radii = pouts
            blend_args = [ct(ranges), ct(ids), w_means2d, w_conic, w_opacity, w_color, w_depth,
                          bg, W, H, tiles_x]
            wp.launch(K.blend_forward, dim=tiles_x * tiles_y * TILE * TILE, block_dim=TILE * TILE,
                      inputs=blend_args + [int(settings["weights"])],
                      outputs=[ct(color, K.vec3), ct(alpha), ct(depth), ct(T), ct(last), ct(weights)],
                      device=wdev, record_tape=False)
            n_threads = tiles_x * tiles_y * TILE * TILE
            io = {}  # filled by backward(): upstream gradients in, dL/d(screen mean) out

            def blend_backward():
                wp.launch(K.blend_backward, dim=n_threads, block_dim=TILE * TILE,
                          inputs=blend_args + [ct(depth), ct(T), ct(last), *io["upstream"]],
                          outputs=[a.grad for a in blend_args[2:7]], device=wdev)
                # the projection adjoint consumes (zeroes) its output grads: keep dL/d(screen mean) first
                io["screen"] = wp.to_torch(w_means2d.grad).clone()

            tape.record_func(backward=blend_backward, arrays=[])
        ctx.state = (K, tape, wargs, pouts, grads, io, device)
        ctx.image_size = (H, W)
        ctx.mark_non_differentiable(proj.radii, weights)
        return color, alpha, depth, proj.radii, weights if settings["weights"] else None

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, _g_radii, _g_weights):
        K, tape, wargs, pouts, grads, io, device = ctx.state
        if "screen" in io:
            # a second backward through the same graph (gradcheck, retain_graph): fresh input buffers, since
            # the first call's may be held by the caller, and cleared intermediates
            for i, a in enumerate(wargs):
                grads[i] = torch.zeros_like(grads[i])
                a.grad = wp.from_torch(grads[i], dtype=a.dtype)
            for a in pouts[:6]:
                if a.grad is not None:
                    a.grad.zero_()
        H, W = ctx.image_size
        dtype = grads[0].dtype
        ups = [g.contiguous() if g is not None else torch.zeros(shape, dtype=dtype, device=device)
               for g, shape in ((g_color, (H, W, 3)), (g_alpha, (H, W)), (g_depth, (H, W)))]
        io["upstream"] = [ct(ups[0], K.vec3), ct(ups[1]), ct(ups[2])]
        with warp_on(device):
            tape.backward()
        return (*grads, io["screen"], None, None)
