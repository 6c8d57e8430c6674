"""The references every run is measured against (SPEC §4 "same ruler"), and scoring one run with them.

``build_references`` takes the un-stylized scene, the cameras, the painting and the photos, nothing from any
stylization run, and caches its per-view arrays (un-stylized color/depth/alpha, alpha at 2x, the common
stroke field, recolored photos) in ``cache_dir/<content hash>.npz``. ``score_run`` measures one stylized
scene against them: per-view values of every metric in metrics.METRICS.
"""
from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..fileio import write_bytes
from ..losses.color import color_transfer
from ..losses.stroke_field import field_at_cells, map_field_matched, stroke_field
from ..losses.vgg import flatten_feats, resize_style
from ..renderer import render
from ..types import Camera
from . import metrics as M

REFS_VERSION = 2  # bump when what the references contain changes: old cache entries are then ignored
EVAL_HEIGHT = 256  # style / content / stroke statistics / detail are measured at this height (SPEC §3 style)
FIELD_SCALE = 0.5  # the un-stylized render is matched at x0.5, as training feeds renders to VGG (SPEC §3)


@dataclass
class Refs:
    cameras: list
    base: list  # per view {"color" [H,W,3], "depth" [H,W], "alpha" [H,W]} numpy, the un-stylized scene
    alpha2x: list  # per view un-stylized alpha at 2x [2H,2W]
    photos: list  # per view [H,W,3]
    recolored: list  # photos recolored to the painting's palette [H,W,3]
    fields: list | None  # per view common doubled-angle field [H,W,2]; None without pretrained features
    painting: np.ndarray  # [h,w,3]
    background: tuple
    eval_height: int = EVAL_HEIGHT
    pretrained: bool = False
    key: str = ""
    painting_stats: dict = field(default_factory=dict)
    photo_feats: list = field(default_factory=list)  # per view VGG content features of the photo (in memory)
    corr: dict = field(default_factory=dict)  # (i, k) -> correspondences of views i and i+k (built on first use)


def scaled(cam, f: float):
    return Camera(cam.world_to_camera, cam.fx * f, cam.fy * f, cam.cx * f, cam.cy * f, round(cam.width * f),
                  round(cam.height * f), cam.near, cam.far, name=cam.name)


def render_views(g, cameras, background, device="cpu") -> list[dict]:
    """color [H,W,3], depth, alpha [H,W] numpy of ``g`` from each camera."""
    g = g.to(device=device, dtype=torch.float32)
    out = []
    with torch.no_grad():
        for cam in cameras:
            r = render(g, cam, background)
            out.append({"color": r.color.clamp(0, 1).cpu().numpy(), "depth": r.depth.cpu().numpy(),
                        "alpha": r.alpha.cpu().numpy()})
    return out


def content_key(scene, cameras, background, painting, photos, net, eval_height) -> str:
    h = hashlib.sha256(f"refs v{REFS_VERSION} h{eval_height} s{FIELD_SCALE} {net.source} {tuple(background)}".encode())
    for f in scene.FIELDS:
        h.update(np.ascontiguousarray(M._np(getattr(scene, f)), np.float32).tobytes())
    for c in cameras:
        h.update(np.asarray([*M._np(c.world_to_camera).ravel(), c.fx, c.fy, c.cx, c.cy, c.width, c.height,
                             c.near, c.far], np.float64).tobytes())
    for im in [painting, *photos]:
        h.update(np.ascontiguousarray(im, np.float32).tobytes())
    return h.hexdigest()[:32]


def common_field(net, base_color: np.ndarray, painting: np.ndarray, style_cells_field, style_feats) -> np.ndarray:
    """The painting's stroke field carried onto a view [H,W,2]: every relu3 cell of the UN-stylized render
    (RGB, x FIELD_SCALE) takes the doubled-angle vector of its nearest painting cell (cosine), upsampled."""
    dev = next(net.parameters()).device
    with torch.no_grad():
        f = net(torch.from_numpy(base_color).to(dev), FIELD_SCALE)  # [1,768,hc,wc]
        a = torch.nn.functional.normalize(flatten_feats(f).double(), dim=0)
        idx = (a.T @ style_feats).argmax(1, keepdim=True)  # [Nc,1]
    h, w = base_color.shape[:2]
    d = map_field_matched(style_cells_field, idx, torch.ones(idx.shape), h, w, tuple(f.shape[-2:]))[2]
    return d.cpu().numpy().astype(np.float32)


def _painting_side(net, painting: np.ndarray, eval_height: int, pretrained: bool) -> dict:
    p_eval = M.resize_to_height(painting, eval_height)
    out = {"strokes": M.stroke_descriptor(painting), "hf": M.hf_energy(M.luma(p_eval)), "tones": M.tones(p_eval),
           "colours": M.colours(p_eval)}
    if pretrained:
        out |= M.vgg_feats(net, p_eval)
        work = resize_style(painting)  # the field's working size (SPEC §3: height 256)
        dev = next(net.parameters()).device
        with torch.no_grad():
            sf = net(torch.from_numpy(work).to(dev))
        out["cells_field"] = field_at_cells(stroke_field(work)[2], tuple(sf.shape[-2:]))
        out["cells_feats"] = torch.nn.functional.normalize(flatten_feats(sf).double(), dim=0)
    return out


