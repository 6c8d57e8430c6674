"""The user study (paper §4.3, "User Study"): blind pairwise rating of stylization runs by people.

A study is a list of pairs of run folders (A, B): the first run of each pair is the candidate, the second the
reference (e.g. the baseline). Each rater sees, item by item, the painting and the two runs' renders of the same
view (or their orbit videos) in a random left/right order, and picks one side per criterion (Flow Alignment,
Painterly Materiality, Aesthetic Preference). This module holds everything but the web server
(``tlvg_warp.rate_server``): what a run folder offers, the study file, each rater's item order and sides, the
answer log (one JSON line per answer, appended and synced to disk at once) and the report (win rates of A with
95% intervals per criterion, split by expertise, as a table, Markdown and a bar chart).

Files in the study folder: ``study.json`` (the pairs, views and the seed of the randomization), ``answers.jsonl``
(the log), and after ``--report``: ``report.md`` and ``report.png``.
"""
from __future__ import annotations

import datetime
import hashlib
import json
import math
import os
import random
import re
import secrets
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..fileio import atomic_path, write_json, write_text

FORMAT = 1
STUDY_FILE = "study.json"
ANSWERS_FILE = "answers.jsonl"
REPORT_MD = "report.md"
REPORT_PNG = "report.png"
# (key, name, question shown to the rater), the paper's three dimensions
CRITERIA = (
    ("flow", "Flow Alignment", "Which one's brushstrokes follow the shapes and geometry of the scene better?"),
    ("materiality", "Painterly Materiality", "Which one looks more like real paint (impasto, texture, brush marks)?"),
    ("aesthetics", "Aesthetic Preference", "Which one do you like more overall?"),
)
CRITERION_KEYS = tuple(c[0] for c in CRITERIA)
EXPERTISE = ("professional", "other")  # "are you an art professional (design or fine arts)?" yes / no
GROUPS = (("all", "all raters"), ("professional", "art professionals"), ("other", "others"))
ORBIT = "orbit.mp4"  # the item name of a pair's orbit videos
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".webp")
RUN_MARKERS = ("stylized.ply", "metrics.json", "config.yaml", "checkpoint.pt", "sources.json")  # a stylize run folder
Z95 = 1.959963984540054  # the standard normal's 97.5% quantile
BOOTSTRAP = 2000
# raters needed for the bootstrap over raters and for a verdict: with fewer, resampling raters has too few
# distinct outcomes to be an interval (2 raters: 3), and the answers of a few people are not a population
MIN_RATERS = 5
RATER_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")
CAMERA_REL_TOL = 1e-3  # camera centres of "the same view" agree to this fraction of the cameras' spread


# --- run folders ---------------------------------------------------------------------------------------------
@dataclass
class RunMedia:
    """What a run folder offers a study: its per-view renders by file name (renders/view_000.png, ... as
    ``stylize`` writes them, or the images of a plain folder, e.g. a baseline's outputs), orbit.mp4, the painting
    it was stylized after, and what identifies its views (metrics.json ``views``, cameras.json)."""
    path: Path
    views: dict
    orbit: Path | None = None
    painting: Path | None = None
    view_names: list | None = None
    cameras: list | None = None


def _images(folder: Path) -> dict:
    return {p.name: p for p in sorted(folder.iterdir())
            if p.is_file() and p.suffix.lower() in IMAGE_EXTS and p.stem.lower() != "style"}


def _json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise InputError(f"not readable JSON ({type(e).__name__})", path) from None


def _painting(run: Path) -> Path | None:
    """style.png (the painting as the run used it, written by every stylize run), else config.yaml's ``style``."""
    for ext in (".png", ".jpg", ".jpeg"):
        if (run / f"style{ext}").is_file():
            return run / f"style{ext}"
    cfg = run / "config.yaml"
    if cfg.is_file():
        import yaml  # lazy: CLI startup (the rate server, which the command line imports, imports this module)

        try:
            style = (yaml.safe_load(cfg.read_text()) or {}).get("style")
        except (yaml.YAMLError, UnicodeDecodeError, AttributeError):
            style = None
        if style:
            for cand in (run / str(style), Path(str(style))):
                if cand.is_file():
                    return cand
    return None


