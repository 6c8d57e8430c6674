"""Rasterizer speed benchmark: tlvg_warp against gsplat and gswarp (when importable) in the same run.

Cases: random scenes (one camera), the garden points, and fitted scenes (``--scene PLY[:DATASET[:IMAGES]]``:
every view of the dataset, or orbit views around a PLY alone). Per case and rasterizer: forward and
forward+backward wall time (the median over views of each view's median of R after warm-up, the peers
interleaved view by view), peak memory (the largest over the views), image parity against gsplat (mean
absolute difference, mean over views), and on the GPU the kernel time per render split into stages
(projection, SH, binning, sorts, blending; CUPTI through torch.profiler over every view). For our rasterizer
the per-pixel list lengths show the regime: intersections per render, Gaussians binned per tile and walked per
pixel (mean and max). Absolute times mean something only on the GPU; on the CPU this is a smoke run.

Ours renders without the expected depth (``render(depth=False)``) unless asked: gsplat's RGB mode computes none."""
from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

from ..errors import InputError
from ..io.datasets import load_dataset
from ..io.ply import load_ply
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
    d = np.load(path, allow_pickle=False)
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


def orbit_cameras(g: Gaussians, n: int, width: int, height: int, fov_deg: float = 50.0) -> list[Camera]:
    """n views on a circle around a scene with no dataset: looking at the median of the means from twice the
    90th-percentile distance to it, in the plane of the two widest axes of the means."""
    m = g.means.detach().double().cpu()
    center = m.median(0).values
    spread = (m - center).norm(dim=1).quantile(0.9).item() if m.shape[0] > 1 else 1.0
    axes = torch.linalg.svd(m - center, full_matrices=False).Vh if m.shape[0] > 2 else torch.eye(3, dtype=torch.float64)
    a, b, up = axes[0], axes[1], axes[2]
    cams = []
    for k in range(n):
        t = 2 * math.pi * k / n
        eye = center + 2.0 * max(spread, 1e-3) * (math.cos(t) * a + math.sin(t) * b + 0.3 * up)
        cams.append(Camera.look_at(eye.tolist(), center.tolist(), up=up.tolist(), fov_deg=fov_deg, width=width,
                                   height=height))
    return cams


@dataclass
class Case:
    name: str
    g: Gaussians
    cams: list = field(default_factory=list)  # every view timed; random and garden cases have one


def scene_case(spec: str, device, max_views: int | None = None, orbit_size=(1008, 756)) -> Case:
    """``PLY[:DATASET[:IMAGES]]``: the fitted scene and every view of its dataset (IMAGES: the photo folder
    whose size the views take, e.g. images_4), or orbit views (8, ``orbit_size``) when no dataset is given."""
    parts = spec.split(":")
    if len(parts) > 3 or not parts[0]:
        raise InputError(f"--scene wants PLY[:DATASET[:IMAGES]], got {spec!r}")
    ply = Path(parts[0])
    g = load_ply(ply).to(device)
    if len(parts) > 1 and parts[1]:
        cams = list(load_dataset(parts[1], images=parts[2] if len(parts) > 2 and parts[2] else None).cameras)
        where = Path(parts[1]).name
    else:
        cams = orbit_cameras(g, 8, *orbit_size)
        where = "orbit"
    cams = cams[:max_views] if max_views else cams
    name = f"{ply.parent.name or ply.stem}/{ply.name} ({g.num:,} G, SH {g.sh_degree}, {where} {len(cams)} views " \
           f"{cams[0].width}x{cams[0].height})"
    return Case(name, g, cams)


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
    # lazy: imports Warp
    import warp as wp

    _sync(device)
    torch.cuda.reset_peak_memory_stats(device)
    base = torch.cuda.memory_allocated(device)
    # Warp's pool keeps a process-wide high-water mark that cannot be reset: count only what this call adds to it
    # (a peer run earlier in the process, e.g. gswarp on another view, must not show in the next one's figure)
    wp_base = wp.get_mempool_used_mem_high(f"cuda:{device.index or 0}")
    fn()
    _sync(device)
    torch_peak = torch.cuda.max_memory_allocated(device) - base
    wp_peak = wp.get_mempool_used_mem_high(f"cuda:{device.index or 0}") - wp_base
    return (torch_peak + max(wp_peak, 0)) / 2**20


# -- the three rasterizers behind one signature: peer(g, **options) -> view(cam) -> (forward(), forward_backward(),
# image()). The parameters are copied once per scene; a view only builds its camera's closures. ---------------------

def _leaf_params(g: Gaussians):
    return [t.detach().clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh)]


