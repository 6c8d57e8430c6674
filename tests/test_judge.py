"""The VLM judge against a stub OpenAI-compatible server on 127.0.0.1.

The stub decides from the images it receives (not from any A/B bookkeeping), so the true winner of each
view is known independently of the shuffle: Flow Alignment goes to the brighter image, Materiality to the
higher-contrast one, Aesthetics is always a tie, Authenticity = 1 + round(9 * mean / 255). Each model name
selects a misbehavior (fences, HTTP 500, malformed, timeouts, garbage, 401) so invalid counts are known too.
"""
import base64
import json
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np
import pytest

from tlvg_warp.cli import main
from tlvg_warp.errors import InputError
from tlvg_warp.eval import judge

RENDER_HW = (16, 16)
PAINT_HW = (24, 20)  # a different size than the renders: the stub tells the painting apart by its shape
N_VIEWS = 8
TIE_VIEW = 0  # view whose two renders are identical: every criterion must come back a tie
BROKEN_VIEWS = (3, 5)  # "picky" never answers these properly
MODELS = ["clean", "fenced", "flaky", "picky", "garbage", "slow", "forbidden"]
ALWAYS_INVALID = {"garbage", "forbidden"}
RETRIES = 2
BACKOFF = 0.001  # seconds; real runs use seconds, tests must not wait
TIMEOUT = 1.0  # client timeout: far above a stub reply (ms) so only "slow" ever times out, and once per view
SLOW_S = 2.0
EXACT = 1e-12  # win rates are ratios of small integers, computed the same way: only float rounding differs


def _img(base, amp, hw):
    """Flat gray plus a +-amp checkerboard: mean = base, std = amp (both exact, amp <= base <= 255-amp)."""
    yy, xx = np.indices(hw)
    return np.repeat((base + amp * np.where((yy + xx) % 2, 1, -1))[..., None], 3, axis=2).astype(np.uint8)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    rng = np.random.default_rng(7)
    bases = rng.choice(np.arange(50, 200), size=2 * N_VIEWS, replace=False)  # distinct means: no accidental ties
    amps = rng.choice(np.arange(0, 45), size=2 * N_VIEWS, replace=False)
    for r in ("A", "B"):
        (root / r / "renders").mkdir(parents=True)
    for v in range(N_VIEWS):
        ia, ib = (2 * v, 2 * v) if v == TIE_VIEW else (2 * v, 2 * v + 1)
        cv2.imwrite(str(root / "A" / "renders" / f"view_{v:03d}.png"), _img(bases[ia], amps[ia], RENDER_HW))
        cv2.imwrite(str(root / "B" / "renders" / f"view_{v:03d}.png"), _img(bases[ib], amps[ib], RENDER_HW))
    cv2.imwrite(str(root / "painting.png"), _img(120, 30, PAINT_HW))
    (root / "A" / "config.yaml").write_text("style: ../painting.png\niterations: 10\n")
    return root


def _stats(img):
    return float(img.mean()), float(img.std())


def _decode(url):
    assert url.startswith("data:image/png;base64,")
    return cv2.imdecode(np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)


def _answer(sa, sb):
    cmp = lambda x, y: "A" if x > y else "B" if x < y else "tie"  # noqa: E731
    score = lambda s: 1 + round(9 * s[0] / 255)  # noqa: E731
    return {"flow_alignment": cmp(sa[0], sb[0]), "materiality": cmp(sa[1], sb[1]), "aesthetics": "tie",
            "authenticity": {"A": score(sa), "B": score(sb)}}


