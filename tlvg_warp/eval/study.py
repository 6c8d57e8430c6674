"""A study: configs x scenes x paintings x seeds, each scene fitted once, every stylization run once (finished
runs are skipped, interrupted ones resumed), every (scene, painting) evaluated with one ruler together with its
anchors (the un-stylized scene and the painting pasted over every view), then the paper's Table 1 per scene (a
row per config with its wall time, the anchors as reference rows), the ablation table, the speed-quality chart,
optionally the VLM panel; written as study.json, study.csv and study.html. Intervals are over seeds and views: a
two-stage bootstrap draws seeds, then views within each (metrics.interval).

STUDY.yaml (paths relative to the YAML file):
    out: runs/study            # study folder
    device: auto               # cpu | cuda | auto (stylize and evaluate)
    iterations: null           # null: each config's own schedule (abcgs 1400 = 400/600/400, tlvg 3000);
                               # a number forces that many steps on every config (smoke runs)
    seeds: 3                   # stylizations per (scene, painting, config), seeds 0..N-1
    vgg_weights: null          # null: the default resolution (SPEC §3); random: smoke runs
    eval_height: 256           # style/content evaluation height
    max_views: 0               # evaluate the first N views (0: all)
    set: []                    # KEY=VALUE overrides for every stylization
    configs: {tlvg: configs/tlvg.yaml, abcgs: configs/abcgs.yaml, ...}
    ours: tlvg
    baseline: abcgs
    ablations: [no_advection, ...]  # compared with `ours` in the ablation table
    scenes: {fern: {data: path, downscale: 4, fit_iterations: 7000}, demo: {demo: true, downscale: 4}}
    paintings: {starry_night: path}
    judge: {models: [m1, m2], base_url: URL, max_views: 4}   # used with --judge
"""
from __future__ import annotations

import csv
import io
import os
import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..config_io import read_yaml_mapping
from ..distributed import Dist, local_only
from ..errors import InputError, WriteError, one_line
from ..fileio import write_json, write_text
from ..io import load_dataset
from ..losses.vgg import load_vgg
from ..stylize.job import stylize_run
from ..stylize.pipeline import StylizeDiverged
from ..train.reconstruct import ReconstructConfig, fit_scene
from . import judge
from . import metrics as M
from . import report as H
from .engine import evaluate_runs, not_discriminating, report_html, winners
from .refs import compare, summarize

TOP_KEYS = {"out", "device", "iterations", "seeds", "vgg_weights", "eval_height", "max_views", "set", "configs",
            "ours", "baseline", "ablations", "scenes", "paintings", "judge"}
DEFAULT_SEEDS = 3


@dataclass
class Study:
    path: Path
    out: Path
    configs: dict
    scenes: dict
    paintings: dict
    device: str = "auto"
    iterations: int | None = None  # None: each config's own schedule
    seeds: int = DEFAULT_SEEDS
    vgg_weights: str | None = None
    eval_height: int = 256
    max_views: int = 0
    overrides: list = field(default_factory=list)
    ours: str | None = None
    baseline: str | None = None
    ablations: list = field(default_factory=list)
    judge: dict = field(default_factory=dict)