def load_run(path) -> RunMedia:
    run = Path(path)
    if not run.is_dir():
        raise InputError("no such run folder", run)
    if (run / "renders").is_dir():
        views = _images(run / "renders")
    elif any((run / m).exists() for m in RUN_MARKERS):
        raise InputError("run folder without renders/ (a stylize run writes renders/view_000.png, ... per view)",
                         run)
    else:  # a plain folder of images, e.g. a baseline's renders named like ours
        views = _images(run)
    if not views:
        raise InputError("no renders (expected renders/view_000.png, ... as a stylize run writes them)", run)
    m = _json(run / "metrics.json") if (run / "metrics.json").is_file() else {}
    names = m.get("views") if isinstance(m, dict) and isinstance(m.get("views"), list) else None
    cams = _json(run / "cameras.json") if (run / "cameras.json").is_file() else None
    return RunMedia(run, views, run / ORBIT if (run / ORBIT).is_file() else None, _painting(run), names,
                    cams if isinstance(cams, list) else None)


def _short(names) -> str:
    names = sorted(names)
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def _image_size(path: Path):
    import cv2  # lazy: CLI startup, as yaml above

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("unreadable image", path)
    return img.shape[1], img.shape[0]


def check_pair(a: RunMedia, b: RunMedia) -> None:
    """One-line InputError unless the two runs render the same views: the same render file names, the same
    dataset views (metrics.json ``views``) and cameras (cameras.json) where both record them, and the same
    aspect ratio."""
    if set(a.views) != set(b.views):
        only_a, only_b = set(a.views) - set(b.views), set(b.views) - set(a.views)
        what = "; ".join(s for s in (f"only in {a.path}: {_short(only_a)}" if only_a else "",
                                     f"only in {b.path}: {_short(only_b)}" if only_b else "") if s)
        raise InputError(f"the pair does not render the same views ({what})", a.path)
    if a.view_names is not None and b.view_names is not None and a.view_names != b.view_names:
        diff = next(i for i in range(max(len(a.view_names), len(b.view_names)))
                    if a.view_names[i:i + 1] != b.view_names[i:i + 1])
        raise InputError(f"the pair renders different views: metrics.json views differ from {b.path} at view {diff} "
                         f"({a.view_names[diff:diff + 1]} vs {b.view_names[diff:diff + 1]})", a.path)
    if a.cameras is not None and b.cameras is not None:
        if len(a.cameras) != len(b.cameras):
            raise InputError(f"the pair renders different views: cameras.json has {len(a.cameras)} cameras, "
                             f"{b.path}'s {len(b.cameras)}", a.path)
        try:
            pa = np.array([c["position"] for c in a.cameras], float)
            pb = np.array([c["position"] for c in b.cameras], float)
        except (KeyError, TypeError, ValueError):
            pa = pb = None
        if pa is not None and pa.shape == pb.shape and len(pa):
            spread = max(float(np.ptp(pa, axis=0).max()), 1e-9)
            worst = float(np.abs(pa - pb).max())
            if worst > CAMERA_REL_TOL * spread:
                raise InputError(f"the pair renders different views: cameras.json camera centres differ from "
                                 f"{b.path}'s by up to {worst:.3g} (cameras spread over {spread:.3g})", a.path)
    first = sorted(a.views)[0]
    (wa, ha), (wb, hb) = _image_size(a.views[first]), _image_size(b.views[first])
    if abs(wa / ha - wb / hb) > 0.02:
        raise InputError(f"the pair's renders differ in shape: {first} is {wa}x{ha} here, {wb}x{hb} in {b.path}",
                         a.path)


