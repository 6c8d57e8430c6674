"""Stability where 3DGS stylization breaks: drive the pipeline into hard cases and record what
happens — finished or not (exceptions are caught and recorded, never re-raised), NaN count in every output
(Gaussian parameters and renders), hole fraction (pixels whose alpha fell below 0.5 that were covered, alpha
>= 0.5, by the input scene), the quality metrics, Gaussian count in and out, wall time.

The pipeline is reached through :func:`stylize_scene` only (one switch point; bench_sweep uses it too).
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import time
import traceback
from dataclasses import dataclass, field

import cv2
import torch

from ..io.demo import builtin_painting, demo_dataset
from ..losses.vgg import load_vgg
from ..renderer import render
from ..stylize import StylizeInputs, run_stylize
from ..stylize.config import config_from_dict
from ..types import Gaussians
from . import quick as M

HOLE_ALPHA = 0.5  # a pixel is covered at alpha >= 0.5 (same threshold as the consistency metric)


# ---------------------------------------------------------------- the pipeline, behind one function
def stylize_scene(gaussians, cameras, names, photos, style, background, overrides: dict, vgg=None):
    """Run the stylization pipeline in memory. Returns (stylized Gaussians, per-view target doubled fields
    [H,W,2] or None, the pipeline's metrics dict)."""
    cfg = config_from_dict(overrides)  # dotted keys for sections (e.g. "lr.means")
    inp = StylizeInputs(gaussians, list(cameras), list(names), list(photos), style, tuple(background))
    res = run_stylize(inp, cfg, None, progress=False, vgg=vgg, quiet=True)
    fields = [f[..., :2].cpu() for f in res.fields] if res.fields else None
    return res.gaussians, fields, dict(res.metrics)


# ---------------------------------------------------------------- scenarios
@dataclass
class Base:
    """The scene a scenario starts from (the demo by default)."""

    gaussians: Gaussians
    cameras: list
    names: list
    photos: list
    style: torch.Tensor
    background: tuple
    overrides: dict = field(default_factory=dict)


@dataclass
class Scenario:
    name: str
    what: str
    apply: object  # Base -> Base (a modified copy)
    quick: bool = True  # part of the fast subset (--quick, the tests)
    gpu_only: bool = False  # skipped without CUDA (too slow on CPU)


def _with(b: Base, **kw) -> Base:
    return dataclasses.replace(b, **kw)


def _cfg(b: Base, **kw) -> Base:
    return _with(b, overrides=b.overrides | kw)


def _painting(kind: str, h=256, w=320) -> torch.Tensor:
    if kind == "flat":
        return torch.tensor([0.35, 0.45, 0.7]).expand(h, w, 3).contiguous()
    if kind == "noise":
        return torch.rand(h, w, 3, generator=torch.Generator().manual_seed(0))
    if kind == "stripes":  # one-pixel horizontal stripes, black and white
        return (torch.arange(h) % 2).float().view(h, 1, 1).expand(h, w, 3).contiguous()
    raise ValueError(kind)


def _edit(g: Gaussians, **fields) -> Gaussians:
    d = {f: getattr(g, f).detach().clone() for f in Gaussians.FIELDS}
    for k, fn in fields.items():
        d[k] = fn(d[k])
    return Gaussians(**d)


def _pick(n: int, k: int, seed: int = 0) -> torch.Tensor:
    return torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max(1, min(n, k))]


def _append(g: Gaussians, extra: Gaussians) -> Gaussians:
    return Gaussians(**{f: torch.cat([getattr(g, f), getattr(extra, f).to(getattr(g, f))]) for f in Gaussians.FIELDS})


def _zero_scales(b: Base) -> Base:
    idx = _pick(b.gaussians.num, b.gaussians.num // 10)

    def f(s):
        s[idx] = -30.0  # exp(-30) ~ 1e-13: a point, below every pixel's footprint (0.3 px² blur only)
        return s
    return _with(b, gaussians=_edit(b.gaussians, log_scales=f))


def _huge_scales(b: Base) -> Base:
    idx = _pick(b.gaussians.num, 20)

    def f(s):
        s[idx] = 5.0  # ~150 m: covers every view entirely
        return s
    return _with(b, gaussians=_edit(b.gaussians, log_scales=f))


def _near_plane(b: Base) -> Base:
    """200 Gaussians just past the near plane (z = 0.02 m) of the first camera, spread over its view."""
    cam, n = b.cameras[0], 200
    gen = torch.Generator().manual_seed(1)
    z = torch.full((n,), 0.02, dtype=torch.float64)
    uv = torch.rand(n, 2, generator=gen, dtype=torch.float64) * torch.tensor([cam.width, cam.height])
    xc = torch.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], -1)
    world = (xc - cam.t) @ cam.R
    extra = _clones(b.gaussians, n, world, log_scale=math.log(0.005))
    return _with(b, gaussians=_append(b.gaussians, extra))