def load_study(path) -> Study:
    path = Path(path)
    d = read_yaml_mapping(path, "study file")
    bad = sorted(set(d) - TOP_KEYS)
    if bad:
        raise InputError(f"unknown key(s) {bad}; known: {sorted(TOP_KEYS)}", path)
    for k in ("configs", "scenes", "paintings"):
        if not isinstance(d.get(k), dict) or not d[k]:
            raise InputError(f"'{k}' must be a non-empty mapping of name: ...", path)
    root = path.parent
    rel = lambda p: p if p in (None, "builtin") else str((root / p).resolve())  # noqa: E731
    configs = {n: rel(p) for n, p in d["configs"].items()}
    for n, p in configs.items():
        if not Path(p).is_file():
            raise InputError(f"config {n!r}: {p} not found", path)
    scenes = {}
    for n, s in d["scenes"].items():
        s = dict(s or {})
        if not s.get("demo"):
            if not s.get("data") or not Path(rel(s["data"])).exists():
                raise InputError(f"scene {n!r}: data {s.get('data')!r} not found", path)
            s["data"] = rel(s["data"])
        scenes[n] = s
    paintings = {n: rel(p) for n, p in d["paintings"].items()}
    for n, p in paintings.items():
        if p != "builtin" and not Path(p).is_file():
            raise InputError(f"painting {n!r}: {p} not found", path)
    iters = d.get("iterations")
    seeds = d.get("seeds", DEFAULT_SEEDS)
    if iters is not None and (not isinstance(iters, int) or iters < 1):
        raise InputError(f"iterations must be null (each config's own schedule) or >= 1, got {iters!r}", path)
    if not isinstance(seeds, int) or seeds < 1:
        raise InputError(f"seeds must be an integer >= 1, got {seeds!r}", path)
    st = Study(path, Path(rel(d.get("out", "study"))), configs, scenes, paintings, str(d.get("device", "auto")),
               iters, seeds, d.get("vgg_weights"), int(d.get("eval_height", 256)),
               int(d.get("max_views", 0)), list(d.get("set") or []), d.get("ours"), d.get("baseline"),
               list(d.get("ablations") or []), dict(d.get("judge") or {}))
    for role in ("ours", "baseline", *st.ablations):
        name = getattr(st, role) if role in ("ours", "baseline") else role
        if name is not None and name not in configs:
            raise InputError(f"{role} {name!r} is not one of the configs {sorted(configs)}", path)
    return st


def only_configs(st: Study, names) -> Study:
    """Keep the named configs (a subset, e.g. to spend less device time); roles that lose their config are
    dropped (no ablation row without ours)."""
    unknown = [n for n in names if n not in st.configs]
    if unknown or not names:
        raise InputError(f"--only-configs: {unknown or 'nothing'} not among the configs {sorted(st.configs)}", st.path)
    st.configs = {n: p for n, p in st.configs.items() if n in names}
    st.ours = st.ours if st.ours in st.configs else None
    st.baseline = st.baseline if st.baseline in st.configs else None
    st.ablations = [a for a in st.ablations if a in st.configs]
    return st


def resolve_device(dev: str) -> str:
    return ("cuda" if torch.cuda.is_available() else "cpu") if dev == "auto" else dev


# ---------------------------------------------------------------- running
def fit_scene_once(st: Study, name: str, log, device: str | None = None) -> Path | None:
    """The scene's un-stylized PLY (fitted here once); None for the built-in demo."""
    s = st.scenes[name]
    if s.get("demo"):
        return None
    ply = st.out / "scenes" / name / "point_cloud.ply"
    if ply.is_file():
        log(f"scene {name}: fitted already ({ply})")
        return ply
    ds = load_dataset(s["data"], downscale=s.get("downscale"))
    rc = ReconstructConfig(iterations=int(s.get("fit_iterations", 7000)), holdout_every=0,
                           device=device or resolve_device(st.device), save_renders=False)
    log(f"scene {name}: fitting {len(ds.cameras)} photos ({rc.iterations} iterations)")
    fit_scene(ds, rc, ply.parent, progress=False, overwrite=True)
    return ply


def run_dir(st: Study, scene: str, painting: str, config: str, seed: int = 0) -> Path:
    return st.out / "runs" / scene / painting / config / f"seed_{seed}"


def run_dirs(st: Study, scene: str, painting: str, config: str) -> list[Path]:
    return [run_dir(st, scene, painting, config, k) for k in range(st.seeds)]


def finished(d: Path) -> bool:
    return (d / "metrics.json").is_file() and (d / "stylized.ply").is_file()