def _pick_views(names: list, max_views: int | None) -> list:
    """Evenly spaced views (neighbours along a trajectory look alike), all when ``max_views`` is None or 0."""
    if not max_views or max_views >= len(names):
        return list(names)
    step = len(names) / max_views
    return [names[int(i * step)] for i in range(max_views)]


# --- the study -------------------------------------------------------------------------------------------------
def _labels(paths: list) -> list:
    """Short names of run folders: the folder's name, with its parent where two names collide."""
    names = [p.name for p in paths]
    return [f"{p.parent.name}/{p.name}" if names.count(p.name) > 1 else p.name for p in paths]


@dataclass
class Study:
    """The pairs and items of a study and its randomization seed (``study.json``)."""
    folder: Path
    pairs: list  # [{"a", "b", "a_name", "b_name", "painting", "views": [...]}]
    media: str  # "views", "orbit" or "both"
    seed: int
    created: str = ""
    _files: dict = field(default_factory=dict, repr=False)  # media id -> Path

    @property
    def items(self) -> list:
        """Every (pair, view) item as "pair/view" ids, in study order."""
        return [f"{k}/{v}" for k, p in enumerate(self.pairs) for v in p["views"]]

    def to_json(self) -> dict:
        return {"format": FORMAT, "media": self.media, "seed": self.seed, "created": self.created,
                "criteria": [{"key": k, "name": n} for k, n, _ in CRITERIA], "pairs": self.pairs}

    # media files by opaque id: the page never sees a path or which run a file belongs to
    def media_id(self, path: Path) -> str:
        mid = hashlib.sha256(f"{self.seed}:{Path(path).resolve()}".encode()).hexdigest()[:24]
        self._files[mid] = Path(path)
        return mid

    def media_file(self, mid: str) -> Path | None:
        return self._files.get(mid)

    def item_files(self, item: str) -> tuple:
        """(painting, A's file, B's file) of an item."""
        k, view = item.split("/", 1)
        p = self.pairs[int(k)]
        base = (lambda run: Path(run) / ORBIT) if view == ORBIT else \
            (lambda run: (Path(run) / "renders" / view) if (Path(run) / "renders").is_dir() else Path(run) / view)
        return Path(p["painting"]), base(p["a"]), base(p["b"])

    def register_media(self) -> None:
        for item in self.items:
            for f in self.item_files(item):
                self.media_id(f)

    # each rater's order and sides: fixed by (seed, rater), so a rater who comes back continues where they were
    def order(self, rater: str) -> list:
        items = self.items
        random.Random(f"{self.seed}:order:{rater}").shuffle(items)
        return items

    def a_left(self, rater: str) -> list:
        """Whether A is on the left at each position of the rater's order: positions 2j and 2j+1 take opposite
        sides in a random order, so any prefix of a rater's answers has A on the left half the time (+-1)."""
        rng = random.Random(f"{self.seed}:sides:{rater}")
        out = []
        for _ in range((len(self.items) + 1) // 2):
            first = rng.random() < 0.5
            out += [first, not first]
        return out[:len(self.items)]


def build_study(runs: list, out, media: str = "views", max_views: int | None = None, style=None,
                seed: int | None = None) -> Study:
    """Check the runs (pairs of the same views) and create ``out/study.json``, or reopen the study already there
    when it is of the same pairs (a server restarted on the same folder continues the study)."""
    if len(runs) < 2 or len(runs) % 2:
        raise InputError(f"rate takes pairs of run folders (RUN_A RUN_B [RUN_C RUN_D ...]); got {len(runs)} "
                         f"folder{'s' if len(runs) != 1 else ''}")
    if media not in ("views", "orbit", "both"):
        raise InputError(f"media must be views, orbit or both, not {media!r}")
    style = Path(style).resolve() if style is not None else None
    if style is not None and not style.is_file():
        raise InputError("no such painting", style)
    loaded = [load_run(r) for r in runs]
    paths = [r.path.resolve() for r in loaded]
    labels = _labels(paths)
    pairs = []
    for k in range(0, len(loaded), 2):
        a, b = loaded[k], loaded[k + 1]
        if paths[k] == paths[k + 1]:
            raise InputError("a run is paired with itself", a.path)
        check_pair(a, b)
        views = _pick_views(sorted(a.views), max_views) if media in ("views", "both") else []
        if media in ("orbit", "both"):
            for r in (a, b):
                if r.orbit is None:
                    raise InputError(f"no {ORBIT} in the run folder (needed for --media {media})", r.path)
            views.append(ORBIT)
        painting = style or a.painting or b.painting
        if painting is None:
            raise InputError(f"no painting in the run folder or in {b.path} (style.png or config.yaml style); "
                             "pass --style", a.path)
        pairs.append({"a": str(paths[k]), "b": str(paths[k + 1]), "a_name": labels[k], "b_name": labels[k + 1],
                      "painting": str(Path(painting).resolve()), "views": views})
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("study folder path exists and is not a folder", out)
    f = out / STUDY_FILE
    if f.is_file():
        old = load_study(out)
        same = [(p["a"], p["b"], p["views"]) for p in old.pairs] == [(p["a"], p["b"], p["views"]) for p in pairs]
        if not same or old.media != media:
            raise InputError(f"the folder holds a study of other runs or views ({STUDY_FILE}); pass another --out "
                             "to start a new study", out)
        old.register_media()
        return old
    study = Study(out, pairs, media, secrets.randbits(48) if seed is None else int(seed), _now())
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot create the study folder ({e.strerror or e})", out) from None
    write_json(f, study.to_json())
    study.register_media()
    return study


def load_study(folder) -> Study:
    folder = Path(folder)
    f = folder / STUDY_FILE
    if not f.is_file():
        raise InputError(f"not a study folder (no {STUDY_FILE}; start one with rate RUN_A RUN_B --out DIR)", folder)
    d = _json(f)
    try:
        study = Study(folder, list(d["pairs"]), d["media"], int(d["seed"]), d.get("created", ""))
    except (KeyError, TypeError, ValueError):
        raise InputError("not a study file of this version", f) from None
    return study


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).astimezone().isoformat(timespec="seconds")


