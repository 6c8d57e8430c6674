"""Flow terms of the method (paper eq. 1 and its anisotropy energy, SPEC §3), per Gaussian:

  align_i = 1 − |⟨d_i, t_i⟩|      d_i: major axis of the projected footprint Σ2D, t_i: target stroke direction
  aniso_i = (nᵀΣ2D n)/(tᵀΣ2D t) + λmin/λmax       n ⟂ t

written with the doubled angle so that no eigenvector is ever formed: for Σ2D = [[a, b], [b, c]],
cos 2(φ − θ) = ((a − c) cos 2θ + 2b sin 2θ) / sqrt((a − c)² + 4b²) and |cos(φ − θ)| = sqrt((1 + cos 2(φ − θ)) / 2).
Warp generates the adjoint (to means, quats and log_scales through Σ2D)."""
import warp as wp

from .projection import EWA_BLUR

ISO_EPS = 1e-12  # keeps an exactly isotropic footprint (no major axis) at a finite, zero-ish gradient


def make_flow_terms(scalar, module: str, ewa_cov2d):
    vec2 = wp.types.vector(2, scalar)
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

    @wp.kernel(module=module)
    def flow_terms_kernel(
        means: wp.array(dtype=vec3),  # [N]
        quats: wp.array(dtype=vec4),  # [N]
        log_scales: wp.array(dtype=vec3),  # [N]
        target: wp.array(dtype=vec2),  # [N] (cos 2θ, sin 2θ) of the stroke direction at the Gaussian's center
        active: wp.array(dtype=wp.int32),  # [N] 1 where the term applies (visible, finite, coherent field)
        R: mat33,
        t: vec3,
        fx: scalar,
        fy: scalar,
        width: int,
        height: int,
        align: wp.array(dtype=scalar),  # [N] out
        aniso: wp.array(dtype=scalar),  # [N] out
    ):
        i = wp.tid()
        if active[i] == 0:
            return
        ls = log_scales[i]
        s = vec3(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
        S2 = ewa_cov2d(R * means[i] + t, quats[i], s, R, fx, fy, width, height)
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