def stylize_kwargs(st: Study, scene: str, ply, painting: str, config: str, seed: int,
                   device: str | None = None) -> dict:
    """One run's stylize_run keywords (stylize/job.py; `stylize`'s options): the config's own schedule unless the
    study forces `iterations`."""
    s = st.scenes[scene]
    kw = {"config": st.configs[config], "out": str(run_dir(st, scene, painting, config, seed)),
          "device": device or resolve_device(st.device), "quiet": True,
          "overrides": [f"seed={seed}", *(str(o) for o in st.overrides)], "iterations": st.iterations,
          "vgg_weights": None if st.vgg_weights is None else str(st.vgg_weights)}
    if st.paintings[painting] != "builtin":
        kw["style"] = st.paintings[painting]
    if ply is not None:
        kw |= {"scene": str(ply), "data": s["data"]}
    if s.get("downscale"):
        kw["downscale"] = s["downscale"]
    return kw


def stylize_once(st: Study, scene: str, ply, painting: str, config: str, log, device: str | None = None,
                 seed: int = 0) -> str:
    """'skipped' (finished before), 'ran', or 'failed (why)'."""
    d = run_dir(st, scene, painting, config, seed)
    key = f"{scene}/{painting}/{config}/seed_{seed}"
    if finished(d):
        log(f"skip {key}: finished")
        return "skipped"
    kw = stylize_kwargs(st, scene, ply, painting, config, seed, device)
    if (d / "checkpoint.pt").is_file():
        kw["resume"] = str(d)
    elif d.exists():
        kw["overwrite"] = True
    log(f"stylize {key} ...")
    try:
        stylize_run(**kw)
    except (InputError, WriteError, StylizeDiverged) as e:
        log(f"error: {key}: {one_line(e)}")
        return f"failed ({type(e).__name__})"
    return "ran" if finished(d) else "failed (no outputs)"


# ---------------------------------------------------------------- tables
def pooled(per_lists: list) -> dict:
    """Per-view dicts of several (scene, painting) evaluations of one config, concatenated in a fixed order,
    so configs stay paired view by view."""
    out = {}
    for pv in per_lists:
        for k, v in pv.items():
            out[k] = None if v is None or out.get(k, []) is None else out.get(k, []) + list(v)
    return out


def seed_groups(per_lists: list, seed_index: list) -> dict:
    """{metric: the seed of every pooled item}, for per-view dicts pooled in this order (``seed_index``: the seed
    of each dict): the intervals then draw seeds first, then views within each (metrics.interval)."""
    out = {}
    for pv, k in zip(per_lists, seed_index):
        for m, v in pv.items():
            if v is not None:
                out.setdefault(m, []).extend([k] * len(v))
    return out


def config_rows(names, per_views, times, counts, anchors: dict | None = None,
                groups: dict | None = None) -> tuple[list, dict, dict]:
    """(rows: one per config, then one per anchor with "anchor": True; winners; not-discriminating marks). A
    config wins a metric only where it also beats the anchor the metric exists to beat (evaluate's rule).
    ``groups``: :func:`seed_groups` of the pooled items (None: one seed, items drawn alike)."""
    anchors = anchors or {}
    rows = [{"config": n, **summarize(pv, groups), "gaussians": c, "wall_time_s": t}
            for n, pv, t, c in zip(names, per_views, times, counts)]
    rows += [{"config": a, "anchor": True, **summarize(pv, groups)} for a, pv in anchors.items()]
    return rows, winners(names, per_views, anchors, groups), not_discriminating(per_views, anchors, groups)


def ablation_rows(st: Study, pooled_all: dict, groups: dict | None = None) -> list:
    out = []
    if st.ours not in pooled_all:
        return out
    for a in st.ablations:
        if a in pooled_all:
            out.append({"config": a, **compare(pooled_all[a], pooled_all[st.ours], groups)})
    return out