class Stub:
    """The server plus what it saw: per-request (model, stats A, stats B) and any protocol violation."""

    def __init__(self, broken_keys, api_key=None):
        self.broken, self.api_key = broken_keys, api_key
        self.lock, self.tries, self.seen, self.problems = threading.Lock(), {}, [], []
        stub = self

        class H(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                code, payload = stub.handle(self.path, self.headers, body)
                data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
                try:
                    self.send_response(code)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):  # the client timed out on "slow": expected
                    pass

        # A listen backlog above the client's concurrency: with the default 5, a dropped SYN waits 1 s to
        # be resent and a healthy request times out.
        srv = type("Srv", (ThreadingHTTPServer,), {"request_queue_size": 64})
        self.server = srv(("127.0.0.1", 0), H)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/v1"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def reset(self):
        with self.lock:
            self.tries.clear(), self.seen.clear()

    def check(self, path, headers, body):
        assert path == "/v1/chat/completions", path
        if self.api_key:
            assert headers.get("Authorization") == f"Bearer {self.api_key}"
        (msg,) = body["messages"]
        assert msg["role"] == "user"
        parts = msg["content"]
        assert [p["type"] for p in parts] == ["text", "image_url", "image_url", "image_url"]
        for word in ("Flow Alignment", "Materiality", "Aesthetics", "sticker", "Authenticity", "JSON"):
            assert word in parts[0]["text"], word
        imgs = [_decode(p["image_url"]["url"]) for p in parts[1:]]
        assert [i.shape[:2] for i in imgs] == [PAINT_HW, RENDER_HW, RENDER_HW]
        return _stats(imgs[1]), _stats(imgs[2])

    def handle(self, path, headers, body):
        try:
            sa, sb = self.check(path, headers, body)
        except Exception as e:  # noqa: BLE001 - assertions in a server thread must surface in the test
            self.problems.append(repr(e))
            return 400, {"error": "bad request"}
        model, key = body["model"], tuple(sorted([sa[0], sb[0]]))
        with self.lock:
            n = self.tries[(model, key)] = self.tries.get((model, key), 0) + 1
            self.seen.append((model, sa, sb))
        good = json.dumps(_answer(sa, sb))
        ok = lambda text: (200, {"choices": [{"message": {"role": "assistant", "content": text}}]})  # noqa: E731
        if model == "fenced":
            return ok(f"Here is my verdict:\n```json\n{good}\n```\nHope this helps.")
        if model == "flaky" and n == 1:
            return 500, {"error": "overloaded"}
        if model == "picky" and (key in self.broken or n == 1):
            return ok(good[: len(good) // 2] if n % 2 else good.replace('"tie"', '"C"'))
        if model == "garbage":
            return ok("lorem ipsum") if n % 2 else (200, {"choices": [{"message": {"content": None,
                                                                                     "refusal": "I can't."}}]})
        if model == "slow" and n == 1:
            time.sleep(SLOW_S)
        if model == "forbidden":
            return 401, {"error": "bad key"}
        return ok(good)


@pytest.fixture(scope="module")
def truth(runs):
    """Per view: (mean, std) of --a's and --b's render, read from disk independently of the judge."""
    return {f"view_{v:03d}.png": tuple(_stats(cv2.imread(str(runs / r / "renders" / f"view_{v:03d}.png")))
                                       for r in ("A", "B")) for v in range(N_VIEWS)}


@pytest.fixture(scope="module")
def stub(truth):
    broken = {tuple(sorted([truth[f"view_{v:03d}.png"][0][0], truth[f"view_{v:03d}.png"][1][0]]))
              for v in BROKEN_VIEWS}
    s = Stub(broken, api_key="testkey")
    yield s
    s.server.shutdown()


def _judge(runs, stub, seed=0, models=MODELS):
    stub.reset()
    return judge.run_judge(runs / "A", runs / "B", models, stub.url, api_key="testkey", seed=seed,
                           timeout=TIMEOUT, retries=RETRIES, backoff=BACKOFF, workers=8)


def _expected(truth, views):
    """Closed form: per criterion, (wins of --a + ties/2) / number of views; authenticity means."""
    cmp = lambda x, y: 1.0 if x > y else 0.0 if x < y else 0.5  # noqa: E731
    n = len(views)
    wr = {"flow_alignment": sum(cmp(truth[v][0][0], truth[v][1][0]) for v in views) / n,
          "materiality": sum(cmp(truth[v][0][1], truth[v][1][1]) for v in views) / n, "aesthetics": 0.5}
    auth = {k: sum(1 + round(9 * truth[v][i][0] / 255) for v in views) / n for i, k in enumerate("ab")}
    return wr, auth


@pytest.mark.parametrize("seed", [0, 1])
def test_win_rates_match_closed_form(runs, stub, truth, seed):
    res = _judge(runs, stub, seed)
    assert stub.problems == []
    views = sorted(truth)
    valid_views = {m: [] if m in ALWAYS_INVALID else
                   [v for v in views if m != "picky" or int(v[5:8]) not in BROKEN_VIEWS] for m in MODELS}
    for m in MODELS:
        s = res["per_model"][m]
        assert s["invalid"] == N_VIEWS - len(valid_views[m]), m
        if not valid_views[m]:
            assert all(x is None for x in s["win_rate"].values()) and s["authenticity"]["a"] is None
            continue
        wr, auth = _expected(truth, valid_views[m])
        for c in judge.CRITERIA:
            assert abs(s["win_rate"][c] - wr[c]) < EXACT, (m, c)
        assert abs(s["authenticity"]["a"] - auth["a"]) < EXACT and abs(s["authenticity"]["b"] - auth["b"]) < EXACT
    # The panel pools every valid verdict (it is not a mean of per-model rates).
    pooled = [v for m in MODELS for v in valid_views[m]]
    wr, auth = _expected(truth, pooled)
    assert res["panel"]["invalid"] == sum(N_VIEWS - len(valid_views[m]) for m in MODELS)
    assert all(abs(res["panel"]["win_rate"][c] - wr[c]) < EXACT for c in judge.CRITERIA)
    assert abs(res["panel"]["authenticity"]["a"] - auth["a"]) < EXACT
    # A tie view is a tie whatever the order; 401 is not retried, garbage is retried RETRIES times.
    tie = [r for r in res["records"] if r["view"] == f"view_{TIE_VIEW:03d}.png" and r["valid"]]
    assert tie and all(set(r["verdict"].values()) == {"tie"} for r in tie)
    recs = {(r["model"], r["view"]): r for r in res["records"]}
    assert all(recs["forbidden", v]["attempts"] == 1 for v in views)
    assert all(recs["garbage", v]["attempts"] == RETRIES + 1 for v in views)
    assert all(recs["slow", v]["attempts"] == 2 and "transport" in recs["slow", v]["errors"][0] for v in views)


def test_shuffle_is_seeded_and_reaches_the_request(runs, stub, truth):
    r1, r2, r3 = _judge(runs, stub, 5), _judge(runs, stub, 5), _judge(runs, stub, 6)
    assert json.dumps(r1["records"]) == json.dumps(r2["records"])
    order = lambda r: [x["shown_as_A"] for x in r["records"]]  # noqa: E731
    assert order(r1) != order(r3)
    for m in MODELS:  # both orders occur for every model across views
        assert {x["shown_as_A"] for x in r3["records"] if x["model"] == m} == {"a", "b"}
    # What the server actually received in position A is the run the record says it showed as A.
    for rec in r3["records"]:
        (ma, _), (mb, _) = truth[rec["view"]]
        if ma == mb:
            continue
        got = {sa[0] for model, sa, sb in stub.seen if model == rec["model"] and {sa[0], sb[0]} == {ma, mb}}
        assert got == {ma if rec["shown_as_A"] == "a" else mb}, rec


def test_backoff_is_exponential(runs, stub):
    delays = []
    urls = [judge.png_data_url(p) for p in (runs / "painting.png", *sorted((runs / "A" / "renders").iterdir())[:2])]
    content = [{"type": "text", "text": judge.PROMPT}] + [{"type": "image_url", "image_url": {"url": u}} for u in urls]
    res = judge.judge_one(stub.url, "garbage", content, "testkey", 5, 3, 0.5, sleep=delays.append)
    assert stub.problems == []
    assert not res["valid"] and res["attempts"] == 4 and delays == [0.5, 1.0, 2.0]


@pytest.mark.parametrize("text,want", [
    ('{"flow_alignment":"A","materiality":"b","aesthetics":"Tie","authenticity":{"A":7,"B":"3"}}',
     ("A", "B", "tie", 7.0, 3.0)),
    ('Sure!\n```json\n{"flow_alignment":"B","materiality":"A","aesthetics":"A",'
     '"authenticity":{"A":10,"B":1}}\n```', ("B", "A", "A", 10.0, 1.0)),
    ('verdict: {"flow_alignment":"tie","materiality":"tie","aesthetics":"B","authenticity":{"a":5,"b":6}} end',
     ("tie", "tie", "B", 5.0, 6.0)),
    ('{"flow_alignment":"A","materiality":"A","aesthetics":"A","authenticity":{"A":11,"B":3}}', None),
    ('{"flow_alignment":"C","materiality":"A","aesthetics":"A","authenticity":{"A":1,"B":3}}', None),
    ('{"flow_alignment":"A","materiality":"A","aesthetics":"A"}', None),
    ("I'm sorry, I can't compare these images.", None),
    ("", None),
])
def test_parse_verdict(text, want):
    if want is None:
        with pytest.raises(ValueError):
            judge.parse_verdict(text)
        return
    p = judge.parse_verdict(text)
    assert (p["flow_alignment"], p["materiality"], p["aesthetics"], p["authenticity"]["A"],
            p["authenticity"]["B"]) == want


def test_cli_plain_folders_with_style(runs, stub, truth, tmp_path, capsys, monkeypatch):
    a, b = tmp_path / "ours", tmp_path / "base"
    for src, dst in ((runs / "A" / "renders", a), (runs / "B" / "renders", b)):
        dst.mkdir()
        for f in src.iterdir():
            (dst / f.name).write_bytes(f.read_bytes())
    monkeypatch.setenv("OPENAI_API_KEY", "testkey")  # the key from the environment reaches the header
    stub.reset()
    rc = main(["judge", "--a", str(a), "--b", str(b), "--models", "clean,garbage", "--base-url", stub.url,
               "--style", str(runs / "painting.png"), "--out", str(tmp_path / "out"), "--seed", "3",
               "--retries", "1", "--backoff", "0.001", "--max-views", "4", "--quiet"])
    out = capsys.readouterr().out
    assert rc == 0 and stub.problems == []
    res = json.loads((tmp_path / "out" / "judge.json").read_text())
    assert res["seed"] == 3 and len(res["views"]) == 4 and res["panel"]["invalid"] == 4
    wr, _ = _expected(truth, res["views"])
    assert abs(res["panel"]["win_rate"]["flow_alignment"] - wr["flow_alignment"]) < EXACT
    assert f"{100 * wr['flow_alignment']:6.2f}%" in out and "Flow Alignment" in out and "Invalid answers: 4" in out
    rc = main(["judge", "--a", str(a), "--b", str(b), "--models", "garbage", "--base-url", stub.url,
               "--style", str(runs / "painting.png"), "--out", str(tmp_path / "out2"), "--retries", "0",
               "--quiet"])
    assert rc == 1  # nothing usable is a failed run, but still a report, not a crash
    assert json.loads((tmp_path / "out2" / "judge.json").read_text())["panel"]["valid"] == 0


def test_missing_folder_exits_2_with_one_line(tmp_path):
    p = subprocess.run([sys.executable, "-m", "tlvg_warp", "judge", "--a", str(tmp_path / "nope"), "--b",
                        str(tmp_path), "--models", "m", "--base-url", "http://127.0.0.1:9/v1"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "nope" in lines[0] and "no such folder" in lines[0], p.stderr


def _copy_run(runs, dst, style=True):
    (dst / "renders").mkdir(parents=True)
    for f in (runs / "A" / "renders").iterdir():
        (dst / "renders" / f.name).write_bytes(f.read_bytes())
    if style:
        (dst / "style.png").write_bytes((runs / "painting.png").read_bytes())
    return dst


@pytest.mark.parametrize("case", ["no_pairs", "unreadable", "no_painting", "config_missing_style"])
def test_bad_input_is_input_error(runs, tmp_path, case):
    a = _copy_run(runs, tmp_path / "a", style=case != "no_painting")
    b = _copy_run(runs, tmp_path / "b", style=False)
    culprit = {"no_pairs": a, "unreadable": b / "renders" / "view_002.png", "no_painting": a,
               "config_missing_style": a / "config.yaml"}[case]
    if case == "no_pairs":
        for f in (b / "renders").iterdir():
            f.rename(f.with_name("other_" + f.name))
    elif case == "unreadable":
        culprit.write_bytes(b"not a png")
    elif case == "config_missing_style":
        culprit.write_text("style: gone.png\n")
    with pytest.raises(InputError) as e:
        judge.run_judge(a, b, ["m"], "http://127.0.0.1:9/v1", retries=0)
    assert e.value.path == str(culprit) and "\n" not in str(e.value)


def test_style_copy_found_and_max_views_spread(runs, tmp_path):
    a = _copy_run(runs, tmp_path / "a")
    pairs, style = judge.resolve_inputs(a, runs / "B", max_views=4)
    assert style == a / "style.png"
    assert [n for n, _, _ in pairs] == [f"view_{v:03d}.png" for v in (0, 2, 4, 6)]
