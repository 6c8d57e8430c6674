"""Add the runs of a second study's evaluations to a first one's, pair by pair, and recompute the paired comparisons.

    python benchmarks/merge_evaluations.py STUDY_A STUDY_B OUT --take abk=abcgs --rename abcgs=abcgs_split

For two studies run on the same fitted scenes and views (one machine, one call after the other): each pair's
evaluation in B must have the same references, views and anchor scores as in A (checked, else the pair is
refused), so the runs of B can be scored against A's with `evaluate`'s own comparison. ``--take NAME=NEW`` copies
B's run NAME into A as NEW; ``--rename OLD=NEW`` renames one of A's runs first. Writes OUT/<scene>/<painting>/
evaluation/evaluation.json and copies each run's metrics.json, the layout `study_table.py` reads.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path

from tlvg_warp.eval.engine import not_discriminating, pair_comparisons, winners


def pairs_of(study: Path) -> dict:
    return {(f.parents[2].name, f.parents[1].name): f for f in sorted(study.glob("*/*/evaluation/evaluation.json"))}


def same_ruler(a: dict, b: dict) -> bool:
    """One ruler: same references key and views, and the anchors scored alike on every view."""
    if a["references"] != b["references"] or a["views"] != b["views"]:
        return False
    pa = {x["name"]: x["per_view"] for x in a["anchors"]}
    pb = {x["name"]: x["per_view"] for x in b["anchors"]}
    if {n: sorted(v) for n, v in pa.items()} != {n: sorted(v) for n, v in pb.items()}:
        return False
    # alike to 1e-9: evaluations with another thread count sum in another order (last-digit differences)
    return all(len(pa[n][m]) == len(pb[n][m]) and all(x == y or (x is not None and y is not None and
                                                                 math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-12))
                                                      for x, y in zip(pa[n][m], pb[n][m]))
               for n in pa for m in pa[n])


def merge(a: dict, b: dict, take: dict, rename: dict) -> dict:
    runs = [dict(r, name=rename.get(r["name"], r["name"])) for r in a["runs"]]
    runs += [dict(r, name=take[r["name"]]) for r in b["runs"] if r["name"] in take]
    names = [r["name"] for r in runs]
    per = [r["per_view"] for r in runs]
    anchor_per = {x["name"]: x["per_view"] for x in a["anchors"]}
    return dict(a, names=names, runs=runs, comparisons=pair_comparisons(names, per, anchor_per), winners=winners(names, per, anchor_per),
                not_discriminating=not_discriminating(per, anchor_per), merged_from_second_study=sorted(take.values()))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("a"), ap.add_argument("b"), ap.add_argument("out")
    ap.add_argument("--take", action="append", default=[], help="B's run NAME=NEW to add")
    ap.add_argument("--rename", action="append", default=[], help="A's run OLD=NEW, before adding")
    args = ap.parse_args()
    take = dict(x.split("=", 1) for x in args.take)
    rename = dict(x.split("=", 1) for x in args.rename)
    a_pairs, b_pairs, out = pairs_of(Path(args.a)), pairs_of(Path(args.b)), Path(args.out)
    for key, fa in a_pairs.items():
        ea = json.loads(fa.read_text())
        fb = b_pairs.get(key)
        eb = json.loads(fb.read_text()) if fb else None
        if eb is None or not same_ruler(ea, eb):
            print(f"{key[0]} x {key[1]}: not merged (no evaluation in B, or another ruler)")
            continue
        dst = out / key[0] / key[1]
        (dst / "evaluation").mkdir(parents=True, exist_ok=True)
        (dst / "evaluation" / "evaluation.json").write_text(json.dumps(merge(ea, eb, take, rename)))
        copies = {rename.get(r["name"], r["name"]): fa.parents[1] / r["name"] for r in ea["runs"]}
        copies |= {take[r["name"]]: fb.parents[1] / r["name"] for r in eb["runs"] if r["name"] in take}
        for name, src in copies.items():  # each run's metrics.json under its name in the merged evaluation
            if (src / "metrics.json").is_file():
                (dst / name).mkdir(exist_ok=True)
                shutil.copy(src / "metrics.json", dst / name / "metrics.json")
        print(f"{key[0]} x {key[1]}: merged")


if __name__ == "__main__":
    main()