def csv_text(tables: dict, ablation: list) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["table", "config", "kind", "metric", "mean", "lo", "hi", "n", "winner_or_verdict"])
    for scene, t in tables.items():
        nd = t.get("not_discriminating") or {}
        for r in t["rows"]:
            kind = "anchor" if r.get("anchor") else "config"
            for k in M.METRICS:
                if r.get("anchor") and k not in r:
                    continue
                v = r.get(k)
                verdict = "winner" if t["winners"].get(k) == r["config"] else ""
                if r.get("anchor") and nd.get(k) == r["config"]:
                    verdict = "beats every config: not discriminating"
                if isinstance(v, dict):
                    w.writerow([scene, r["config"], kind, k, v["mean"], v["lo"], v["hi"], v["n"], verdict])
                elif v is not None:
                    w.writerow([scene, r["config"], kind, k, v, "", "", "", ""])
                elif M.METRICS[k].per_view:
                    w.writerow([scene, r["config"], kind, k, "not measured", "", "", "", ""])
    for r in ablation:
        for k, v in r.items():
            if k != "config" and isinstance(v, dict):
                w.writerow(["ablation (config - ours)", r["config"], "config", k, v["mean"], v["lo"], v["hi"],
                            v["n"], v["better"]])
    return buf.getvalue()


def job_queue(st: Study, dist, launch: str, kind: str, jobs: list):
    """This rank's share of `jobs`, taken one at a time from a queue shared by every rank of the launch: a job
    belongs to the rank that first creates its claim file (O_CREAT | O_EXCL, atomic on a local disk and on
    NFS v3+) in STUDY_OUT/.claims/<launch>/, so a rank that finishes early takes the next unclaimed job.
    Claims are per launch: a later launch (resume) claims every job anew and skips the finished ones."""
    folder = st.out / ".claims" / launch
    folder.mkdir(parents=True, exist_ok=True)
    for key in jobs:
        path = folder / (kind + "__" + key.replace("/", "__"))
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            continue
        with os.fdopen(fd, "w") as f:
            f.write(f"rank {dist.rank} pid {os.getpid()}\n")
        yield key


def new_launch_id(dist) -> str:
    """One id for the whole launch (the main rank's, broadcast): names this launch's claim folder."""
    mine = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}-{uuid.uuid4().hex[:8]}" if dist.is_main else None
    return dist.broadcast_object(mine)


def run_study(st: Study, judge_cfg: dict | None = None, log=print, dist=None) -> dict | None:
    """Run the study; under torchrun (`dist.world` > 1) its jobs are spread over the ranks: the scene fits
    first (a shared queue, then a barrier), then the stylizations (the same queue: one job per rank at a
    time), then the evaluations (one (scene, painting) per rank at a time); the main rank gathers every
    rank's results and writes the one table. Returns the result on the main rank, None on the others."""
    dist = dist or Dist()
    t0 = time.perf_counter()
    dev_name = resolve_device(st.device)
    device = torch.device(dev_name)
    if dist.world > 1:
        inner = log
        log = lambda msg: inner(f"[rank {dist.rank}/{dist.world}] {msg}")  # noqa: E731
    if dist.is_main:
        st.out.mkdir(parents=True, exist_ok=True)
    launch = new_launch_id(dist)
    keys = [f"{s}/{p}/{c}/seed_{k}" for s in st.scenes for p in st.paintings for c in st.configs
            for k in range(st.seeds)]
    status, ranks, evals, net = _run_jobs(st, dist, launch, keys, log, dev_name, device)
    parts = dist.gather_objects({"status": status, "ranks": ranks, "evals": evals})
    if not dist.is_main:
        dist.barrier()  # the main rank's report is written before any rank returns
        return None
    status, ranks, evals = {}, {}, {}
    for part in parts:
        status |= part["status"]
        ranks |= part["ranks"]
        evals |= part["evals"]
    status = {k: status.get(k, "not run") for k in keys}  # the order of one process
    if net is None:
        net = load_vgg(st.vgg_weights, device=device)
    tables, pooled_all, anchors_all, groups_all = _scene_tables(st, evals)
    pooled_all = {c: pooled(v) for c, v in pooled_all.items() if len(v) == len(tables)}
    anchors_all = {a: pooled(v) for a, v in anchors_all.items() if len(v) == len(tables)}
    g_all = pooled(groups_all) if groups_all and len(groups_all) == len(tables) else {}  # in the scenes' order
    overall = {c: summarize(pv, g_all) for c, pv in pooled_all.items()}
    overall_anchors = {a: summarize(pv, g_all) for a, pv in anchors_all.items()}
    all_times = {c: _mean([r["wall_time_s"] for t in tables.values() for r in t["rows"] if r["config"] == c])
                 for c in pooled_all}
    result = {"study": str(st.path), "out": str(st.out), "device": str(device), "vgg": net.source,
              "vgg_random": bool(net.is_random), "iterations": st.iterations, "seeds": st.seeds, "status": status,
              "tables": tables, "ablation": ablation_rows(st, pooled_all, g_all or None), "overall": overall,
              "overall_anchors": overall_anchors,
              "times": all_times, "ours": st.ours, "baseline": st.baseline,
              "ranks": {"world": dist.world, "stylized_by": {k: ranks[k] for k in keys if k in ranks}}}
    if judge_cfg:
        result["judge"] = run_panel(st, judge_cfg, log)
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    write_json(st.out / "study.json", result)
    write_text(st.out / "study.csv", csv_text(tables, result["ablation"]))
    write_text(st.out / "study.html", study_html(result))
    shutil.rmtree(st.out / ".claims" / launch, ignore_errors=True)
    dist.barrier()
    return result