def _stacked(b: Base, n: int = 2000) -> Base:
    """Thousands of Gaussians at one point, on the center pixel of the first view."""
    cam = b.cameras[0]
    center = b.gaussians.means.double().mean(0)
    d = float((center @ cam.R[2] + cam.t[2]).clamp_min(cam.near * 10))
    xc = torch.tensor([0.0, 0.0, d], dtype=torch.float64)
    xc[0] = (cam.width / 2 + 0.5 - cam.cx) / cam.fx * d
    xc[1] = (cam.height / 2 + 0.5 - cam.cy) / cam.fy * d
    world = ((xc - cam.t) @ cam.R).expand(n, 3)
    return _with(b, gaussians=_append(b.gaussians, _clones(b.gaussians, n, world, log_scale=math.log(0.01))))


def _clones(g: Gaussians, n: int, means: torch.Tensor, log_scale: float) -> Gaussians:
    gen = torch.Generator().manual_seed(2)
    sh = torch.zeros(n, g.sh.shape[1], 3, dtype=g.dtype)
    sh[:, 0] = torch.randn(n, 3, generator=gen).to(g.dtype)
    q = torch.zeros(n, 4, dtype=g.dtype)
    q[:, 0] = 1
    return Gaussians(means.to(g.dtype).contiguous(), q, torch.full((n, 3), log_scale, dtype=g.dtype),
                     torch.full((n,), 2.0, dtype=g.dtype), sh)


def _nan(b: Base) -> Base:
    idx = _pick(b.gaussians.num, 8, seed=3)

    def f(t):
        t[idx[:4]] = math.nan
        return t

    def s(t):
        t[idx[4:]] = math.nan
        return t
    return _with(b, gaussians=_edit(b.gaussians, means=f, sh=s))


def _resize(b: Base, w: int, h: int) -> Base:
    cams = [dataclasses.replace(c, fx=c.fx * w / c.width, fy=c.fy * h / c.height, cx=c.cx * w / c.width,
                                cy=c.cy * h / c.height, width=w, height=h) for c in b.cameras]
    interp = lambda p: cv2.INTER_AREA if w < p.shape[1] else cv2.INTER_LINEAR  # noqa: E731
    photos = [torch.from_numpy(cv2.resize(p.numpy(), (w, h), interpolation=interp(p))) for p in b.photos]
    return _with(b, cameras=cams, photos=photos)


def scenarios(quick_iters: int, long_iters: int = 10000) -> list[Scenario]:
    return [
        Scenario("baseline", "the demo as is (reference row)", lambda b: b),
        Scenario("advection_x10", "xyz lr x10, tangential λ = 0 (aggressive advection)",
                 lambda b: _cfg(b, **{"lr.means": 1.6e-3, "lr.means_final": 1.6e-5, "geometry.tangential_lambda": 0.0})),
        Scenario("paint_flat", "flat-color painting (no strokes at all)", lambda b: _with(b, style=_painting("flat"))),
        Scenario("paint_noise", "white-noise painting (no coherent strokes)",
                 lambda b: _with(b, style=_painting("noise"))),
        Scenario("paint_stripes", "one-pixel stripes (aliasing at every resize)",
                 lambda b: _with(b, style=_painting("stripes"))),
        Scenario("gauss_zero_scale", "10% of Gaussians with scale exp(-30) ~ 0", _zero_scales),
        Scenario("gauss_huge_scale", "20 Gaussians with scale e^5 ~ 150 m", _huge_scales),
        Scenario("gauss_near_plane", "200 Gaussians 2 cm in front of the first camera", _near_plane),
        Scenario("gauss_stacked", "2000 Gaussians stacked on one pixel", _stacked),
        Scenario("gauss_nan", "NaN injected into 4 means and 4 SH rows", _nan),
        Scenario("image_tiny", "8x6 images", lambda b: _resize(b, 8, 6)),
        Scenario("image_huge", "1920x1440 images", lambda b: _resize(b, 1920, 1440), quick=False, gpu_only=True),
        Scenario("long_run", f"{long_iters} iterations", lambda b: _cfg(b, iterations=long_iters),
                 quick=False, gpu_only=True),
    ]


def demo_base(quick: bool, device: str, n_views=None, size=None, stride=None, iterations=None) -> Base:
    n_views = n_views or (4 if quick else 12)
    w, h = size or ((32, 24) if quick else (160, 120))
    ds = demo_dataset(n_views=n_views, width=w, height=h)
    stride = stride or (4 if quick else 1)  # quick: ~4.7k Gaussians, each scenario a few seconds on CPU
    g = ds.gaussians.subset(slice(None, None, stride))
    photos = [ds.image(i) for i in range(len(ds))]
    ov = {"device": device, "iterations": iterations or (6 if quick else 300), "log_every": 1000}
    if quick:
        ov["style_height"] = 64
    return Base(g, list(ds.cameras), list(ds.names), photos, builtin_painting(), tuple(ds.background), ov)


# ---------------------------------------------------------------- measuring one scenario
def coverage(g: Gaussians, cameras, background) -> list[torch.Tensor]:
    with torch.no_grad():
        return [render(g, c, background).alpha.detach().cpu() >= HOLE_ALPHA for c in cameras]


