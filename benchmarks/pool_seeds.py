"""Pool the seeds of each config in a study's evaluations: intervals over seeds and views, as the `study` command gives.

    python benchmarks/pool_seeds.py STUDY OUT --pool tlvg=tlvg,tlvg_s1,tlvg_s2 --pool abcgs=abcgs,abcgs_s1,abcgs_s2

For each pair evaluated under STUDY/<scene>/<painting>/evaluation/ (tune.py's layout, every seed a run of its own
on the same views): the pooled config's per-view scores are the seeds' concatenated (seed, view) in the order
given, and each anchor's per-view scores are repeated once per seed in the same order, so the paired comparisons
stay paired item by item (the `study` command's pooling, eval/study.py). Intervals are a two-stage bootstrap (seeds
drawn with replacement, then views within each drawn seed; metrics.interval), so they hold the spread between seeds.
A pair where a pooled config lacks a seed is refused. The pooled run's metrics.json is its first seed's;
``seed_spread`` in the output lists each seed's mean of every metric, so run-to-run spread is read beside the
intervals. Writes the layout `study_table.py` reads.
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from tlvg_warp.eval.engine import not_discriminating, pair_comparisons, winners
from tlvg_warp.eval.refs import summarize
from tlvg_warp.eval.study import pooled, seed_groups


def mean(v):
    return None if v is None else sum(v) / len(v)


def pool(ev: dict, pools: dict) -> dict | None:
    """The evaluation ``ev`` with each pool's seeds replaced by one pooled run, or None where a seed is missing or
    the pools' seeds were scored on different numbers of views (their items would not pair). Every pool has the same
    number of seeds (main checks it: the anchors are repeated once per seed)."""
    by_name = {r["name"]: r for r in ev["runs"]}
    if any(s not in by_name for seeds in pools.values() for s in seeds):
        return None
    runs, spread = [], {}
    groups = None  # {metric: the seed index of each pooled item}: the intervals draw seeds, then views
    for name, seeds in pools.items():
        pv = pooled([by_name[s]["per_view"] for s in seeds])
        g = seed_groups([by_name[s]["per_view"] for s in seeds], list(range(len(seeds))))
        if groups is not None and g != groups:
            return None  # the pools' items must line up (same views per seed) to be compared
        groups = g
        first = by_name[seeds[0]]
        runs.append(dict(first, name=name, summary=summarize(pv, groups) | {k: first["summary"][k] for k in
                                                                 ("gaussians", "bytes", "wall_time_s")
                                                                 if k in first["summary"]},
                         per_view=pv, seeds=list(seeds)))
        spread[name] = {s: {k: mean(v) for k, v in by_name[s]["per_view"].items()} for s in seeds}
    n = len(next(iter(pools.values())))
    anchors = [dict(a, per_view=pooled([a["per_view"]] * n)) for a in ev["anchors"]]
    for a in anchors:
        a["summary"] = summarize(a["per_view"], groups)
    names = [r["name"] for r in runs]
    per = [r["per_view"] for r in runs]
    anchor_per = {a["name"]: a["per_view"] for a in anchors}
    return dict(ev, names=names, runs=runs, anchors=anchors,
                comparisons=pair_comparisons(names, per, anchor_per, groups),
                winners=winners(names, per, anchor_per, groups),
                not_discriminating=not_discriminating(per, anchor_per, groups), seed_spread=spread,
                intervals="two-stage bootstrap: seeds, then views within each seed")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("study"), ap.add_argument("out")
    ap.add_argument("--pool", action="append", required=True, help="NAME=seed_run,seed_run,... (the first is seed 0)")
    args = ap.parse_args()
    pools = {k: v.split(",") for k, v in (x.split("=", 1) for x in args.pool)}
    if len({len(s) for s in pools.values()}) != 1:
        raise SystemExit("every pool needs the same number of seeds (the anchors are repeated once per seed)")
    study, out = Path(args.study), Path(args.out)
    for f in sorted(study.glob("*/*/evaluation/evaluation.json")):
        scene, painting = f.parents[2].name, f.parents[1].name
        res = pool(json.loads(f.read_text()), pools)
        if res is None:
            print(f"{scene} x {painting}: not pooled (a seed is missing, or the seeds' views differ)")
            continue
        dst = out / scene / painting
        (dst / "evaluation").mkdir(parents=True, exist_ok=True)
        (dst / "evaluation" / "evaluation.json").write_text(json.dumps(res))
        for name, seeds in pools.items():
            src = f.parents[1] / seeds[0] / "metrics.json"
            if src.is_file():
                (dst / name).mkdir(exist_ok=True)
                shutil.copy(src, dst / name / "metrics.json")
        print(f"{scene} x {painting}: pooled {', '.join(f'{k} ({len(v)} seeds)' for k, v in pools.items())}")


if __name__ == "__main__":
    main()