def _run_jobs(st: Study, dist, launch: str, keys: list, log, dev_name: str, device) -> tuple:
    """This rank's share of the study's jobs: the scene fits, then the stylizations ``keys``
    (scene/painting/config/seed_k), then the evaluations per (scene, painting). Returns (status per run key,
    rank per run key, evaluations per (scene, painting): run name -> its result and "__anchors__", the VGG loaded
    for them or None)."""
    fit_jobs = [s for s in st.scenes if not st.scenes[s].get("demo")]
    with local_only():  # every job is a whole single-process run on this rank's device
        for s in job_queue(st, dist, launch, "fit", fit_jobs):
            fit_scene_once(st, s, log, device=dev_name)
        dist.barrier()  # every scene is fitted before any stylization reads it
        plys = {s: (None if st.scenes[s].get("demo") else st.out / "scenes" / s / "point_cloud.ply")
                for s in st.scenes}
        status, ranks = {}, {}
        for key in job_queue(st, dist, launch, "stylize", keys):
            s, p, c, sd = key.split("/")
            status[key] = stylize_once(st, s, plys[s], p, c, log, device=dev_name, seed=int(sd.split("_")[1]))
            ranks[key] = dist.rank
        dist.barrier()  # every run is finished (or failed) before any evaluation reads them
        net = None
        evals = {}
        groups = [f"{s}/{p}" for s in st.scenes for p in st.paintings]
        for g in job_queue(st, dist, launch, "evaluate", groups):
            s, p = g.split("/")
            dirs = [d for c in st.configs for d in run_dirs(st, s, p, c) if finished(d)]
            if not dirs:
                continue
            if net is None:
                net = load_vgg(st.vgg_weights, device=device)
            res, runs, refs = evaluate_runs(dirs, net, device, scene=plys[s], max_views=st.max_views,
                                            eval_height=st.eval_height, log=log,
                                            cache_dir=st.out / "eval_cache")
            out = st.out / "eval" / f"{s}__{p}"
            write_json(out / "evaluation.json", res)
            write_text(out / "evaluation.html", report_html(res, runs, refs))
            evals[(s, p)] = {f"{Path(r['run']).parent.name}/{Path(r['run']).name}": r for r in res["runs"]}
            evals[(s, p)]["__anchors__"] = {a["name"]: a for a in res.get("anchors") or []}
    return status, ranks, evals, net


