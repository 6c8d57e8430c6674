"""Per-call cost of the stylize step's loss terms, before and after issue 15's loss rewrite (development aid).

    python3 .ci/profile_losses.py [--device cuda] [--impl both|before|after] [--reps 50] [--scale 1.0]
                                  [--vgg-bf16] [--channels-last] [--refresh-every 10] [--gaussians 360000]

Builds every term at the fern stylize sizes (render 504x378, VGG at x0.5 -> 2961 cells, the painting at the
config's style height 256 -> Starry Night 6528 cells, 360k Gaussians for the flow terms; ``--scale`` shrinks the
render and the painting for a CPU run), with the pretrained VGG when $TLVG_VGG_WEIGHTS is set (else random
weights, which changes the FAST solve's conditioning: use the pretrained one for figures). The render is the fern
photo and the painting Starry Night when ../shared/data is present, else noise.

For each term: milliseconds per call (forward + backward, wall clock over --reps calls, synchronized at the end:
what a host-bound loop pays) and, on CUDA, kernel launches and host synchronizations per call from one profiled
call (torch.profiler events cudaLaunchKernel/cuLaunchKernel*, and cudaStreamSynchronize/cudaDeviceSynchronize/
blocking cudaMemcpy). On the CPU the count column is aten kernels as dispatched (views and allocations left
out) plus Warp launches: a proxy for launches.

"before" is the code as it was before the rewrite (commit 173c8bd): the FAST match through torch.unique/nonzero
and a sparse COO U, a float64 LU solve, F.cosine_similarity; NNFM/Gram/content recomputing the painting's side;
Lab through autograd of rgb_to_lab with the target's statistics per call; two VGG passes (luminance and RGB);
flow targets and weighting in torch. Those are reproduced below (``legacy_*``) or kept in the package
(``flow_terms_unfused``), so one run prints both columns."""
import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tlvg_warp.losses import color as C  # noqa: E402
from tlvg_warp.losses import style as S  # noqa: E402
from tlvg_warp.losses.vgg import flatten_feats, load_vgg, resize_style  # noqa: E402


# ----------------------------------------------------------------------------- the code before issue 15
def legacy_union_keys(keys, n):
    if n > (1 << 28):
        return torch.unique(keys)
    mask = torch.zeros(n, dtype=torch.bool, device=keys.device)
    mask[keys] = True
    return mask.nonzero().squeeze(1)


@torch.no_grad()
def legacy_fast_target(a, s, idx):
    nc, ns = a.shape[1], s.shape[1]
    idx_r, idx_c = idx
    rows = torch.cat([torch.arange(nc, device=a.device).repeat_interleave(idx_r.shape[1]), idx_c.reshape(-1)])
    cols = torch.cat([idx_r.reshape(-1), torch.arange(ns, device=a.device).repeat(idx_c.shape[0])])
    key = legacy_union_keys(rows * ns + cols, nc * ns)
    rows, cols = key // ns, key % ns
    n = float(key.numel())
    u1 = torch.bincount(rows, minlength=nc).to(a.dtype) / n
    u = torch.sparse_coo_tensor(torch.stack([rows, cols]), torch.full_like(rows, 1, dtype=a.dtype) / n,
                                (nc, ns), is_coalesced=True, check_invariants=False)
    us = torch.sparse.mm(u, s.T.contiguous())
    if nc < a.shape[0]:
        a64 = a.double()
        G = a64.T @ a64
        M = G * u1.double()[None, :] + S.RIDGE * torch.eye(nc, dtype=torch.float64, device=a.device)
        Y, info = torch.linalg.solve_ex(M, G)
        b = (us.double().T @ Y.T).to(a.dtype)
        ok = (info == 0) & torch.isfinite(b).all()
    else:
        A = (a * u1) @ a.T
        A64 = A.double() + S.RIDGE * torch.eye(A.shape[0], dtype=torch.float64, device=a.device)
        P, info = torch.linalg.solve_ex(A64, (a @ us).double())
        b, ok = P.to(a.dtype).T @ a, (info == 0) & torch.isfinite(P).all()
    return torch.where(ok, b, a)


