"""Rasterizer speed benchmark: tlvg_warp against gsplat and gswarp (when importable) in the same run.

Times forward and forward+backward (median of R after warm-up), checks image parity against gsplat (mean
absolute difference) and reports peak memory. Absolute times mean something only on the GPU; on the CPU
this is a smoke run."""
from __future__ import annotations

import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from ..renderer import render
from ..types import Camera, Gaussians


def random_scene(n: int, log_scale: float, degree: int, device, seed: int = 0) -> Gaussians:
    """n Gaussians uniform in a unit cube 3 units in front of the camera (the peer figures' setup)."""
    gen = torch.Generator(device="cpu").manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=gen)  # noqa: E731
    means = torch.rand(n, 3, generator=gen) * 2 - 1
    g = Gaussians(means, r(n, 4), r(n, 3) * 0.3 + log_scale, r(n), r(n, (degree + 1) ** 2, 3) * 0.2)
    return g.to(device)


def bench_camera(width: int, height: int) -> Camera:
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[2, 3] = 3.0
    f = 0.5 * width / math.tan(math.radians(30))
    return Camera(w2c, f, f, width / 2, height / 2, width, height)


def garden_scene(path: Path, device, degree: int):
    d = np.load(path)
    means = torch.from_numpy(d["means3d"]).float()
    n = means.shape[0]
    rgb = torch.from_numpy(d["colors"]).float() / 255.0
    # scales from the spacing of the points: the mean nearest-neighbour distance of a random sample
    sample = means[torch.randperm(n, generator=torch.Generator().manual_seed(0))[:4096]]
    nn = torch.cdist(sample, sample).topk(4, largest=False).values[:, 1:].mean()
    g = Gaussians.from_colors(means, rgb, float(nn), opacity=0.8, degree=degree)
    K = d["Ks"][0]
    H, W = int(round(K[1, 2] * 2)), int(round(K[0, 2] * 2))
    cam = Camera(torch.from_numpy(d["viewmats"][0]).double(), K[0, 0], K[1, 1], K[0, 2], K[1, 2], W, H)
    return g.to(device), cam


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_fn(fn, device, repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    _sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def peak_mb(fn, device) -> float:
    if device.type != "cuda":
        return float("nan")
    import warp as wp

    _sync(device)
    torch.cuda.reset_peak_memory_stats(device)
    base = torch.cuda.memory_allocated(device)
    wp_base = wp.get_mempool_used_mem_current(f"cuda:{device.index or 0}")
    fn()
    _sync(device)
    torch_peak = torch.cuda.max_memory_allocated(device) - base
    wp_peak = wp.get_mempool_used_mem_high(f"cuda:{device.index or 0}") - wp_base
    return (torch_peak + max(wp_peak, 0)) / 2**20


# -- the three rasterizers behind one signature: (g, cam) -> (forward(), forward_backward(), image) ------------

def ours(g: Gaussians, cam: Camera):
    params = [t.detach().clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
    gp = Gaussians(*params)
    up = torch.rand(cam.height, cam.width, 3, device=g.device)

    def fwd():
        with torch.no_grad():
            return render(gp, cam).color

    def fwd_bwd():
        out = render(gp, cam)
        (out.color * up).sum().backward()

    return fwd, fwd_bwd, fwd


def gsplat_peer(g: Gaussians, cam: Camera):
    from gsplat import rasterization

    params = [t.detach().clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
    view = cam.world_to_camera.float().to(g.device)[None]
    K = cam.K.float().to(g.device)[None]
    up = torch.rand(cam.height, cam.width, 3, device=g.device)

    def run():
        m, q, ls, ol, sh = params
        img, _, _ = rasterization(m, q, torch.exp(ls), torch.sigmoid(ol), sh, view, K, cam.width, cam.height,
                                  sh_degree=g.sh_degree, packed=False)
        return img[0]

    def fwd():
        with torch.no_grad():
            return run()

    def fwd_bwd():
        (run() * up).sum().backward()

    return fwd, fwd_bwd, fwd


def gswarp_peer(g: Gaussians, cam: Camera):
    from gswarp import GaussianRasterizationSettings, GaussianRasterizer

    dev = g.device
    params = [t.detach().clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]
    tanx, tany = 0.5 * cam.width / cam.fx, 0.5 * cam.height / cam.fy
    znear, zfar = cam.near, 100.0
    P = torch.zeros(4, 4)
    P[0, 0], P[1, 1] = 1 / tanx, 1 / tany
    P[3, 2], P[2, 2], P[2, 3] = 1.0, zfar / (zfar - znear), -(zfar * znear) / (zfar - znear)
    view = cam.world_to_camera.float().T.contiguous().to(dev)
    proj = (view @ P.T.to(dev)).contiguous()
    settings = GaussianRasterizationSettings(
        image_height=cam.height, image_width=cam.width, tanfovx=tanx, tanfovy=tany, bg=torch.zeros(3, device=dev),
        scale_modifier=1.0, viewmatrix=view, projmatrix=proj, sh_degree=g.sh_degree,
        campos=cam.center.float().to(dev), prefiltered=False, debug=False, auto_tune_verbose=False)
    raster = GaussianRasterizer(settings)
    up = torch.rand(3, cam.height, cam.width, device=dev)

    def run():
        m, q, ls, ol, sh = params
        screen = torch.zeros_like(m, requires_grad=True)
        out = raster(means3D=m, means2D=screen, opacities=torch.sigmoid(ol)[:, None], shs=sh,
                     scales=torch.exp(ls), rotations=torch.nn.functional.normalize(q, dim=-1))
        return out[0] if isinstance(out, (tuple, list)) else out

    def fwd():
        with torch.no_grad():
            return run().permute(1, 2, 0)

    def fwd_bwd():
        (run() * up).sum().backward()

    return fwd, fwd_bwd, fwd


PEERS = {"tlvg_warp": ours, "gsplat": gsplat_peer, "gswarp": gswarp_peer}


def warm_step(peer: str, n: int, device, warmup: int = 5):
    """The forward+backward step of ``peer`` on the 1008x756 random scene of ``n`` Gaussians, warmed up (kernels
    compiled, allocator primed): what the .ci profilers time."""
    _, step, _ = PEERS[peer](random_scene(n, -4.0, 3, device), bench_camera(1008, 756))
    for _ in range(warmup):
        step()
    _sync(device)
    return step


def run_bench(cases, device, repeats: int, peers=("tlvg_warp", "gsplat", "gswarp"), log=print) -> list[dict]:
    rows = []
    for case_name, (g, cam) in cases:
        images = {}
        for peer in peers:
            row = {"case": case_name, "peer": peer, "n": g.num, "size": f"{cam.width}x{cam.height}"}
            try:
                fwd, fwd_bwd, image = PEERS[peer](g, cam)
                row["fwd_ms"] = time_fn(fwd, device, repeats)
                row["fwd_bwd_ms"] = time_fn(fwd_bwd, device, repeats)
                row["peak_mb"] = peak_mb(fwd_bwd, device)
                images[peer] = image().detach().float()
            except ImportError as e:
                row["error"] = f"not importable: {e.name}"
            except Exception as e:  # a peer failing (e.g. out of memory) must not end the run
                row["error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:120] if str(e) else ''}"
            rows.append(row)
            log(row)
            if device.type == "cuda":
                torch.cuda.empty_cache()
        ref = images.get("gsplat")
        for row in rows[-len(peers):]:
            if ref is not None and row["peer"] in images:
                row["mad_vs_gsplat"] = (images[row["peer"]] - ref).abs().mean().item()
        base = next((r for r in rows[-len(peers):] if r["peer"] == "tlvg_warp" and "fwd_ms" in r), None)
        for row in rows[-len(peers):]:
            if base and "fwd_ms" in row:
                row["fwd_ratio"] = row["fwd_ms"] / base["fwd_ms"]
                row["fwd_bwd_ratio"] = row["fwd_bwd_ms"] / base["fwd_bwd_ms"]
    return rows


def format_table(rows) -> str:
    head = "| case | peer | fwd ms | fwd+bwd ms | fwd / ours | fwd+bwd / ours | peak MiB | MAD vs gsplat |"
    lines = [head, "|" + " --- |" * 8]
    f = lambda v, p=2: "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{p}f}"  # noqa: E731
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | {r['peer']} | {r['error']} | | | | | |")
            continue
        lines.append(f"| {r['case']} | {r['peer']} | {f(r['fwd_ms'])} | {f(r['fwd_bwd_ms'])} | {f(r.get('fwd_ratio'))} "
                     f"| {f(r.get('fwd_bwd_ratio'))} | {f(r['peak_mb'], 0)} | {f(r.get('mad_vs_gsplat'), 4)} |")
    return "\n".join(lines)