def _scene_tables(st: Study, evals: dict) -> tuple:
    """Per scene, the configs' rows against the anchors over its paintings and seeds, and what pools them over
    the scenes: (tables, pooled per-view values per config and per anchor (one entry per scene), seed groups)."""
    configs = list(st.configs)
    seeds = [f"seed_{k}" for k in range(st.seeds)]
    tables, pooled_all, anchors_all, groups_all = {}, {}, {}, []
    for s in st.scenes:
        # a config counts where every (painting, seed) run finished; its views are pooled in the order (painting,
        # seed, view), and each anchor's views are repeated per seed in the same order, so every row stays paired
        have = [c for c in configs if all(f"{c}/{k}" in evals.get((s, p), {}) for p in st.paintings for k in seeds)]
        runs_of = lambda c: [evals[(s, p)][f"{c}/{k}"] for p in st.paintings for k in seeds]  # noqa: E731
        pv = [pooled([r["per_view"] for r in runs_of(c)]) for c in have]
        times = [_mean([r["summary"]["wall_time_s"] for r in runs_of(c)]) for c in have]
        counts = [_mean([r["summary"]["gaussians"] for r in runs_of(c)]) for c in have]
        names_a = [a for a in M.ANCHORS if all(a in evals.get((s, p), {}).get("__anchors__", {}) for p in st.paintings)]
        anchors = {a: pooled([evals[(s, p)]["__anchors__"][a]["per_view"] for p in st.paintings for _ in seeds])
                   for a in names_a} if have else {}
        # several seeds: intervals draw seeds, then views (the runs of one seed index stay together across paintings)
        groups = (seed_groups([r["per_view"] for r in runs_of(have[0])],
                              [k for _ in st.paintings for k in range(st.seeds)]) if have and st.seeds > 1 else None)
        rows, win, nd = config_rows(have, pv, times, counts, anchors, groups)
        tables[s] = {"rows": rows, "winners": win, "not_discriminating": nd, "seeds": st.seeds}
        if groups is not None:
            groups_all.append(groups)
        for c, v in zip(have, pv):
            pooled_all.setdefault(c, []).append(v)
        for a, v in anchors.items():
            anchors_all.setdefault(a, []).append(v)
    return tables, pooled_all, anchors_all, groups_all


def _mean(xs):
    xs = [x for x in xs if isinstance(x, (int, float))]
    return sum(xs) / len(xs) if xs else None


def run_panel(st: Study, jc: dict, log) -> dict:
    """The VLM panel on ours vs baseline for every (scene, painting): {scene/painting: judge result}."""
    out = {}
    for s in st.scenes:
        for p in st.paintings:
            a, b = run_dir(st, s, p, st.ours), run_dir(st, s, p, st.baseline)  # seed 0 of each
            if finished(a) and finished(b):
                res = judge.run_judge(a, b, jc["models"], jc["base_url"], jc.get("api_key"),
                                      max_views=jc.get("max_views"), log=None)
                out[f"{s}/{p}"] = res
                write_json(st.out / "judge" / f"{s}__{p}.json", res)
                log(judge.format_table(res))
    return out


# ---------------------------------------------------------------- report
def config_table_html(rows, winners, not_disc=None) -> str:
    """Table 1 of one scene: a row per config, then the anchors as grey reference rows; the winner's cell green;
    a metric whose anchor beats every config says so under the table."""
    nd = not_disc or {}
    keys = [k for k in M.METRICS if any(k in r for r in rows)]
    head = "<tr><th class=l>config</th>" + "".join(
        f"<th title='{H.esc(M.METRICS[k].unit)}'>{H.esc(M.METRICS[k].words)}<br><span class=small>"
        f"{H.esc(M.METRICS[k].unit)}; {'↑' if M.METRICS[k].higher_better else '↓'}</span></th>" for k in keys) + "</tr>"
    body = []
    for r in rows:
        if r.get("anchor"):
            tds = "".join(f"<td class=ref>{H.cell(r.get(k)) if k in r else ''}</td>" for k in keys)
            body.append(f"<tr><td class='l ref'><i>{H.esc(r['config'])}</i> <span class=small>(reference)"
                        f"</span></td>{tds}</tr>")
            continue
        tds = "".join(f"<td{' class=win' if winners.get(k) == r['config'] else ''}>{H.cell(r.get(k))}</td>"
                      for k in keys)
        body.append(f"<tr><td class=l><b>{H.esc(r['config'])}</b></td>{tds}</tr>")
    notes = "".join(f"<li><span class=nd>{H.esc(M.METRICS[k].words)}: not discriminating</span> ({H.esc(a)} "
                    f"beats every config)</li>" for k, a in nd.items())
    return f"<table>{head}{''.join(body)}</table>" + (f"<ul class=small>{notes}</ul>" if notes else "")