def build_references(scene, cameras, background, painting, photos, net, *, eval_height: int = EVAL_HEIGHT,
                     cache_dir=None, device="cpu", log=None) -> Refs:
    """References of (scene, painting, views). ``net`` a VGG16Features; without pretrained weights the
    common field is not built (flow alignment is then not measured). ``log``: a line per stage."""
    log = log or (lambda msg: None)
    painting = np.ascontiguousarray(M._np(painting)[..., :3], np.float32)
    photos = [np.ascontiguousarray(M._np(p)[..., :3], np.float32) for p in photos]
    pretrained = not net.is_random
    key = content_key(scene, cameras, background, painting, photos, net, eval_height)
    refs = Refs(list(cameras), [], [], photos, [], None, painting, tuple(background), eval_height, pretrained, key)
    log("references: the painting's statistics")
    refs.painting_stats = _painting_side(net, painting, eval_height, pretrained)
    path = None if cache_dir is None else (Path(cache_dir) / f"{key}.npz")
    if path is not None and path.is_file():
        log(f"references: cached ({path})")
        refs = _load_cached(refs, path)
        if pretrained:
            dev = next(net.parameters()).device
            refs.photo_feats = [{k: v.to(dev) for k, v in f.items()} for f in refs.photo_feats]
        return refs
    if pretrained:
        log(f"references: content features of {len(photos)} photos")
        refs.photo_feats = [f["content"] for f in M.vgg_feats_batch(
            net, [M.resize_to_height(p, eval_height) for p in photos])]
    log(f"references: rendering the un-stylized scene ({len(cameras)} views, 1x and 2x)")
    refs.base = render_views(scene, cameras, background, device)
    refs.alpha2x = [v["alpha"] for v in render_views(scene, [scaled(c, 2.0) for c in cameras], background, device)]
    refs.recolored = [np.asarray(x, np.float32) for x in color_transfer(photos, painting)[0]]
    if pretrained:
        log("references: the common stroke field of every view")
        ps = refs.painting_stats
        refs.fields = [common_field(net, b["color"], painting, ps["cells_field"], ps["cells_feats"])
                       for b in refs.base]
    if path is not None:
        _save_cached(refs, path)
    return refs


def _save_cached(refs: Refs, path) -> None:
    arrs = {}
    for i, b in enumerate(refs.base):
        arrs |= {f"color{i}": b["color"], f"depth{i}": b["depth"], f"alpha{i}": b["alpha"],
                 f"alpha2x{i}": refs.alpha2x[i], f"recolored{i}": refs.recolored[i]}
        if refs.fields is not None:
            arrs[f"field{i}"] = refs.fields[i]
        for k, f in (refs.photo_feats[i].items() if refs.photo_feats else ()):
            arrs[f"photo_{k}_{i}"] = f.cpu().numpy()
    buf = io.BytesIO()
    np.savez(buf, **arrs)
    write_bytes(path, buf.getvalue())


def _load_cached(refs: Refs, path) -> Refs:
    """The cached arrays: plain numeric arrays only (``allow_pickle=False``: an array of Python objects, which
    unpickling would construct, is refused), all present, each a number array. One line when not."""
    n = len(refs.cameras)
    try:
        with np.load(path, allow_pickle=False) as z:
            def get(k):
                a = z[k]
                if a.dtype.kind not in "fiub":
                    raise ValueError(f"array {k} is {a.dtype}, not numbers")
                return a

            base = [{"color": get(f"color{i}"), "depth": get(f"depth{i}"), "alpha": get(f"alpha{i}")}
                    for i in range(n)]
            alpha2x = [get(f"alpha2x{i}") for i in range(n)]
            recolored = [get(f"recolored{i}") for i in range(n)]
            fields = [get(f"field{i}") for i in range(n)] if refs.pretrained else None
            photo_feats = [{k: torch.from_numpy(get(f"photo_{k}_{i}")) for k in M.CONTENT_LAYERS}
                           for i in range(n)] if refs.pretrained else []
    except Exception as e:  # noqa: BLE001 - a damaged or foreign cache file is one line, never code
        why = "it holds Python objects, which are never unpickled" if "allow_pickle" in str(e) else \
            f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
        raise InputError(f"unreadable reference cache ({why}); delete it to rebuild it", path) from None
    refs.base, refs.alpha2x, refs.recolored, refs.fields = base, alpha2x, recolored, fields
    refs.photo_feats = photo_feats
    return refs


# ---------------------------------------------------------------- one run
def stylized_views(g, refs: Refs, device="cpu") -> tuple[list, list]:
    """(views at training size [{"color","alpha"}], alphas at 2x) of a stylized scene."""
    views = render_views(g, refs.cameras, refs.background, device)
    a2 = [v["alpha"] for v in render_views(g, [scaled(c, 2.0) for c in refs.cameras], refs.background, device)]
    return views, a2