# --- the answer log ----------------------------------------------------------------------------------------------
class AnswerLog:
    """answers.jsonl: one JSON object per line, appended, flushed and fsync'ed before the rater's next item is
    sent, so a server that dies loses nothing that was acknowledged. Records: ``{"type": "answer", ...}`` and
    ``{"type": "rater", "rater", "expertise"}`` (the expertise question, answered at any time; the last counts)."""

    def __init__(self, folder):
        self.path = Path(folder) / ANSWERS_FILE
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # a line cut short by a crash stays alone on its line: the next record starts on a new one
        if self.path.is_file() and self.path.stat().st_size:
            with open(self.path, "rb") as f:
                f.seek(-1, os.SEEK_END)
                if f.read(1) != b"\n":
                    self._append_raw(b"\n")

    def _append_raw(self, data: bytes) -> None:
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            os.write(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)

    def append(self, record: dict) -> None:
        self._append_raw((json.dumps(record, sort_keys=True) + "\n").encode())


def read_answers(folder) -> tuple:
    """(answer records, {rater: expertise}, unreadable lines). A rater's repeated answer to an item (two open
    tabs) counts once, the first."""
    path = Path(folder) / ANSWERS_FILE
    answers, expertise, bad, seen = [], {}, 0, set()
    if not path.is_file():
        return answers, expertise, bad
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            if not line.strip():
                continue
            try:
                r = json.loads(line)
            except ValueError:
                bad += 1
                continue
            if not isinstance(r, dict):
                bad += 1
            elif r.get("type") == "rater":
                expertise[r.get("rater")] = r.get("expertise")
            elif r.get("type") == "answer":
                key = (r.get("rater"), r.get("item"))
                if key not in seen:
                    seen.add(key)
                    answers.append(r)
    return answers, expertise, bad