def ablation_html(rows, ours) -> str:
    if not rows:
        return "<p class=small>no ablations</p>"
    keys = [k for k in M.METRICS if any(k in r for r in rows)]
    head = "<tr><th class=l>ablation</th>" + "".join(f"<th>{H.esc(M.METRICS[k].words)}<br><span class=small>"
                                                    f"{'↑' if M.METRICS[k].higher_better else '↓'}</span></th>"
                                                    for k in keys) + "</tr>"
    body = []
    for r in rows:
        tds = []
        for k in keys:
            d = r.get(k)
            if not d or d.get("mean") is None:
                tds.append("<td>–</td>")
                continue
            word = {"a": "better", "b": "worse"}.get(d["better"], d["better"])
            tds.append(f"<td>{H.fmt(d['mean'], 3)} <span class=small>[{H.fmt(d['lo'], 3)}, {H.fmt(d['hi'], 3)}]"
                       f"</span><br>{word}</td>")
        body.append(f"<tr><td class=l><b>{H.esc(r['config'])}</b></td>{''.join(tds)}</tr>")
    return (f"<p class=small>Each cell: the ablation minus {H.esc(ours)}, mean paired difference over every view of "
            f"every scene and painting with its 95% interval; 'worse' / 'better' only when the interval excludes 0."
            f"</p><table>{head}{''.join(body)}</table>")


def judge_html(panel: dict) -> str:
    parts = []
    for key, res in panel.items():
        parts.append(f"<h3>{H.esc(key)}</h3><pre>{H.esc(judge.format_table(res))}</pre>")
    return "".join(parts)


def study_html(res: dict) -> str:
    iters = ("each config's own schedule" if res.get("iterations") is None
             else f"{res['iterations']} iterations per run")
    body = [f"<p>{H.esc(res['study'])}: {iters}, {res.get('seeds', 1)} seed(s) per config (intervals over seeds "
            f"and views) on {H.esc(res['device'])}; VGG: {H.esc(res['vgg'])}</p>"]
    if res["vgg_random"]:
        body.append("<p class=warn>VGG-16 weights are random: style, content and flow alignment are not measured."
                    "</p>")
    body += [H.METHOD_NOTE, H.ANCHOR_NOTE]
    for s, t in res["tables"].items():
        body.append(f"<h2>Scene {H.esc(s)}</h2>" + config_table_html(t["rows"], t["winners"],
                                                                      t.get("not_discriminating")))
    body.append(f"<h2>Ablations (vs {H.esc(res['ours'])})</h2>" + ablation_html(res["ablation"], res["ours"]))
    names = list(res["overall"])
    sums = [res["overall"][n] for n in names]
    body.append("<h2>Speed and quality (all scenes)</h2>"
                + H.speed_chart(names, [res["times"].get(n) for n in names], sums))
    an = list(res.get("overall_anchors") or {})
    body.append("<h2>Means with 95% intervals (all scenes)</h2>"
                + H.bars_chart(names + an, sums + [res["overall_anchors"][a] for a in an]))
    if res.get("judge"):
        body.append("<h2>VLM-as-a-judge</h2>" + judge_html(res["judge"]))
    links = "".join(f"<li>{H.esc(k)}: {H.esc(v)}</li>" for k, v in res["status"].items())
    body.append(f"<h2>Runs</h2><ul class=small>{links}</ul><p class=small>Per (scene, painting) reports: "
                f"eval/&lt;scene&gt;__&lt;painting&gt;/evaluation.html</p>")
    return H.page("tlvg_warp study", "".join(body))
