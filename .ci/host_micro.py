"""Host cost of the pieces before a render's first kernel (development aid): microseconds per call, median."""
import statistics
import time

import torch
import warp as wp

import tlvg_warp.ops as ops
from tlvg_warp import render
from tlvg_warp.eval.bench_raster import bench_camera, random_scene
from tlvg_warp.renderer import check_inputs

dev = torch.device("cuda")
g = random_scene(1000, -4.0, 3, dev)
cam = bench_camera(64, 48)
K = ops.kernels_for(torch.float32)
render(g, cam)
torch.cuda.synchronize()


def t(name, f, n=300):
    for _ in range(20):
        f()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t0)
    print(f"{name:40s} {statistics.median(ts) * 1e6:8.1f} us")


ins = (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)
tys = (K.vec3, K.vec4, K.vec3, K.scalar, K.vec3)
t("check_inputs", lambda: check_inputs(g, cam, None))
t("probe zeros+expand", lambda: torch.zeros(1, 2, device=dev).expand(1000, 2).detach().requires_grad_(True))
t("warp_on enter/exit", lambda: ops.warp_on(dev).__enter__() and None)


def wo():
    with ops.warp_on(dev):
        pass


t("warp_on with-block", wo)
t("stream_from_torch", lambda: wp.stream_from_torch(dev))
t("to_warp x5", lambda: [ops.to_warp(x, ty) for x, ty in zip(ins, tys)])
t("ct x5", lambda: [ops.ct(x, ty) for x, ty in zip(ins, tys)])
t("camera_values", lambda: ops.camera_values(cam))
cv = ops.camera_values(cam)
t("camera_args", lambda: ops.camera_args(cam, K, cv))
t("packed_zeros 5", lambda: ops.packed_zeros([(1000, 2), (1000, 3), (1000,), (1000,), (1000, 3)], torch.float32, dev))
t("torch.zeros", lambda: torch.zeros(1000, device=dev))
t("wp.Tape()", lambda: wp.Tape())
wargs = [ops.to_warp(x, ty) for x, ty in zip(ins, tys)]
outs = [ops.to_warp(torch.zeros(1000, 2, device=dev), K.vec2), ops.to_warp(torch.zeros(1000, 3, device=dev), K.vec3),
        ops.to_warp(torch.zeros(1000, device=dev), K.scalar), ops.to_warp(torch.zeros(1000, device=dev), K.scalar),
        wp.from_torch(torch.zeros(1000, dtype=torch.int32, device=dev), dtype=wp.int32)]
ca = ops.camera_args(cam, K, cv)
with ops.warp_on(dev) as wdev:
    t("wp.launch project (19 args)", lambda: wp.launch(K.project, dim=1000, inputs=wargs[:4] + ca, outputs=outs,
                                                       device=wdev))
    tape = wp.Tape()

    def taped():
        with tape:
            wp.launch(K.project, dim=1000, inputs=wargs[:4] + ca, outputs=outs, device=wdev)
        tape.reset()
    t("taped launch project", taped)
    cts = [ops.ct(x) for x in (torch.zeros(1000, 2, device=dev), )]
t("render fwd (1000 G, 64x48)", lambda: render(g, cam))
gp = g.to(dev)