# --- statistics --------------------------------------------------------------------------------------------------
def wilson(k: int, n: int, z: float = Z95) -> tuple:
    """The Wilson score interval of a binomial proportion k/n; (nan, nan) for n = 0."""
    if n <= 0:
        return (math.nan, math.nan)
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z / den * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (max(0.0, centre - half), min(1.0, centre + half))


def rater_bootstrap(wins, counts, n: int = BOOTSTRAP, seed: int = 0) -> tuple:
    """95% percentile interval of the pooled win rate sum(wins)/sum(counts) when the raters are resampled with
    replacement (answers of one rater are not independent); (nan, nan) with fewer than ``MIN_RATERS``."""
    wins, counts = np.asarray(wins, float), np.asarray(counts, float)
    keep = counts > 0
    wins, counts = wins[keep], counts[keep]
    if len(counts) < MIN_RATERS:
        return (math.nan, math.nan)
    idx = np.random.default_rng(seed).integers(0, len(counts), (n, len(counts)))
    rates = wins[idx].sum(1) / counts[idx].sum(1)
    lo, hi = np.percentile(rates, [2.5, 97.5])
    return (float(lo), float(hi))


@dataclass
class Cell:
    """The win rate of A for one criterion and group of raters."""
    wins: int
    n: int
    raters: int
    wilson: tuple
    boot: tuple

    @property
    def rate(self) -> float:
        return self.wins / self.n if self.n else math.nan

    def verdict(self) -> str:
        """"A", "B" or "none": a win only with at least MIN_RATERS raters and where both intervals (Wilson over
        answers, bootstrap over raters) exclude 50% on the same side."""
        ivs = (self.wilson, self.boot)
        if self.raters < MIN_RATERS or any(math.isnan(iv[0]) for iv in ivs):
            return "none"
        if all(lo > 0.5 for lo, _ in ivs):
            return "A"
        if all(hi < 0.5 for _, hi in ivs):
            return "B"
        return "none"


def cell(answers: list, criterion: str, side: str = "A") -> Cell:
    """Win rate of ``side`` ("A": the pair's first run; "left": the left image, a check of position bias)."""
    per = {}
    for r in answers:
        w = r["winner"][criterion] if side == "A" else r["choice"][criterion]
        won = w == ("A" if side == "A" else "left")
        pr = per.setdefault(r["rater"], [0, 0])
        pr[0] += won
        pr[1] += 1
    wins = sum(v[0] for v in per.values())
    n = sum(v[1] for v in per.values())
    return Cell(wins, n, len(per), wilson(wins, n), rater_bootstrap([v[0] for v in per.values()],
                                                                    [v[1] for v in per.values()]))


def summarize(folder) -> dict:
    """Everything the report shows, from study.json and answers.jsonl."""
    study = load_study(folder)
    answers, expertise, bad = read_answers(folder)
    items = set(study.items)
    answers = [r for r in answers if r.get("item") in items and isinstance(r.get("winner"), dict)
               and all(r["winner"].get(c) in ("A", "B") for c in CRITERION_KEYS)]
    raters = sorted({r["rater"] for r in answers})
    group_of = {r: (expertise.get(r) if expertise.get(r) in EXPERTISE else None) for r in raters}
    groups = {"all": answers}
    for g in EXPERTISE:
        groups[g] = [r for r in answers if group_of[r["rater"]] == g]
    table = {g: {c: cell(rs, c) for c in CRITERION_KEYS} for g, rs in groups.items()}
    per_pair = [{c: cell([r for r in answers if r["pair"] == k], c) for c in CRITERION_KEYS}
                for k in range(len(study.pairs))]
    left = {c: cell(answers, c, side="left") for c in CRITERION_KEYS}
    return {"study": study, "answers": len(answers), "raters": raters, "groups": table,
            "raters_by_group": {g: len({r["rater"] for r in rs}) for g, rs in groups.items()},
            "undeclared": sum(1 for r in raters if group_of[r] is None), "per_pair": per_pair, "left": left,
            "unreadable_lines": bad}


# --- the report ------------------------------------------------------------------------------------------------
def _pct(x) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.1f}%"


