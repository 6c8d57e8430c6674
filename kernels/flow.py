"""Flow terms of the method (paper eq. 1 and its anisotropy energy, SPEC §3), per Gaussian:

  align_i = 1 − |⟨d_i, t_i⟩|      d_i: major axis of the projected footprint Σ2D, t_i: target stroke direction
  aniso_i = (nᵀΣ2D n)/(tᵀΣ2D t) + λmin/λmax       n ⟂ t

written with the doubled angle so that no eigenvector is ever formed: for Σ2D = [[a, b], [b, c]],
cos 2(φ − θ) = ((a − c) cos 2θ + 2b sin 2θ) / sqrt((a − c)² + 4b²) and |cos(φ − θ)| = sqrt((1 + cos 2(φ − θ)) / 2).
Warp generates the adjoint (to means, quats and log_scales through Σ2D).

``flow_targets_kernel`` computes what those terms are measured against: each Gaussian's target direction at its
projected center (a bilinear sample of the view's doubled-angle field, border padding), its coherence and weight.
(No ``from __future__ import annotations`` here: Warp reads the kernels' annotations as objects.)"""
import functools

import warp as wp

from .camera import camera_struct
from .projection import EWA_BLUR

COHERENCE_MIN = 1e-3  # below this the painting has no direction to follow at that spot
ISO_EPS = 1e-12  # keeps an exactly isotropic footprint (no major axis) at a finite, zero-ish gradient


def make_flow_terms(scalar, module: str, ewa_cov2d, camera_t):
    """The energies kernel for ``scalar`` in ``module``; ``camera_t``: ``camera.camera_struct`` of that type."""
    vec2 = wp.types.vector(2, scalar)
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)

    @wp.kernel(module=module)
    def flow_terms_kernel(
        means: wp.array(dtype=vec3),  # [N]
        quats: wp.array(dtype=vec4),  # [N]
        log_scales: wp.array(dtype=vec3),  # [N]
        target: wp.array(dtype=vec2),  # [N] (cos 2θ, sin 2θ) of the stroke direction at the Gaussian's center
        active: wp.array(dtype=wp.int32),  # [N] 1 where the term applies (visible, finite, coherent field)
        cam: camera_t,
        align: wp.array(dtype=scalar),  # [N] out
        aniso: wp.array(dtype=scalar),  # [N] out
    ):
        i = wp.tid()
        if active[i] == 0:
            return
        ls = log_scales[i]
        s = vec3(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
        S2 = ewa_cov2d(cam.R * means[i] + cam.t, quats[i], s, cam.R, cam.fx, cam.fy, cam.width, cam.height)
        a = S2[0, 0] + scalar(EWA_BLUR)
        b = S2[0, 1]
        c = S2[1, 1] + scalar(EWA_BLUR)
        c2 = target[i][0]
        s2 = target[i][1]
        amc = a - c
        r = wp.sqrt(amc * amc + scalar(4.0) * b * b + scalar(ISO_EPS))
        cos2 = (amc * c2 + scalar(2.0) * b * s2) / r
        align[i] = scalar(1.0) - wp.sqrt(wp.max(scalar(0.5) * (scalar(1.0) + cos2), scalar(0.0)) + scalar(ISO_EPS))
        # t = (cos θ, sin θ): tᵀΣt = ½(a + c) + ½(a − c)cos 2θ + b sin 2θ, and nᵀΣn the same with a minus
        along = scalar(0.5) * (a + c) + scalar(0.5) * amc * c2 + b * s2
        across = scalar(0.5) * (a + c) - scalar(0.5) * amc * c2 - b * s2
        mid = scalar(0.5) * (a + c)
        half = scalar(0.5) * r
        aniso[i] = across / along + (mid - half) / (mid + half)

    return flow_terms_kernel


@functools.lru_cache(maxsize=None)
def flow_targets_kernel(scalar_name: str):
    """Per Gaussian: its projected center's target direction, whether the terms apply there, and its weight
    (coherence x blend weight), no gradient: tlvg_warp.flow's ``flow_targets`` and its weights as one kernel
    (a Warp module of its own per scalar type, built once per process)."""
    scalar = {"float32": wp.float32, "float64": wp.float64}[scalar_name]
    vec2 = wp.types.vector(2, scalar)
    vec3 = wp.types.vector(3, scalar)
    camera_t = camera_struct(scalar_name)

    @wp.kernel(module=f"tlvg_flow_targets_{scalar_name}")
    def targets_kernel(
        means: wp.array(dtype=vec3),  # [N]
        log_scales: wp.array(dtype=vec3),  # [N]
        weights: wp.array(dtype=scalar),  # [N] Σ αT in this view
        field: wp.array3d(dtype=scalar),  # [Hf, Wf, >=2] doubled-angle field c·(cos 2θ, sin 2θ)
        cam: camera_t,
        coh_min: scalar,
        target: wp.array(dtype=vec2),  # [N] out: (cos 2θ, sin 2θ) at the projected center (0 where inactive)
        active: wp.array(dtype=wp.int32),  # [N] out
        w: wp.array(dtype=scalar),  # [N] out: coherence x weight, 0 where inactive
    ):
        i = wp.tid()
        target[i] = vec2(scalar(0.0), scalar(0.0))
        active[i] = 0
        w[i] = scalar(0.0)
        mu = means[i]
        if not (wp.isfinite(mu) and wp.isfinite(log_scales[i])):
            return
        p = cam.R * mu + cam.t
        z = p[2]
        if not (z > cam.near):
            return
        u = cam.fx * p[0] / z + cam.cx
        v = cam.fy * p[1] / z + cam.cy
        if not (u >= scalar(0.0) and u < scalar(cam.width) and v >= scalar(0.0) and v < scalar(cam.height)):
            return
        # grid_sample(bilinear, align_corners=False, padding border) of the field at pixel (u, v) of the view
        hf = field.shape[0]
        wf = field.shape[1]
        ix = wp.clamp(u * scalar(wf) / scalar(cam.width) - scalar(0.5), scalar(0.0), scalar(wf - 1))
        iy = wp.clamp(v * scalar(hf) / scalar(cam.height) - scalar(0.5), scalar(0.0), scalar(hf - 1))
        x0 = int(wp.floor(ix))
        y0 = int(wp.floor(iy))
        ax = ix - scalar(x0)
        ay = iy - scalar(y0)
        x1 = wp.min(x0 + 1, wf - 1)  # its weight is 0 when x0 is the last column
        y1 = wp.min(y0 + 1, hf - 1)
        w00 = (scalar(1.0) - ax) * (scalar(1.0) - ay)
        w01 = ax * (scalar(1.0) - ay)
        w10 = (scalar(1.0) - ax) * ay
        w11 = ax * ay
        vx = w00 * field[y0, x0, 0] + w01 * field[y0, x1, 0] + w10 * field[y1, x0, 0] + w11 * field[y1, x1, 0]
        vy = w00 * field[y0, x0, 1] + w01 * field[y0, x1, 1] + w10 * field[y1, x0, 1] + w11 * field[y1, x1, 1]
        coh = wp.sqrt(vx * vx + vy * vy)
        if not (coh > coh_min):
            return
        target[i] = vec2(vx / coh, vy / coh)
        active[i] = 1
        w[i] = wp.max(coh * weights[i], scalar(0.0))  # Σ w is torch's sum: one address for every thread's
        # atomic add made this kernel 0.56 ms of a fern stylize step on the GPU

    return targets_kernel