def ours_views(g: Gaussians, depth: bool = False):
    gp = Gaussians(*_leaf_params(g))

    def view(cam: Camera):
        up = torch.rand(cam.height, cam.width, 3, device=g.device)

        def fwd():
            with torch.no_grad():
                return render(gp, cam, depth=depth).color

        def fwd_bwd():  # holds no output through the backward, as the peers' steps hold none
            (render(gp, cam, depth=depth).color * up).sum().backward()

        return fwd, fwd_bwd, fwd

    return view


def gsplat_views(g: Gaussians, depth: bool = False):
    # lazy: an optional peer (gsplat)
    from gsplat import rasterization

    params = _leaf_params(g)

    def view(cam: Camera):
        viewmat = cam.world_to_camera.float().to(g.device)[None]
        K = cam.K.float().to(g.device)[None]
        up = torch.rand(cam.height, cam.width, 3, device=g.device)

        def run():
            m, q, ls, ol, sh = params
            img, _, _ = rasterization(m, q, torch.exp(ls), torch.sigmoid(ol), sh, viewmat, K, cam.width, cam.height,
                                      sh_degree=g.sh_degree, packed=False)
            return img[0]

        def fwd():
            with torch.no_grad():
                return run()

        def fwd_bwd():
            (run() * up).sum().backward()

        return fwd, fwd_bwd, fwd

    return view