def _iv(iv) -> str:
    return "-" if math.isnan(iv[0]) else f"[{100 * iv[0]:.1f}, {100 * iv[1]:.1f}]"


def _who(study: Study, side: str) -> str:
    names = sorted({p[f"{side.lower()}_name"] for p in study.pairs})
    return ", ".join(names)


def verdict_lines(s: dict) -> list:
    study = s["study"]
    out = []
    for key, name, _ in CRITERIA:
        c = s["groups"]["all"][key]
        v = c.verdict()
        stats = f"{_pct(c.rate)} of {c.n} answers from {c.raters} rater{'s' if c.raters != 1 else ''}, 95% " \
                f"Wilson {_iv(c.wilson)}, raters bootstrap {_iv(c.boot)}"
        if c.n == 0:
            out.append(f"{name}: no answers yet")
        elif v == "A":
            out.append(f"{name}: A ({_who(study, 'A')}) wins: {stats}")
        elif v == "B":
            out.append(f"{name}: B ({_who(study, 'B')}) wins: A has {stats}")
        else:
            why = f"fewer than {MIN_RATERS} raters" if c.raters < MIN_RATERS else "an interval includes 50%"
            out.append(f"{name}: no winner ({why}): A has {stats}")
    return out


def _rows(s: dict) -> list:
    rows = []
    for key, name, _ in CRITERIA:
        for g, gname in GROUPS:
            c = s["groups"][g][key]
            rows.append([name, gname, str(c.n), str(c.raters), _pct(c.rate), _iv(c.wilson), _iv(c.boot),
                         {"A": "A wins", "B": "B wins", "none": "-"}[c.verdict()] if c.n else "-"])
    return rows


HEAD = ["criterion", "raters' group", "answers", "raters", "A wins", "Wilson 95%", "raters bootstrap 95%",
        "verdict"]


def format_table(s: dict) -> str:
    study = s["study"]
    rows = _rows(s)
    w = [max(len(HEAD[i]), *(len(r[i]) for r in rows)) for i in range(len(HEAD))]
    line = lambda r: "  ".join(x.ljust(w[i]) for i, x in enumerate(r)).rstrip()  # noqa: E731
    n_pro, n_oth = s["raters_by_group"]["professional"], s["raters_by_group"]["other"]
    out = [f"user study {study.folder}: {s['answers']} answers from {len(s['raters'])} raters "
           f"({n_pro} art professionals, {n_oth} others, {s['undeclared']} did not say), {len(study.pairs)} "
           f"pair{'s' if len(study.pairs) != 1 else ''}",
           f"win rate of A ({_who(study, 'A')}) against B ({_who(study, 'B')}), 95% intervals in %",
           line(HEAD), line(["-" * x for x in w])]
    prev = None
    for r in rows:
        out.append(line([r[0] if r[0] != prev else ""] + r[1:]))
        prev = r[0]
    return "\n".join(out)