def score_views(views: list, alpha2x: list, refs: Refs, net) -> dict:
    """Per-view values {metric: [value per view]} (consistency: per pair (i, i+k), indexed by i). Metrics that
    need pretrained features are None (not measured) when ``net`` is random."""
    n = len(views)
    per = {k: [] for k, m in M.METRICS.items() if m.per_view}
    ps = refs.painting_stats
    imgs = [np.ascontiguousarray(v["color"], np.float32) for v in views]
    evs = [M.resize_to_height(img, refs.eval_height) for img in imgs]
    measured = refs.pretrained and not net.is_random
    # each view's pixels inside the scene at the evaluation size: an object's outline is not brushwork
    insides = [M.interior(refs.base[i]["alpha"], evs[i].shape[:2]) for i in range(n)]
    feats = M.vgg_feats_batch(net, evs, insides) if measured else [None] * n
    for i, v in enumerate(views):
        img, ev, f, inside = imgs[i], evs[i], feats[i], insides[i]
        per["stroke_scales"].append(M.stroke_distance(M.stroke_descriptor(img, refs.base[i]["alpha"]),
                                                      ps["strokes"]))
        per["detail"].append(M.detail(ev, ps["hf"]))
        per["detail_inside"].append(M.detail(ev, ps["hf"], inside))
        per["tone_inside"].append(M.tone_distance(ev, ps["tones"], inside))
        per["colour_inside"].append(M.colour_distance(ev, ps["colours"], inside))
        per["holes_1x"].append(M.holes(v["alpha"], refs.base[i]["alpha"]))
        per["holes_2x"].append(M.holes(alpha2x[i], refs.alpha2x[i]))
        per["spill"].append(M.spill(v["alpha"], refs.base[i]["alpha"]))
        per["chroma_noise"].append(M.hf_energy(M.lab_ab(img)) / max(M.hf_energy(M.lab_ab(refs.recolored[i])), 1e-12))
        if measured:
            per["flow_alignment"].append(M.flow_alignment(img, refs.fields[i]))
            per["flow_energy"].append(M.flow_energy(img, refs.fields[i]))
            per["style_gram"].append(M.style_gram(f["grams"], ps["grams"]))
            per["style_gram_inside"].append(M.style_gram(f["grams_inside"], ps["grams"]))
            per["style_nnfm"].append(M.style_nnfm(f["relu3"], ps["relu3"]))
            per["style_nnfm_inside"].append(M.style_nnfm(f["relu3_inside"], ps["relu3"]))
            per["content"].append(M.content(f["content"], refs.photo_feats[i]))
    for k in M.KS:
        per[f"consistency_k{k}"] = [M.pair_error(views[i], views[i + k], correspondences(refs, i, k))
                                    for i in range(n - k)]
    for k, m in M.METRICS.items():
        if m.per_view and m.pretrained and not per[k]:
            per[k] = None  # not measured
    return per


def correspondences(refs: Refs, i: int, k: int):
    """The un-stylized scene's correspondences of views i and i+k (the same for every run: built once)."""
    if (i, k) not in refs.corr:
        refs.corr[(i, k)] = M.correspondences(refs.base[i], refs.base[i + k], refs.cameras[i], refs.cameras[i + k])
    return refs.corr[(i, k)]


def anchor_views(refs: Refs) -> dict:
    """The anchors every evaluation scores beside the runs, as (views, alphas at 2x) like ``stylized_views``:
    "no stylization" (the un-stylized scene's own renders and coverage) and "sticker" (the painting
    center-cropped and resized over the whole of every view: full coverage, no scene, no 3D)."""
    un = [{"color": b["color"], "alpha": b["alpha"]} for b in refs.base]
    st = [{"color": M.sticker(refs.painting, *b["color"].shape[:2]), "alpha": np.ones_like(b["alpha"])}
          for b in refs.base]
    return {M.UNSTYLIZED: (un, list(refs.alpha2x)), M.STICKER: (st, [np.ones_like(a) for a in refs.alpha2x])}


def summarize(per: dict, groups: dict | None = None) -> dict:
    """Per metric the mean and interval over views. ``groups``: {metric: one label per view item} (the seed of
    each item where runs of several seeds are pooled: a two-stage bootstrap, metrics.interval)."""
    g = groups or {}
    return {k: (None if v is None else M.interval(v, groups=g.get(k))) for k, v in per.items()}


def compare(per_a: dict, per_b: dict, groups: dict | None = None) -> dict:
    """Paired comparison of two runs scored on the same references, per metric measured for both (``groups``:
    as in :func:`summarize`)."""
    g = groups or {}
    return {k: M.paired(per_a[k], per_b[k], M.METRICS[k], groups=g.get(k)) for k in per_a
            if per_a[k] is not None and per_b.get(k) is not None}


__all__ = ["Refs", "build_references", "score_views", "stylized_views", "summarize", "compare", "render_views",
           "scaled", "anchor_views"]
