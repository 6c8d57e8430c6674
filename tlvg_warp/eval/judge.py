"""VLM-as-a-Judge (paper §4.3.2, SPEC §4): a panel of chat models compares two runs view by view.

Each (view, model) pair is one request to an OpenAI-compatible ``/chat/completions`` endpoint: a text
prompt, then the painting, image A, image B as base64 PNG data URLs. Which run shows as "A" is drawn per
(view, model) from ``random.Random(seed)`` so position bias averages out, and verdicts are mapped back to
``--a`` / ``--b``. Bad answers and transport failures are retried with exponential backoff, then counted
as invalid; the run never crashes on what a model says.
"""
from __future__ import annotations

import base64
import json
import random
import re
import socket
import sys
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import urlparse

import cv2
import yaml

from ..errors import InputError
from ..io.images import read_image

CRITERIA = ("flow_alignment", "materiality", "aesthetics")
CRITERION_NAMES = {"flow_alignment": "Flow Alignment", "materiality": "Materiality", "aesthetics": "Aesthetics"}
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff")
RAW_KEEP = 2000  # chars of each raw answer kept in judge.json: enough to see why it failed, not a novel
# Transient HTTP statuses worth retrying; any other 4xx (bad key, unknown model) will not fix itself.
RETRY_STATUS = {408, 409, 425, 429, 500, 502, 503, 504}

PROMPT = """You are an art critic judging 3D scene stylization. You get three images: first the reference \
painting, then image A and image B, two renders of the same 3D scene and view stylized after that painting.

Compare A and B on three criteria:
1. Flow Alignment: do the brushstrokes follow the geometry of the scene (wrapping around surfaces, \
following edges and curvature) the way the painter's strokes follow form?
2. Materiality: does it look like physical paint (impasto, thick directional strokes, paint ridges) \
rather than a digital filter?
3. Aesthetics: overall artistic quality and faithfulness to the painting's style.

Tie-breaker rule: penalize flat "sticker" texture mapping, where the style pattern is pasted onto the \
scene like a decal that ignores depth and shape; reward geometric flow, where strokes wrap around the 3D \
form. Answer "tie" only when the two are truly indistinguishable on that criterion.

Also give each image an Authenticity score from 1 to 10: how convincingly it reads as a real painting by \
the same artist (10 = indistinguishable from a physical painting).

Also score each image from 1 to 10 on each of the three criteria (10 = best).

Answer with JSON only, no other text:
{"flow_alignment": "A" | "B" | "tie", "materiality": "A" | "B" | "tie", "aesthetics": "A" | "B" | "tie", \
"authenticity": {"A": <integer 1-10>, "B": <integer 1-10>}, \
"scores": {"flow_alignment": {"A": <1-10>, "B": <1-10>}, "materiality": {"A": <1-10>, "B": <1-10>}, \
"aesthetics": {"A": <1-10>, "B": <1-10>}}}"""


# ----------------------------------------------------------------------------------------------- inputs
def _images_in(folder: Path) -> dict[str, Path]:
    # A copied painting beside plain images is the reference, not a view to judge.
    return {p.name: p for p in sorted(folder.iterdir())
            if p.is_file() and p.suffix.lower() in IMAGE_EXTS and p.stem.lower() != "style"}


def _run_style(run: Path) -> Path | None:
    """The painting a run folder names: config.yaml `style` (relative to the run or the cwd), or style.*."""
    cfg = run / "config.yaml"
    if cfg.is_file():
        try:
            data = yaml.safe_load(cfg.read_text()) or {}
        except (yaml.YAMLError, UnicodeDecodeError) as e:
            raise InputError(f"not valid YAML ({str(e).splitlines()[0]})", cfg) from None
        style = data.get("style") if isinstance(data, dict) else None
        if style:
            for cand in (run / str(style), Path(str(style))):
                if cand.is_file():
                    return cand
            raise InputError(f"style painting {style!r} not found", cfg)
    for ext in (".png", ".jpg", ".jpeg"):
        if (run / f"style{ext}").is_file():
            return run / f"style{ext}"
    return None


def resolve_inputs(run_a, run_b, style=None, max_views=None):
    """Pair the two runs' renders by file name and find the painting; every one of those images must decode.
    Returns (pairs, style_path)."""
    imgs = []
    for run in (Path(run_a), Path(run_b)):
        if not run.is_dir():
            raise InputError("no such folder (expected a run folder or a folder of images)", run)
        folder = run / "renders" if (run / "renders").is_dir() else run
        imgs.append(_images_in(folder))
    names = sorted(set(imgs[0]) & set(imgs[1]))
    if not names:
        raise InputError(f"no images share a file name with {run_b} ({len(imgs[0])} vs {len(imgs[1])} images)",
                         run_a)
    if max_views is not None and 0 < max_views < len(names):
        # Evenly spaced rather than the first N: views along a trajectory are similar to their neighbors.
        step = len(names) / max_views
        names = [names[int(i * step)] for i in range(max_views)]
    if style is not None:
        style = Path(style)
        if not style.is_file():
            raise InputError("no such painting", style)
    else:
        style = _run_style(Path(run_a)) or _run_style(Path(run_b))
        if style is None:
            raise InputError("no painting: no config.yaml `style` or style.png in either run; pass --style",
                             run_a)
    pairs = [(n, imgs[0][n], imgs[1][n]) for n in names]
    check_images([style] + [p for _, a, b in pairs for p in (a, b)])
    return pairs, style