def format_markdown(s: dict, chart: str | None = REPORT_PNG) -> str:
    study = s["study"]
    md = [f"# User study: {_who(study, 'A')} (A) vs {_who(study, 'B')} (B)", "",
          f"{s['answers']} answers from {len(s['raters'])} raters ({s['raters_by_group']['professional']} art "
          f"professionals, {s['raters_by_group']['other']} others, {s['undeclared']} did not say); "
          f"{len(study.pairs)} pair{'s' if len(study.pairs) != 1 else ''}, {len(study.items)} items, "
          f"media: {study.media}. Generated {_now()}.", "",
          "## Verdicts", "", *[f"- {v}" for v in verdict_lines(s)], "",
          f"A win needs at least {MIN_RATERS} raters and both 95% intervals (Wilson over answers; bootstrap over "
          f"raters, {BOOTSTRAP} resamples) to exclude 50% on the same side.", "",
          "## Win rate of A per criterion", "",
          "| " + " | ".join(HEAD) + " |", "|" + "|".join("---" for _ in HEAD) + "|"]
    md += ["| " + " | ".join(r) + " |" for r in _rows(s)]
    if chart:
        md += ["", f"![win rates]({chart})"]
    md += ["", "## Per pair (all raters)", "", "| pair | A | B | items | "
           + " | ".join(f"{n}: A wins (answers)" for _, n, _ in CRITERIA) + " |", "|---|---|---|---|"
           + "|".join("---" for _ in CRITERIA) + "|"]
    for k, (p, cells) in enumerate(zip(study.pairs, s["per_pair"])):
        md.append(f"| {k} | {p['a_name']} | {p['b_name']} | {len(p['views'])} | "
                  + " | ".join(f"{_pct(cells[c].rate)} ({cells[c].n})" for c in CRITERION_KEYS) + " |")
    md += ["", "## Position check", "",
           "How often raters picked the left image (an interval that includes 50% shows no side bias):", ""]
    md += [f"- {n}: {_pct(s['left'][c].rate)} left, Wilson {_iv(s['left'][c].wilson)}" for c, n, _ in CRITERIA]
    if s["unreadable_lines"]:
        md += ["", f"{s['unreadable_lines']} unreadable line(s) in {ANSWERS_FILE} were skipped."]
    return "\n".join(md) + "\n"


COLORS = {"all": "#4c72b0", "professional": "#dd8452", "other": "#55a868"}


def chart(s: dict, path) -> None:
    """Grouped bars in the paper's style: per criterion, the win rate of A for all raters, art professionals and
    others, with 95% Wilson intervals and the 50% line."""
    # lazy: matplotlib is heavy and only the chart needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    study = s["study"]
    fig, ax = plt.subplots(figsize=(7.0, 3.8))
    x = np.arange(len(CRITERIA))
    width = 0.26
    for j, (g, gname) in enumerate(GROUPS):
        cells = [s["groups"][g][c] for c in CRITERION_KEYS]
        rates = np.array([100 * c.rate if c.n else 0.0 for c in cells])
        lo = np.array([100 * (c.rate - c.wilson[0]) if c.n else 0.0 for c in cells])
        hi = np.array([100 * (c.wilson[1] - c.rate) if c.n else 0.0 for c in cells])
        pos = x + (j - 1) * width
        ax.bar(pos, rates, width, color=COLORS[g], label=f"{gname} ({s['raters_by_group'][g]})",
               yerr=[lo, hi], capsize=3, error_kw={"elinewidth": 0.8, "ecolor": "#333333"})
        for px, c, r in zip(pos, cells, rates):
            ax.text(px, 2, f"{r:.0f}%" if c.n else "n/a", ha="center", va="bottom", fontsize=7,
                    color="white" if c.n and r > 8 else "#333333")
    ax.axhline(50, color="#333333", ls="--", lw=0.8)
    ax.set_xticks(x, [n for _, n, _ in CRITERIA])
    ax.set_ylim(0, 100)
    ax.set_ylabel(f"win rate of {_who(study, 'A')} (%)", fontsize=8)
    ax.set_title(f"User study: {_who(study, 'A')} vs {_who(study, 'B')} ({s['answers']} answers, "
                 f"{len(s['raters'])} raters; 95% Wilson intervals)", fontsize=9)
    ax.legend(fontsize=7, loc="upper right", ncols=3, frameon=False)
    ax.spines[["top", "right"]].set_visible(False)
    ax.tick_params(labelsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


def write_report(folder) -> dict:
    """report.md and report.png in the study folder; returns the summary (``format_table`` prints it)."""
    s = summarize(folder)
    chart(s, Path(folder) / REPORT_PNG)
    write_text(Path(folder) / REPORT_MD, format_markdown(s))
    return s


__all__ = ["CRITERIA", "RunMedia", "load_run", "check_pair", "Study", "build_study", "load_study", "AnswerLog",
           "read_answers", "wilson", "rater_bootstrap", "summarize", "format_table", "format_markdown",
           "verdict_lines", "write_report", "chart"]