def legacy_topk_both(a, s, k, need_cols=True):
    mdt = S.match_dtype(a)
    an, sn = F.normalize(a, dim=0).to(mdt), F.normalize(s, dim=0).to(mdt)
    nc, ns = an.shape[1], sn.shape[1]
    kr, kc = min(k, ns), min(k, nc)
    idx_r = torch.empty(nc, kr, dtype=torch.long, device=a.device)
    best_v = best_i = None
    for i0, i1 in S._chunks(nc, ns):
        sim = an[:, i0:i1].T @ sn
        idx_r[i0:i1] = sim.topk(kr, dim=1).indices
        if need_cols:
            v, i = sim.topk(min(kc, i1 - i0), dim=0)
            i = i + i0
            if best_v is not None:
                v, i = torch.cat([best_v, v]), torch.cat([best_i, i])
                v, j = v.topk(min(kc, v.shape[0]), dim=0)
                i = i.gather(0, j)
            best_v, best_i = v, i
    return idx_r, best_i


def legacy_fast_loss(a, s):
    s = s.to(a)
    with torch.no_grad():
        idx = legacy_topk_both(a.detach(), s.detach(), S.K_CROSS)
    b = legacy_fast_target(a.detach(), s.detach(), idx)
    return (1.0 - F.cosine_similarity(a, b, dim=1)).mean()


def legacy_nnfm_loss(a, s):
    s = s.to(a)
    with torch.no_grad():
        nn_idx = legacy_topk_both(a.detach(), s.detach(), 1, need_cols=False)[0][:, 0]
    return (1.0 - F.cosine_similarity(a, s[:, nn_idx], dim=0)).mean()


def legacy_gram_loss(a, s):
    return ((S.gram(a) - S.gram(s.to(a))) ** 2).mean()


def legacy_content_loss(a, p):
    return ((a - p.to(a)) ** 2).mean()


def legacy_lab_chroma_loss(render, target):
    ab_r = C.rgb_to_lab(render).reshape(-1, 3)[:, 1:]
    ab_t = C.rgb_to_lab(target.to(render)).reshape(-1, 3)[:, 1:].detach()
    d_mu = (ab_r.mean(0) - ab_t.mean(0)).abs().sum()
    d_sd = (ab_r.std(0, unbiased=False) - ab_t.std(0, unbiased=False)).abs().sum()
    return 0.5 * (d_mu + d_sd)


def legacy_luminance(img):
    w = torch.tensor([0.299, 0.587, 0.114], dtype=img.dtype, device=img.device)
    return (img * w).sum(-1, keepdim=True).expand_as(img)


# ----------------------------------------------------------------------------- measuring
def sync(dev):
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


LAUNCH = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx", "cudaLaunchCooperativeKernel")
SYNCS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy", "cuStreamSynchronize",
         "cuCtxSynchronize")


class _OpCount:
    """Counts aten kernels as dispatched (composite ops decomposed, views and allocations left out) and Warp
    launches: the CPU's stand-in for kernel launches."""

    SKIP = ("empty", "empty_like", "empty_strided", "detach", "alias", "lift_fresh", "_local_scalar_dense",
            "scalar_tensor", "result_type", "resolve_conj", "resolve_neg")

    def __init__(self):
        from torch.utils._python_dispatch import TorchDispatchMode

        counter = self

        class Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                if not func.is_view and func.overloadpacket.__name__ not in _OpCount.SKIP:
                    counter.n += 1
                return func(*args, **(kwargs or {}))

        self.n, self.mode = 0, Mode()

    def __enter__(self):
        self.n = 0
        try:
            import warp as wp
            self._wp, self._launch = wp, wp.launch

            def launch(*a, **k):
                self.n += 1
                return self._launch(*a, **k)
            wp.launch = launch
        except ImportError:
            self._wp = None
        self.mode.__enter__()
        return self

    def __exit__(self, *exc):
        self.mode.__exit__(*exc)
        if self._wp is not None:
            self._wp.launch = self._launch


def count_events(fn, dev):
    """(launches, host syncs) of one call: CUDA from the profiler; CPU: dispatched aten kernels + Warp launches."""
    if dev.type != "cuda":
        with _OpCount() as c:
            fn()
        return c.n, None
    from torch.profiler import ProfilerActivity, profile

    sync(dev)
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
        sync(dev)
    ev = prof.events()
    return sum(1 for e in ev if e.name in LAUNCH), sum(1 for e in ev if e.name in SYNCS)


_BASE = {}


def counts_per_call(fn, dev):
    """count_events minus what the harness itself shows (an empty call: the profiler's and our synchronize)."""
    if dev.type not in _BASE:
        _BASE[dev.type] = count_events(lambda: None, dev)
    la, sy = count_events(fn, dev)
    b_la, b_sy = _BASE[dev.type]
    return la - b_la, (None if sy is None else max(0, sy - b_sy))


def bench(fn, dev, reps, warmup=3):
    for _ in range(warmup):
        fn()
    sync(dev)
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    sync(dev)
    ms = (time.perf_counter() - t) / reps * 1e3
    launches, syncs = counts_per_call(fn, dev)
    return ms, launches, syncs