def check_images(paths) -> None:
    """Decode every image the judge will send (header, truncation, pixel data), so a corrupt render or painting
    is reported, naming the file, before any endpoint is contacted."""
    for p in paths:
        read_image(Path(p))


def png_data_url(path) -> str:
    """Decode (so an unreadable file fails here, as input, not at the model) and re-encode as PNG."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("cannot read image", path)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise InputError("cannot encode image as PNG", path)
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


# ---------------------------------------------------------------------------------------------- parsing
_FENCE = re.compile(r"```(?:json)?\s*(.*?)```", re.S | re.I)


def parse_verdict(text: str) -> dict:
    """The model's answer as {criterion: "A"|"B"|"tie", "authenticity": {"A": s, "B": s}}; ValueError if
    no valid answer can be found. Accepts the JSON bare, inside ``` fences, or amid surrounding prose."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError("empty answer")
    candidates = [text.strip()] + _FENCE.findall(text)
    i, j = text.find("{"), text.rfind("}")
    if 0 <= i < j:
        candidates.append(text[i:j + 1])
    obj = None
    for c in candidates:
        try:
            obj = json.loads(c)
            break
        except (json.JSONDecodeError, ValueError):
            continue
    if not isinstance(obj, dict):
        raise ValueError("no JSON object in answer")
    out = {}
    for k in CRITERIA:
        v = str(obj.get(k, "")).strip().strip(".").lower()
        v = {"a": "A", "b": "B", "tie": "tie", "image a": "A", "image b": "B"}.get(v)
        if v is None:
            raise ValueError(f"{k}: {obj.get(k)!r} is not A, B or tie")
        out[k] = v
    auth = obj.get("authenticity")
    if not isinstance(auth, dict):
        raise ValueError("authenticity missing")
    out["authenticity"] = _pair_scores(auth, "authenticity")
    per = obj.get("scores")  # per-criterion 1-10 scores: optional (older prompts), validated when given
    if per is not None:
        if not isinstance(per, dict) or any(not isinstance(per.get(c), dict) for c in CRITERIA):
            raise ValueError("scores: expected {criterion: {A: s, B: s}} for every criterion")
        out["scores"] = {c: _pair_scores(per[c], f"scores.{c}") for c in CRITERIA}
    return out


def _pair_scores(d: dict, what: str) -> dict:
    scores = {}
    for pos in ("A", "B"):
        s = d.get(pos, d.get(pos.lower()))
        if isinstance(s, str):
            try:
                s = float(s)
            except ValueError:
                pass
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not 1 <= s <= 10:
            raise ValueError(f"{what} {pos}: {s!r} is not a score in 1-10")
        scores[pos] = float(s)
    return scores


# -------------------------------------------------------------------------------------------- transport
class _Retryable(Exception):
    pass


def _answer_text(body: dict) -> str:
    choice = (body.get("choices") or [{}])[0]
    msg = choice.get("message") or {}
    if msg.get("refusal"):
        raise _Retryable(f"refused: {str(msg['refusal'])[:120]}")
    if choice.get("finish_reason") == "content_filter":
        raise _Retryable("refused: content filter")
    content = msg.get("content")
    if isinstance(content, list):  # some servers return content parts even for plain text
        content = "".join(p.get("text", "") for p in content if isinstance(p, dict))
    if not isinstance(content, str):
        raise _Retryable("no message content")
    return content


def ask(base_url, model, content, api_key=None, timeout=60.0):
    """One chat-completions call; the answer's text, or _Retryable / RuntimeError (not worth retrying)."""
    req = urllib.request.Request(
        base_url.rstrip("/") + "/chat/completions",
        data=json.dumps({"model": model, "messages": [{"role": "user", "content": content}]}).encode(),
        headers={"Content-Type": "application/json",
                 **({"Authorization": f"Bearer {api_key}"} if api_key else {})},
        method="POST")
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            raw = r.read()
    except urllib.error.HTTPError as e:
        err = _Retryable if e.code in RETRY_STATUS else RuntimeError
        raise err(f"HTTP {e.code}") from None
    except (urllib.error.URLError, TimeoutError, ConnectionError, OSError) as e:
        reason = getattr(e, "reason", e)  # keep URLs out: records must not depend on the server's port
        raise _Retryable(f"transport: {type(reason).__name__}") from None
    try:
        return _answer_text(json.loads(raw))
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError, TypeError, IndexError):
        raise _Retryable("response is not chat-completions JSON") from None


def judge_one(base_url, model, content, api_key, timeout, retries, backoff, sleep=time.sleep) -> dict:
    """Ask until a valid verdict or retries run out. Never raises for anything the server does."""
    errors, text = [], None
    for attempt in range(retries + 1):
        if attempt:
            sleep(backoff * 2 ** (attempt - 1))
        try:
            text = ask(base_url, model, content, api_key, timeout)
            return {"valid": True, "attempts": attempt + 1, "errors": errors, "raw": text[:RAW_KEEP],
                    "parsed": parse_verdict(text)}
        except ValueError as e:  # malformed answer (parse_verdict); a retry may well fix it
            errors.append(f"malformed: {e}")
        except _Retryable as e:
            errors.append(str(e))
        except RuntimeError as e:
            errors.append(str(e))
            break
        except Exception as e:  # noqa: BLE001 - "never crash": a surprise is one invalid answer, reported
            errors.append(f"unexpected {type(e).__name__}: {e}")
    return {"valid": False, "attempts": len(errors), "errors": errors,
            "raw": None if text is None else text[:RAW_KEEP], "parsed": None}


# ------------------------------------------------------------------------------------------- aggregation
def _mean(xs):
    return sum(xs) / len(xs) if xs else None


def aggregate(records) -> dict:
    """Win rate of --a per criterion (ties count 1/2) over valid verdicts, counts, mean authenticity, mean 1-10
    score per criterion and side, and the paper's Table 1 "Average": per side, the mean of the three criteria's
    mean scores (the paper's 7.19 / 8.36 are those means), None unless all three are scored."""
    valid = [r for r in records if r["valid"]]
    out = {"n": len(records), "valid": len(valid), "invalid": len(records) - len(valid),
           "win_rate": {}, "counts": {}}
    for c in CRITERIA:
        won = {k: sum(r["verdict"][c] == k for r in valid) for k in ("a", "b", "tie")}
        out["counts"][c] = won
        out["win_rate"][c] = (won["a"] + 0.5 * won["tie"]) / len(valid) if valid else None
    rates = [v for v in out["win_rate"].values() if v is not None]
    out["win_rate"]["average"] = _mean(rates)
    out["authenticity"] = {k: _mean([r["authenticity"][k] for r in valid]) for k in ("a", "b")}
    scored = [r for r in valid if r.get("scores")]
    out["scores"] = {c: {k: _mean([r["scores"][c][k] for r in scored]) for k in ("a", "b")} for c in CRITERIA}
    out["scores"]["average"] = {k: (_mean([out["scores"][c][k] for c in CRITERIA])
                                    if all(out["scores"][c][k] is not None for c in CRITERIA) else None)
                                for k in ("a", "b")}
    out["scored"] = len(scored)
    return out


# ------------------------------------------------------------------------------------------------- panel
def run_judge(run_a, run_b, models, base_url, api_key=None, style=None, seed=0, timeout=60.0, retries=3,
              backoff=1.0, max_views=None, workers=4, log=None) -> dict:
    """Judge every paired view with every model; returns the judge.json dict (records + aggregates)."""
    models = list(dict.fromkeys(m.strip() for m in models if m and m.strip()))  # a repeat would count twice
    if not models:
        raise InputError("--models: give at least one model name")
    pairs, style_path = resolve_inputs(run_a, run_b, style, max_views)
    painting = png_data_url(style_path)
    rng = random.Random(seed)
    jobs = []
    for view, pa, pb in pairs:
        urls = {"a": png_data_url(pa), "b": png_data_url(pb)}
        for m in models:
            # Drawn in a fixed (view, model) order before any request goes out, so threads cannot perturb it.
            first = "b" if rng.random() < 0.5 else "a"
            second = "a" if first == "b" else "b"
            content = [{"type": "text", "text": PROMPT}] + [
                {"type": "image_url", "image_url": {"url": u}} for u in (painting, urls[first], urls[second])]
            jobs.append((view, m, {"A": first, "B": second}, content))

    def work(job):
        view, m, pos, content = job
        res = judge_one(base_url, m, content, api_key, timeout, retries, backoff)
        rec = {"view": view, "model": m, "shown_as_A": pos["A"], "valid": res["valid"],
               "attempts": res["attempts"], "errors": res["errors"], "raw": res["raw"]}
        if res["valid"]:
            p = res["parsed"]
            back = lambda v: "tie" if v == "tie" else pos[v]  # noqa: E731 - position -> run
            rec["verdict"] = {c: back(p[c]) for c in CRITERIA}
            rec["authenticity"] = {pos[k]: v for k, v in p["authenticity"].items()}
            if "scores" in p:
                rec["scores"] = {c: {pos[k]: v for k, v in p["scores"][c].items()} for c in CRITERIA}
        if log:
            log(f"{view} {m}: " + ("ok" if res["valid"] else "invalid (" + "; ".join(res["errors"]) + ")"))
        return rec

    t0 = time.perf_counter()
    with ThreadPoolExecutor(max(1, int(workers))) as ex:
        records = list(ex.map(work, jobs))  # map keeps job order: records are reproducible
    return {
        "a": str(run_a), "b": str(run_b), "style": str(style_path), "models": models, "base_url": base_url,
        "seed": seed, "views": [v for v, _, _ in pairs], "retries": retries,
        "wall_s": round(time.perf_counter() - t0, 3),
        "panel": aggregate(records),
        "per_model": {m: aggregate([r for r in records if r["model"] == m]) for m in models},
        "records": records,
    }


def _pct(x):
    return "    n/a" if x is None else f"{100 * x:6.2f}%"


def _score(x):
    return " n/a" if x is None else f"{x:4.2f}"


def format_table(result) -> str:
    """The panel as the paper's Table 1 (win rate of --a per criterion; authenticity of --b and --a),
    then one line per judge model."""
    p = result["panel"]
    a, b = Path(result["a"]).name or result["a"], Path(result["b"]).name or result["b"]
    lines = [f"VLM-as-a-Judge: A = {a} vs B = {b}; {len(result['models'])} model(s), "
             f"{len(result['views'])} view(s), seed {result['seed']}",
             f"{'Criterion':<16}{'Win Rate (A)':>13}{'A/tie/B':>12}{'B score':>9}{'A score':>9}"]
    for c in CRITERIA:
        k = p["counts"][c]
        counts = f"{k['a']}/{k['tie']}/{k['b']}"
        sc = p.get("scores", {}).get(c, {})
        lines.append(f"{CRITERION_NAMES[c]:<16}{_pct(p['win_rate'][c]):>13}{counts:>12}"
                     f"{_score(sc.get('b')):>9}{_score(sc.get('a')):>9}")
    au, av = p["authenticity"], p.get("scores", {}).get("average", {})
    lines.append(f"{'Average':<16}{_pct(p['win_rate']['average']):>13}{'':>12}"
                 f"{_score(av.get('b')):>9}{_score(av.get('a')):>9}")
    lines.append(f"{'Authenticity':<16}{'':>13}{'':>12}{_score(au['b']):>9}{_score(au['a']):>9}")
    lines.append(f"Invalid answers: {p['invalid']} of {p['n']}   (scores: mean 1-10 per criterion; Average row: "
                 f"the mean of the three criteria, as the paper's Table 1)")
    lines.append("")
    lines.append(f"{'Model':<24}{'Flow':>9}{'Mater.':>9}{'Aesth.':>9}{'B auth':>8}{'A auth':>8}{'invalid':>9}"
                 "   B/A score: flow, materiality, aesthetics")
    for m, s in result["per_model"].items():
        w = s["win_rate"]
        sc = s.get("scores", {})
        ba = "  ".join(f"{_score(sc.get(c, {}).get('b'))}/{_score(sc.get(c, {}).get('a'))}" for c in CRITERIA)
        lines.append(f"{m[:23]:<24}{_pct(w['flow_alignment']):>9}{_pct(w['materiality']):>9}"
                     f"{_pct(w['aesthetics']):>9}{_score(s['authenticity']['b']):>8}"
                     f"{_score(s['authenticity']['a']):>8}{s['invalid']:>5}/{s['n']}   {ba}")
    return "\n".join(lines)


LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")
PREFLIGHT_TIMEOUT_S = 5.0


def preflight(base_url: str, api_key=None) -> None:
    """Stop before sending anything (SPEC §4): a remote endpoint without a key, or an endpoint that does not
    accept a connection, is a one-line InputError naming the endpoint (never the key)."""
    u = urlparse(base_url)
    if u.scheme not in ("http", "https") or not u.hostname:
        raise InputError("not an http(s) endpoint", base_url)
    if not api_key and u.hostname not in LOCAL_HOSTS:
        raise InputError("no API key (pass --api-key or set OPENAI_API_KEY)", base_url)
    port = u.port or (443 if u.scheme == "https" else 80)
    try:
        socket.create_connection((u.hostname, port), timeout=PREFLIGHT_TIMEOUT_S).close()
    except OSError as e:
        raise InputError(f"endpoint does not answer ({type(e).__name__})", base_url) from None


def stderr_log(msg):
    print(msg, file=sys.stderr, flush=True)