def gswarp_views(g: Gaussians, depth: bool = False):
    # lazy: an optional peer (gswarp)
    from gswarp import GaussianRasterizationSettings, GaussianRasterizer

    dev = g.device
    params = _leaf_params(g)

    def view(cam: Camera):
        tanx, tany = 0.5 * cam.width / cam.fx, 0.5 * cam.height / cam.fy
        znear, zfar = cam.near, 100.0
        P = torch.zeros(4, 4)
        P[0, 0], P[1, 1] = 1 / tanx, 1 / tany
        P[3, 2], P[2, 2], P[2, 3] = 1.0, zfar / (zfar - znear), -(zfar * znear) / (zfar - znear)
        viewm = cam.world_to_camera.float().T.contiguous().to(dev)
        proj = (viewm @ P.T.to(dev)).contiguous()
        settings = GaussianRasterizationSettings(
            image_height=cam.height, image_width=cam.width, tanfovx=tanx, tanfovy=tany, bg=torch.zeros(3, device=dev),
            scale_modifier=1.0, viewmatrix=viewm, projmatrix=proj, sh_degree=g.sh_degree,
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

    return view


PEER_VIEWS = {"tlvg_warp": ours_views, "gsplat": gsplat_views, "gswarp": gswarp_views}


def _one_view(peer_views):
    return lambda g, cam: peer_views(g)(cam)


PEERS = {k: _one_view(v) for k, v in PEER_VIEWS.items()}  # peer(g, cam) -> (fwd, fwd_bwd, image): one view
ours, gsplat_peer, gswarp_peer = PEERS["tlvg_warp"], PEERS["gsplat"], PEERS["gswarp"]


def warm_step(peer: str, n: int, device, warmup: int = 5):
    """The forward+backward step of ``peer`` on the 1008x756 random scene of ``n`` Gaussians, warmed up (kernels
    compiled, allocator primed): what the .ci profilers time."""
    _, step, _ = PEERS[peer](random_scene(n, -4.0, 3, device), bench_camera(1008, 756))
    for _ in range(warmup):
        step()
    _sync(device)
    return step


# -- what the renders walk: our binning's list lengths ------------------------------------------------------------

def list_lengths(cap: dict) -> dict:
    """From one captured binning (raster.capture_binning): intersections, Gaussians binned per tile (mean over
    all tiles, max) and walked per pixel (one past the last contributor in its tile's list; mean, max)."""
    ranges, last = cap["ranges"], cap["last"]
    per_tile = (ranges[:, 1] - ranges[:, 0]).double()
    H, W = last.shape
    tiles_x = cap["tiles"][0]
    ys = torch.arange(H, device=last.device)[:, None] // 16
    xs = torch.arange(W, device=last.device)[None, :] // 16
    per_px = (last - ranges[ys * tiles_x + xs, 0]).double()
    return {"intersections": int(cap["total"]), "tile_mean": per_tile.mean().item(), "tile_max": int(per_tile.max()),
            "px_mean": per_px.mean().item(), "px_max": int(per_px.max())}


def scene_lists(g: Gaussians, cams) -> dict:
    """list_lengths over views: the mean of the means and the max of the maxima."""
    # lazy: imports Warp
    from ..raster import capture_binning

    per_view = []
    for cam in cams:
        with capture_binning() as cap, torch.no_grad():
            render(g, cam, depth=False)
        per_view.append(list_lengths(cap))
    mean = lambda k: statistics.mean(v[k] for v in per_view)  # noqa: E731
    return {"intersections": mean("intersections"), "intersections_max": max(v["intersections"] for v in per_view),
            "tile_mean": mean("tile_mean"), "tile_max": max(v["tile_max"] for v in per_view),
            "px_mean": mean("px_mean"), "px_max": max(v["px_max"] for v in per_view)}


# -- GPU time per stage (CUPTI kernel records through torch.profiler) ---------------------------------------------

STAGES = (  # first match wins; everything else is "other" (memsets, copies, torch element-wise ops, scans)
    ("blend bwd", ("blend_backward", "rasterize_to_pixels_3dgs_bwd", "renderCUDA_backward", "render_backward")),
    ("blend fwd", ("blend_forward", "rasterize_to_pixels_3dgs_fwd", "renderCUDA", "render_forward")),
    ("bin", ("count_tiles", "emit_keys", "tile_ranges", "intersect_tile", "intersect_offset", "duplicateWithKeys",
             "identifyTileRanges", "duplicate_with_keys", "identify_tile_ranges")),
    ("sort", ("radix", "Radix", "sort")),
    ("sh", ("sh_color", "sh_backward", "sh_coeff_grad", "spherical_harmonics", "computeColorFromSH", "sh_")),
    ("project", ("project", "projection", "preprocess")),
)
STAGE_NAMES = ("project", "sh", "bin", "sort", "blend fwd", "blend bwd", "other")


def stage_of(kernel: str) -> str:
    for stage, keys in STAGES:
        if any(k in kernel for k in keys):
            return stage
    return "other"


def gpu_stages(fns, device, reps: int = 2) -> dict:
    """Kernel time per call of ``fns`` (each run ``reps`` times inside one profiling session), by stage, and the
    top kernels. {} where there is no CUDA device or no profiler."""
    if device.type != "cuda" or not fns:
        return {}
    for fn in fns[:1]:
        fn()
    _sync(device)
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for fn in fns:
            for _ in range(reps):
                fn()
        _sync(device)
    calls = len(fns) * reps
    out = {s: 0.0 for s in STAGE_NAMES}
    kernels = []
    for e in prof.key_averages():
        t = getattr(e, "device_time_total", None) or getattr(e, "cuda_time_total", 0.0)
        if t <= 0:
            continue
        ms = t / calls / 1e3
        out[stage_of(e.key)] += ms
        kernels.append((round(ms, 4), round(e.count / calls, 2), e.key[:100]))
    out["gpu total"] = sum(out[s] for s in STAGE_NAMES)
    out["kernels"] = sorted(kernels, reverse=True)[:16]
    return out


# -- the run ------------------------------------------------------------------------------------------------------

def run_bench(cases, device, repeats: int, peers=("tlvg_warp", "gsplat", "gswarp"), log=print, ours_depth=False,
              profile_reps: int = 2) -> list[dict]:
    """One row per (case, peer). ``cases``: [Case] (or the older [(name, (g, cam))])."""
    cases = [c if isinstance(c, Case) else Case(c[0], c[1][0], [c[1][1]]) for c in cases]
    rows = []
    for case in cases:
        cams = case.cams
        case_rows = {p: {"case": case.name, "peer": p, "n": case.g.num, "size": f"{cams[0].width}x{cams[0].height}",
                         "views": len(cams)} for p in peers}
        if "tlvg_warp" in peers:
            try:
                case_rows["tlvg_warp"]["lists"] = scene_lists(case.g, cams)
                log({"case": case.name, "lists": case_rows["tlvg_warp"]["lists"]})
            except Exception as e:  # noqa: BLE001 - statistics only: the timing goes on
                log({"case": case.name, "lists_error": f"{type(e).__name__}: {e}"})
        makers, samples = {}, {p: {"fwd": [], "fwd_bwd": [], "peak": [], "mad": []} for p in peers}
        for p in peers:
            try:
                makers[p] = PEER_VIEWS[p](case.g, depth=ours_depth) if p == "tlvg_warp" else PEER_VIEWS[p](case.g)
            except ImportError as e:
                case_rows[p]["error"] = f"not importable: {e.name}"
            except Exception as e:  # noqa: BLE001 - a peer failing must not end the run
                case_rows[p]["error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:120] if str(e) else ''}"
        for cam in cams:  # the peers interleaved view by view
            images = {}
            for p in list(makers):
                try:
                    fwd, fwd_bwd, image = makers[p](cam)
                    samples[p]["fwd"].append(time_fn(fwd, device, repeats))
                    samples[p]["fwd_bwd"].append(time_fn(fwd_bwd, device, repeats))
                    samples[p]["peak"].append(peak_mb(fwd_bwd, device))
                    images[p] = image().detach().float()
                except Exception as e:  # noqa: BLE001 - e.g. out of memory: this peer stops, the others go on
                    case_rows[p]["error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:120] if str(e) else ''}"
                    del makers[p]
                if device.type == "cuda":
                    torch.cuda.empty_cache()
            ref = images.get("gsplat")
            for p, img in images.items():
                if ref is not None and img.shape == ref.shape:
                    samples[p]["mad"].append((img - ref).abs().mean().item())
        for p in makers:
            s, row = samples[p], case_rows[p]
            row["fwd_ms"] = statistics.median(s["fwd"])
            row["fwd_bwd_ms"] = statistics.median(s["fwd_bwd"])
            row["peak_mb"] = max(s["peak"])
            row["per_view_fwd_ms"] = [round(t, 4) for t in s["fwd"]]
            row["per_view_fwd_bwd_ms"] = [round(t, 4) for t in s["fwd_bwd"]]
            if s["mad"]:
                row["mad_vs_gsplat"] = statistics.mean(s["mad"])
            try:
                views = [makers[p](cam) for cam in cams]
                row["stages_fwd"] = gpu_stages([v[0] for v in views], device, profile_reps)
                row["stages_fwd_bwd"] = gpu_stages([v[1] for v in views], device, profile_reps)
                del views
            except Exception as e:  # noqa: BLE001 - the profile is an extra
                row["stages_error"] = f"{type(e).__name__}: {e}"
            if device.type == "cuda":
                torch.cuda.empty_cache()
        base = case_rows.get("tlvg_warp")
        for p in peers:
            row = case_rows[p]
            if base and "fwd_ms" in base and "fwd_ms" in row:
                row["fwd_ratio"] = row["fwd_ms"] / base["fwd_ms"]
                row["fwd_bwd_ratio"] = row["fwd_bwd_ms"] / base["fwd_bwd_ms"]
            rows.append(row)
            log({k: v for k, v in row.items() if not k.startswith("per_view") and not k.startswith("stages")})
        del makers
    return rows


def _f(v, p=2):
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{p}f}"


def format_table(rows) -> str:
    """The main table: times, ratios (peer time / ours: above 1, we are faster), peak memory, parity, and our
    lists (binned per tile and walked per pixel, mean / max)."""
    head = ("| case | peer | fwd ms | fwd+bwd ms | fwd / ours | fwd+bwd / ours | peak MiB | MAD vs gsplat "
            "| per tile mean / max | per px mean / max |")
    lines = [head, "|" + " --- |" * 10]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | {r['peer']} | {r['error']} | | | | | | | |")
            continue
        ls = r.get("lists")
        tile = f"{ls['tile_mean']:.0f} / {ls['tile_max']}" if ls else ""
        px = f"{ls['px_mean']:.0f} / {ls['px_max']}" if ls else ""
        lines.append(f"| {r['case']} | {r['peer']} | {_f(r['fwd_ms'])} | {_f(r['fwd_bwd_ms'])} | {_f(r.get('fwd_ratio'))} "
                     f"| {_f(r.get('fwd_bwd_ratio'))} | {_f(r['peak_mb'], 0)} | {_f(r.get('mad_vs_gsplat'), 4)} "
                     f"| {tile} | {px} |")
    return "\n".join(lines)


def format_stages(rows) -> str:
    """GPU kernel time per render by stage (forward, and forward+backward), next to the wall time: the gap is the
    host's share."""
    cols = STAGE_NAMES + ("gpu total",)
    lines = ["| case | peer | mode | " + " | ".join(cols) + " | wall |", "|" + " --- |" * (len(cols) + 4)]
    for r in rows:
        for mode, wall in (("fwd", r.get("fwd_ms")), ("fwd+bwd", r.get("fwd_bwd_ms"))):
            st = r.get("stages_fwd" if mode == "fwd" else "stages_fwd_bwd")
            if not st:
                continue
            lines.append(f"| {r['case']} | {r['peer']} | {mode} | " + " | ".join(_f(st.get(c), 3) for c in cols)
                         + f" | {_f(wall, 3)} |")
    return "\n".join(lines) if len(lines) > 2 else ""


def format_kernels(rows) -> str:
    out = []
    for r in rows:
        for mode in ("fwd", "fwd_bwd"):
            st = r.get(f"stages_{mode}")
            if st and st.get("kernels"):
                out.append(f"{r['case']} | {r['peer']} {mode}: GPU {st['gpu total']:.3f} ms per render")
                out += [f"    {ms:8.4f} ms  x{count:<5g} {name}" for ms, count, name in st["kernels"]]
    return "\n".join(out)