def load_inputs(args, dev):
    data = ROOT.parent / "shared" / "data"
    photo = Path(args.photo) if args.photo else data / "scenes" / "fern_llff" / "images_4" / "image000.png"
    style = Path(args.style) if args.style else data / "styles" / "starry_night.jpg"
    W, H = round(504 * args.scale), round(378 * args.scale)
    if photo.is_file() and style.is_file():
        import cv2
        img = cv2.cvtColor(cv2.imread(str(photo)), cv2.COLOR_BGR2RGB).astype(np.float32) / 255
        img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
        st = cv2.cvtColor(cv2.imread(str(style)), cv2.COLOR_BGR2RGB).astype(np.float32) / 255
        src = f"{photo.name} + {style.name}"
    else:
        rng = np.random.default_rng(0)
        img, st = rng.random((H, W, 3), np.float32), rng.random((512, 800, 3), np.float32)
        src = "noise (../shared/data absent)"
    st = resize_style(st, max(16, round(args.style_height * args.scale)))
    rgb = torch.from_numpy(img).to(dev)
    target = (0.8 * rgb + 0.1).contiguous()  # stands in for the palette-matched photo of the view
    return rgb, torch.from_numpy(st).to(dev), target, src


def flow_setup(args, dev, H, W):
    from tlvg_warp import Gaussians
    from tlvg_warp.eval.bench_raster import bench_camera, random_scene

    g = random_scene(args.gaussians, -4.0, 0, dev)
    g = Gaussians(*[t.detach().clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales,
                                                                         g.opacity_logits, g.sh)])
    cam = bench_camera(W, H)
    gen = torch.Generator().manual_seed(0)
    th = torch.rand(H // 8 + 1, W // 8 + 1, generator=gen) * np.pi
    c = torch.rand(th.shape, generator=gen)
    d = torch.stack([c * torch.cos(2 * th), c * torch.sin(2 * th)], 0)[None]
    d = F.interpolate(d, size=(H, W), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
    field = torch.cat([d, d.norm(dim=-1, keepdim=True)], -1).contiguous().to(dev)  # [H,W,3] as the loop's
    weights = torch.rand(args.gaussians, generator=gen).to(dev)
    return g, cam, field, weights


def cache_experiment(args, dev, vgg):
    """How much the FAST match cache (StyleLoss refresh_every) costs in quality: a shared texture seen through 4
    overlapping crops ("views", one per step in a shuffled order, as the loop's), optimized with the stylize
    step's style (2.0 x FAST on luminance) and content (0.01 x MSE of RGB features) terms for --steps steps
    with Adam, once per refresh_every in --refresh-list. Scored at the end on every view with fresh matches: the
    FAST loss, the Gram distance to the painting (relative Frobenius, independent of the match) and the content
    distance."""
    rgb, style_img, _, src = load_inputs(args, dev)
    H, W = rgb.shape[:2]
    ch, cw = round(H * 0.85), round(W * 0.85)
    offs = [(0, 0), (H - ch, 0), (0, W - cw), (H - ch, W - cw)]
    with torch.no_grad():
        sf = S.StyleFeatures(flatten_feats(vgg(C.luminance(style_img))))
        photo_f = [flatten_feats(vgg(rgb[y:y + ch, x:x + cw], scale=args.vgg_scale)) for y, x in offs]
    print(f"cache experiment: texture {W}x{H}, 4 crops {cw}x{ch} (VGG x{args.vgg_scale}: {photo_f[0].shape[1]} cells), "
          f"painting {sf.shape[1]} cells, {args.steps} steps, {src}; VGG {vgg.source}")
    gen = torch.Generator().manual_seed(0)
    order = [int(i) for _ in range(args.steps // 4 + 1) for i in torch.randperm(4, generator=gen)][:args.steps]

    def score(tex):
        fast_l, gram_d, cont = [], [], []
        with torch.no_grad():
            for v, (y, x) in enumerate(offs):
                crop = tex[y:y + ch, x:x + cw]
                a, a_rgb = vgg.features_of([C.luminance(crop), crop], scale=args.vgg_scale)
                fast_l.append(S.fast_loss(a, sf).item())
                gram_d.append(((S.gram(a) - sf.gram).norm() / sf.gram.norm()).item())
                cont.append(S.content_loss(a_rgb, photo_f[v]).item())
        return np.mean(fast_l), np.mean(gram_d), np.mean(cont)

    f0, g0, c0 = score(rgb)
    print(f"  start: FAST {f0:.4f}  Gram dist {g0:.4f}  content {c0:.3f}")
    print("  refresh_every  cache       matches  s/step   FAST (fresh)   Gram dist   content")
    for R, cache in [(R, c) for R in args.refresh_list for c in (args.cache_kinds if R > 1 else ["-"])]:
        tex = rgb.clone().requires_grad_(True)
        opt = torch.optim.Adam([tex], lr=args.lr)
        style = S.StyleLoss(sf, "fast", refresh_every=R, cache="projection" if cache == "-" else cache)
        t = time.perf_counter()
        for v in order:
            y, x = offs[v]
            crop = tex[y:y + ch, x:x + cw]
            a, a_rgb = vgg.features_of([C.luminance(crop), crop], scale=args.vgg_scale)
            loss = 2.0 * style(a, key=v) + 0.01 * S.content_loss(a_rgb, photo_f[v])
            opt.zero_grad()
            loss.backward()
            opt.step()
            with torch.no_grad():
                tex.clamp_(0, 1)
        sync(dev)
        dt = (time.perf_counter() - t) / len(order)
        f, g, c = score(tex.detach())
        print(f"  {R:13d}  {cache:10s}  {style.refreshes:7d}  {dt:6.3f}   {f:12.4f}   {g:9.4f}   {c:7.3f}", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--impl", choices=("both", "before", "after"), default="both")
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--scale", type=float, default=1.0, help="shrink render and painting (CPU runs)")
    ap.add_argument("--style", default=None, help="painting (default ../shared/data/styles/starry_night.jpg)")
    ap.add_argument("--photo", default=None, help="render stand-in (default fern images_4/image000.png)")
    ap.add_argument("--vgg-weights", default=None, help="default $TLVG_VGG_WEIGHTS, else random")
    ap.add_argument("--style-height", type=int, default=256)
    ap.add_argument("--vgg-scale", type=float, default=0.5)
    ap.add_argument("--gaussians", type=int, default=360_000)
    ap.add_argument("--refresh-every", type=int, default=10, help="the cached FAST row (StyleLoss refresh_every)")
    ap.add_argument("--vgg-bf16", action="store_true", help="after: VGG under bf16 autocast")
    ap.add_argument("--channels-last", action="store_true", help="after: VGG in channels_last")
    ap.add_argument("--no-flow", action="store_true", help="skip the flow terms (they need Warp)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--cache-experiment", action="store_true", help="quality of the FAST match cache instead")
    ap.add_argument("--steps", type=int, default=120, help="cache experiment: optimization steps")
    ap.add_argument("--lr", type=float, default=0.01, help="cache experiment: Adam learning rate on the texture")
    ap.add_argument("--refresh-list", type=int, nargs="+", default=[1, 3, 10, 30])
    ap.add_argument("--cache-kinds", nargs="+", default=["projection", "match"], choices=["projection", "match"])
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    torch.manual_seed(0)
    weights = args.vgg_weights or os.environ.get("TLVG_VGG_WEIGHTS") or "random"
    vgg = load_vgg(weights, dev)
    if args.cache_experiment:
        return cache_experiment(args, dev, vgg)
    rgb, style_img, target, src = load_inputs(args, dev)
    H, W = rgb.shape[:2]
    with torch.no_grad():
        s_feats = flatten_feats(vgg(C.luminance(style_img)))  # [768, Ns] as the loop's style target
        a0 = flatten_feats(vgg(C.luminance(rgb), scale=args.vgg_scale))
        p0 = flatten_feats(vgg(rgb, scale=args.vgg_scale))
    print(f"device {dev} ({torch.cuda.get_device_name(dev) if dev.type == 'cuda' else f'{torch.get_num_threads()} threads'}), "
          f"torch {torch.__version__}; VGG: {vgg.source}; inputs: {src}")
    print(f"render {W}x{H}, VGG x{args.vgg_scale} -> a [{a0.shape[0]}, {a0.shape[1]}]; painting "
          f"{style_img.shape[1]}x{style_img.shape[0]} -> s [{s_feats.shape[0]}, {s_feats.shape[1]}]; reps {args.reps}")

    img = rgb.clone().requires_grad_(True)
    a = a0.clone().requires_grad_(True)
    rows = []

    def run(name, impl, fn):
        def step():
            for t in (img, a):
                t.grad = None
            fn().backward()
        try:
            ms, launches, syncs = bench(step, dev, args.reps)
        except ImportError as e:  # the Warp-kernel terms on a machine without Warp
            print(f"  {name:28s} {impl:7s} skipped ({e})")
            return
        rows.append((name, impl, ms, launches, syncs))
        col = "launches" if dev.type == "cuda" else "kernels"
        sy = "" if syncs is None else f"  syncs {syncs:3d}"
        print(f"  {name:28s} {impl:7s} {ms:9.3f} ms/call  {col} {launches:5d}{sy}", flush=True)

    do_before, do_after = args.impl in ("both", "before"), args.impl in ("both", "after")
    style_f = S.StyleFeatures(s_feats)
    fast = S.StyleLoss(style_f, "fast")
    cached = S.StyleLoss(style_f, "fast", refresh_every=args.refresh_every)
    cached_match = S.StyleLoss(style_f, "fast", refresh_every=args.refresh_every, cache="match")
    nnfm, gramL = S.StyleLoss(style_f, "nnfm"), S.StyleLoss(style_f, "gram")
    try:
        lab_stats = C.lab_chroma_stats(target)
    except ImportError:  # the Lab kernels are Warp kernels
        lab_stats = None
    if args.vgg_bf16 or args.channels_last:
        vgg_fast = load_vgg(weights, dev).set_precision(
            torch.bfloat16 if args.vgg_bf16 else None, args.channels_last)
    else:
        vgg_fast = vgg
    flow = None
    if not args.no_flow:
        try:
            from tlvg_warp import flow as flow_mod
            flow = (flow_mod,) + flow_setup(args, dev, H, W)
        except Exception as e:  # no Warp on this machine
            print(f"  (flow terms skipped: {type(e).__name__}: {e})")

    print("term                         impl       time            counts")
    if do_before:
        run("vgg lum+rgb (fwd+bwd)", "before", lambda: (flatten_feats(vgg(legacy_luminance(img), scale=args.vgg_scale)).sum()
                                                         + flatten_feats(vgg(img, scale=args.vgg_scale)).sum()))
    if do_after:
        run("vgg lum+rgb (fwd+bwd)", "after", lambda: sum(f.sum() for f in vgg_fast.features_of(
            [C.luminance(img), img], scale=args.vgg_scale)))
    if do_before:
        run("style FAST", "before", lambda: legacy_fast_loss(a, s_feats))
    if do_after:
        run("style FAST", "after", lambda: fast(a))
        run(f"style FAST refresh {args.refresh_every} (amort.)", "after", lambda: cached(a, key=0))
        run(f"style FAST match-cache {args.refresh_every}", "after", lambda: cached_match(a, key=0))
        run("style FAST solve=lu64 (old solve)", "after", lambda: S.fast_loss(a, style_f, solve="lu64"))
    if do_before:
        run("style NNFM", "before", lambda: legacy_nnfm_loss(a, s_feats))
    if do_after:
        run("style NNFM", "after", lambda: nnfm(a))
    if do_before:
        run("style Gram", "before", lambda: legacy_gram_loss(a, s_feats))
    if do_after:
        run("style Gram", "after", lambda: gramL(a))
    if do_before:
        run("content", "before", lambda: legacy_content_loss(a, p0))
    if do_after:
        run("content", "after", lambda: S.content_loss(a, p0))
    if do_before:
        run("lab chroma", "before", lambda: legacy_lab_chroma_loss(img, target))
    if do_after:
        run("lab chroma", "after", lambda: C.lab_chroma_loss(img, target_stats=lab_stats if lab_stats is not None
                                                             else C.lab_chroma_stats(target)))
    if flow is not None:
        fm, g, cam, field, weights = flow
        if do_before:
            run(f"flow align+aniso ({args.gaussians // 1000}k)", "before",
                lambda: sum(fm.flow_terms_unfused(g, cam, field, weights)))
        if do_after:
            run(f"flow align+aniso ({args.gaussians // 1000}k)", "after", lambda: sum(fm.flow_terms(g, cam, field, weights)))
    # the stylize step's terms (FAST, content, Lab, flow, VGG): the configured method
    per = {}
    for name, impl, ms, la, sy in rows:
        if (name.startswith(("vgg", "style FAST", "content", "lab", "flow")) and "refresh" not in name
                and "cache" not in name and "lu64" not in name):
            per.setdefault(impl, [0.0, 0, 0])
            per[impl][0] += ms
            per[impl][1] += la
            per[impl][2] += sy or 0
    for impl, (ms, la, sy) in per.items():
        tail = f", {la} launches, {sy} syncs" if dev.type == "cuda" else f", {la} kernels (CPU proxy)"
        print(f"stylize step's loss side ({impl}): {ms:.2f} ms{tail}")


if __name__ == "__main__":
    main()