def hole_fraction(before: list, after_alpha: list) -> float:
    """Share of pixels covered before (alpha >= 0.5) whose alpha fell below 0.5."""
    cov = sum(int(b.sum()) for b in before)
    holes = sum(int((b & (a < HOLE_ALPHA)).sum()) for b, a in zip(before, after_alpha))
    return holes / cov if cov else 0.0


def _finite_gaussians(g: Gaussians) -> Gaussians:
    ok = torch.ones(g.num, dtype=torch.bool, device=g.device)
    for f in Gaussians.FIELDS:
        t = getattr(g, f)
        ok &= torch.isfinite(t.reshape(g.num, -1)).all(1)
    return g.subset(ok)


_FEATS: dict = {}


def _style_feats(vgg, style):
    """The painting's VGG features, once per painting (they cost as much as a short run on CPU)."""
    key = (id(vgg), tuple(style.shape), hashlib.sha1(style.detach().cpu().numpy().tobytes()).hexdigest())
    if key not in _FEATS:
        _FEATS[key] = M.style_target_feats(vgg, style)
    return _FEATS[key]


def run_scenario(sc: Scenario, base: Base, vgg, device: str, vgg_metrics: bool = True) -> dict:
    row = {"scenario": sc.name, "what": sc.what, "finished": False, "error": None, "nan": None,
           "hole_fraction": None, "gaussians_in": None, "gaussians_out": None, "time_s": None}
    t0 = time.perf_counter()
    try:
        b = sc.apply(base)
        row["gaussians_in"] = b.gaussians.num
        # coverage before: the input scene without its NaN rows (a NaN Gaussian covers nothing)
        before = coverage(_finite_gaussians(b.gaussians).to(device=device), b.cameras, b.background)
        g, fields, pm = stylize_scene(b.gaussians.to(device=device), b.cameras, b.names, b.photos, b.style,
                                      b.background, b.overrides, vgg)
        row["time_s"] = time.perf_counter() - t0
        row["finished"] = True
        row["gaussians_out"] = g.num
        views = M.render_views(g, b.cameras, b.background)
        row["nan"] = M.nan_count(*(getattr(g, f) for f in Gaussians.FIELDS)) + sum(
            M.nan_count(v["color"], v["depth"], v["alpha"]) for v in views)
        row["hole_fraction"] = hole_fraction(before, [v["alpha"] for v in views])
        net = vgg if vgg_metrics else None
        q = M.scene_metrics(views, b.style, net, None, fields, ks=(1,),
                            style_feats=_style_feats(vgg, b.style) if vgg_metrics else None)
        q = q["summary"]
        row |= {k: q.get(k) for k in ("flow_alignment", "consistency_k1", "style_fast", "style_gram")}
        row["pipeline_train_s"] = pm.get("train_time_s")
    except Exception as e:  # noqa: BLE001 - the suite records failures, it never stops on one
        row["time_s"] = time.perf_counter() - t0
        row["error"] = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"[:300]
        row["traceback"] = traceback.format_exc(limit=6)
    return row


def run_suite(quick: bool, device: str | None = None, only=None, vgg_weights="random", log=print,
              long_iters: int = 10000, base: Base | None = None, extra=(), vgg_metrics: bool = True) -> dict:
    """Run every scenario (the quick subset with ``quick``); ``base`` replaces the demo scene, ``extra`` adds
    scenarios. Never raises for a failing scenario: its row says finished False and the error."""
    dev = device or ("cuda" if torch.cuda.is_available() else "cpu")
    vgg = load_vgg(vgg_weights, device=dev)
    base = base or demo_base(quick, dev)
    base.overrides["vgg_weights"] = vgg_weights
    rows = []
    for sc in [*scenarios(6, long_iters), *extra]:
        if only and sc.name not in only:
            continue
        if quick and not sc.quick:
            continue
        if sc.gpu_only and dev == "cpu":
            rows.append({"scenario": sc.name, "what": sc.what, "finished": None, "error": "skipped: needs a GPU"})
            continue
        r = run_scenario(sc, base, vgg, dev, vgg_metrics)
        rows.append(r)
        if log:
            log(format_row(r))
    return {"device": dev, "quick": quick, "vgg": vgg.source, "vgg_random": bool(vgg.is_random),
            "views": len(base.cameras), "size": [base.cameras[0].width, base.cameras[0].height],
            "iterations": base.overrides.get("iterations"), "rows": rows}


COLUMNS = ("scenario", "finished", "nan", "hole_fraction", "gaussians_in", "gaussians_out", "flow_alignment",
           "consistency_k1", "style_gram", "time_s")


def _cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, float):
        return f"{v:.3g}" if math.isfinite(v) else str(v)
    return str(v)


def format_row(r: dict) -> str:
    s = " | ".join(_cell(r.get(c)) for c in COLUMNS)
    return s + (f" | {r['error']}" if r.get("error") else "")


def format_table(rows) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " | error |", "|" + "---|" * (len(COLUMNS) + 1)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(c)) for c in COLUMNS) + f" | {r.get('error') or ''} |")
    return "\n".join(lines)

