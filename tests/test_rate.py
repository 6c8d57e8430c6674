"""The user study command (`rate`): run folders paired by view, the study's randomization (each rater's sides
balanced, order and sides fixed per rater so that a rater resumes), the answer log (on disk at once, a cut line
skipped), the report's intervals against independent closed forms (scipy's Wilson interval, known values, the
normal approximation for the rater bootstrap), the server's refusal of every path it did not register, bad input
as one line with exit 2, and the page itself driven in headless Chromium: the answers a rater clicks, judged
from the pixels the page showed, are what the log records and the report counts; a reload does not show an
answered item again. Fake run folders are written in the layout `stylize` writes (checked against a real tiny
CPU run)."""
from __future__ import annotations

import http.client
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from tlvg_warp.cli import main
from tlvg_warp.errors import InputError
from tlvg_warp.eval import rate
from tlvg_warp.rate_server import RateServer

sys.path.insert(0, str(Path(__file__).parent))
from _browser import Chromium, find_chromium  # noqa: E402

needs_chromium = pytest.mark.skipif(find_chromium() is None,
                                    reason="no chromium on PATH (apt-get install -y chromium; CI installs it)")
RED, BLUE, GREEN = (230, 20, 20), (20, 20, 230), (20, 160, 40)  # RGB: run A, run B, the painting
W, H = 64, 48
PAGE_TIMEOUT = 30.0


# --- fake run folders in the layout write_outputs uses -------------------------------------------------------
def fake_run(root: Path, color, n_views=4, names=None, shift=0.0, orbit=False, size=(W, H)) -> Path:
    """renders/view_000.png ... (as stylize/outputs.py's write_view names them), style.png, metrics.json with
    ``views``, cameras.json in the INRIA layout of train/reconstruct.cameras_json, config.yaml."""
    root.mkdir(parents=True)
    (root / "renders").mkdir()
    w, h = size
    for i in range(n_views):
        img = np.zeros((h, w, 3), np.uint8)
        img[:] = color
        img[2 + i: 8 + i, 4:12] = 255  # a small mark per view: the views differ
        cv2.imwrite(str(root / "renders" / f"view_{i:03d}.png"), img[:, :, ::-1])
    paint = np.zeros((64, 80, 3), np.uint8)
    paint[:] = GREEN
    cv2.imwrite(str(root / "style.png"), paint[:, :, ::-1])
    names = names or [f"img_{i:02d}.jpg" for i in range(n_views)]
    (root / "metrics.json").write_text(json.dumps({"views": names, "flow_alignment": 0.1}))
    cams = [{"id": i, "img_name": Path(names[i]).stem, "width": w, "height": h,
             "position": [float(np.cos(i)) + shift, float(np.sin(i)), 0.5], "rotation": np.eye(3).tolist(),
             "fx": 50.0, "fy": 50.0} for i in range(n_views)]
    (root / "cameras.json").write_text(json.dumps(cams))
    (root / "config.yaml").write_text("iterations: 10\n")
    if orbit:
        (root / "orbit.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 4)
    return root


@pytest.fixture
def pair(tmp_path):
    return fake_run(tmp_path / "ours", RED), fake_run(tmp_path / "baseline", BLUE)


def _server(study) -> RateServer:
    return RateServer(study, "127.0.0.1", 0)


def _get(url):
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.status, r.read()


def _post(url, body):
    req = urllib.request.Request(url, json.dumps(body).encode(), {"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def _next(srv, rater):
    return json.loads(_get(f"{srv.address}/api/next?rater={rater}")[1])


def _answer(srv, rater, nxt, choice):
    return _post(f"{srv.address}/api/answer?rater={rater}",
                 {"item": nxt["item"], "position": nxt["position"], "choice": choice})


def _media_color(srv, url) -> tuple:
    """The colour of a served image's border: which run it is."""
    data = _get(srv.address + url)[1]
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    return tuple(int(v) for v in img[-1, -1])


# --- run folders and pairs -----------------------------------------------------------------------------------
def test_study_items_are_the_shared_views_and_media_are_the_runs_files(tmp_path, pair):
    a, b = pair
    study = rate.build_study([a, b], tmp_path / "s", seed=1)
    assert study.items == [f"0/view_{i:03d}.png" for i in range(4)]
    p = study.pairs[0]
    assert (p["a_name"], p["b_name"]) == ("ours", "baseline") and p["painting"] == str((a / "style.png").resolve())
    painting, fa, fb = study.item_files("0/view_002.png")
    assert fa == a.resolve() / "renders" / "view_002.png" and fb == b.resolve() / "renders" / "view_002.png"
    assert json.loads((tmp_path / "s" / "study.json").read_text())["seed"] == 1
    sub = rate.build_study([a, b], tmp_path / "s2", max_views=2, seed=1)  # evenly spaced
    assert sub.items == ["0/view_000.png", "0/view_002.png"]


def test_restart_on_the_same_folder_keeps_the_study_and_refuses_other_runs(tmp_path, pair):
    a, b = pair
    s1 = rate.build_study([a, b], tmp_path / "s")  # a random seed, kept in study.json
    s2 = rate.build_study([a, b], tmp_path / "s")
    assert s2.seed == s1.seed and s2.order("x") == s1.order("x") and s2.a_left("x") == s1.a_left("x")
    c = fake_run(tmp_path / "other", BLUE)
    with pytest.raises(InputError, match="study of other runs"):
        rate.build_study([a, c], tmp_path / "s")


@pytest.mark.parametrize("case, match", [
    ("odd", "pairs of run folders"),
    ("missing", "no such run folder"),
    ("no_renders", "without renders/"),
    ("empty", "no renders"),
    ("fewer_views", "not render the same views.*only in .*ours: view_003.png"),
    ("other_dataset_views", "metrics.json views differ"),
    ("other_cameras", "camera centres differ"),
    ("other_shape", "differ in shape"),
    ("same_run", "paired with itself"),
    ("report_not_a_study", "not a study folder"),
    ("orbit_missing", "no orbit.mp4"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, case, match):
    a = fake_run(tmp_path / "ours", RED)
    b = {"fewer_views": lambda: fake_run(tmp_path / "b", BLUE, n_views=3),
         "other_dataset_views": lambda: fake_run(tmp_path / "b", BLUE, names=[f"x{i}.jpg" for i in range(4)]),
         "other_cameras": lambda: fake_run(tmp_path / "b", BLUE, shift=0.5),
         "other_shape": lambda: fake_run(tmp_path / "b", BLUE, size=(48, 48))}.get(case,
                                                                                lambda: fake_run(tmp_path / "b", BLUE))()
    argv = ["rate", str(a), str(b), "--out", str(tmp_path / "study")]
    if case == "odd":
        argv = ["rate", str(a), str(b), str(a), "--out", str(tmp_path / "study")]
    elif case == "missing":
        argv[2] = str(tmp_path / "nope")
    elif case == "no_renders":
        shutil.rmtree(b / "renders")
    elif case == "empty":
        (tmp_path / "empty").mkdir()
        argv[2] = str(tmp_path / "empty")
    elif case == "same_run":
        argv[2] = str(a)
    elif case == "report_not_a_study":
        argv = ["rate", "--report", str(a)]
    elif case == "orbit_missing":
        argv += ["--media", "orbit"]
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error: "), err
    import re
    assert re.search(match, err[0]), err[0]
    assert not (tmp_path / "study" / "answers.jsonl").exists()


# --- randomization -----------------------------------------------------------------------------------------
def test_sides_are_balanced_per_rater_and_per_item(tmp_path):
    a = fake_run(tmp_path / "a", RED, n_views=7)  # an odd number of items
    b = fake_run(tmp_path / "b", BLUE, n_views=7)
    study = rate.build_study([a, b], tmp_path / "s", seed=123)
    n_items = len(study.items)
    per_item = {it: 0 for it in study.items}
    first_left, orders = 0, set()
    raters = [f"rater{k}" for k in range(400)]
    for r in raters:
        order, left = study.order(r), study.a_left(r)
        assert sorted(order) == sorted(study.items) and len(left) == n_items
        for m in range(1, n_items + 1):  # every prefix: A on the left half the time, +-1 for an odd prefix
            assert abs(2 * sum(left[:m]) - m) <= 1, (r, m, left)
        for it, l in zip(order, left):
            per_item[it] += l
        first_left += left[0]
        orders.add(tuple(order))
    assert len(orders) > 300  # the order differs between raters
    # each item is left about as often as right over raters (binomial sd for 400 raters: 10)
    assert all(150 <= v <= 250 for v in per_item.values()), per_item
    assert 150 <= first_left <= 250
    assert study.order("rater0") == rate.load_study(tmp_path / "s").order("rater0")  # fixed by (seed, rater)


def test_a_rater_answering_everything_sees_a_left_half_the_time(tmp_path):
    a = fake_run(tmp_path / "a", RED, n_views=6)
    b = fake_run(tmp_path / "b", BLUE, n_views=6)
    srv = _server(rate.build_study([a, b], tmp_path / "s", seed=5))
    try:
        a_left = 0
        while not (n := _next(srv, "solo"))["done"]:
            left_is_a = _media_color(srv, n["left"]) == RED  # what was served, not what the log says
            assert _media_color(srv, n["right"]) == (BLUE if left_is_a else RED)
            a_left += left_is_a
            st, out = _answer(srv, "solo", n, {"flow": "left", "materiality": "left", "aesthetics": "right"})
            assert st == 200 and out["ok"]
    finally:
        srv.stop()
    answers, _, _ = rate.read_answers(tmp_path / "s")
    assert a_left == 3 and sum(r["left"] == "A" for r in answers) == 3 and len(answers) == 6


# --- the log, resuming, several raters --------------------------------------------------------------------------
def test_each_answer_is_on_disk_before_the_reply_and_resumes_after_a_restart(tmp_path, pair):
    folder = tmp_path / "s"
    study = rate.build_study(list(pair), folder, seed=9)
    srv = _server(study)
    try:
        n1 = _next(srv, "ann")
        assert _next(srv, "ann")["item"] == n1["item"]  # asking again shows the same item
        st, out = _answer(srv, "ann", n1, {"flow": "left", "materiality": "right", "aesthetics": "left"})
        assert st == 200
        lines = (folder / "answers.jsonl").read_text().splitlines()  # written when the reply came
        rec = json.loads(lines[-1])
        assert rec["rater"] == "ann" and rec["item"] == n1["item"] and rec["choice"]["materiality"] == "right"
        expect_a = "A" if _media_color(srv, n1["left"]) == RED else "B"
        assert rec["left"] == expect_a and rec["winner"]["flow"] == expect_a
        assert rec["winner"]["materiality"] == ("B" if expect_a == "A" else "A")
        st, dup = _answer(srv, "ann", n1, {"flow": "left", "materiality": "left", "aesthetics": "left"})
        assert st == 409 and dup["next"]["item"] != n1["item"]  # a second tab's answer to the same item
        assert len((folder / "answers.jsonl").read_text().splitlines()) == 1
        bob = _next(srv, "bob")  # another rater starts at the beginning of his own order
        assert bob["answered"] == 0
        n2 = out["next"]
    finally:
        srv.stop()
    srv = _server(rate.build_study(list(pair), folder))  # the server restarted on the same folder
    try:
        again = _next(srv, "ann")
        assert again["item"] == n2["item"] and again["answered"] == 1 and again["item"] != n1["item"]
    finally:
        srv.stop()


def test_a_line_cut_by_a_crash_is_skipped_and_the_next_answer_is_kept(tmp_path, pair):
    folder = tmp_path / "s"
    rate.build_study(list(pair), folder, seed=2)
    good = {"type": "answer", "rater": "r1", "item": "0/view_000.png", "pair": 0, "left": "A", "right": "B",
            "choice": dict.fromkeys(rate.CRITERION_KEYS, "left"), "winner": dict.fromkeys(rate.CRITERION_KEYS, "A")}
    (folder / "answers.jsonl").write_text(json.dumps(good) + "\n" + '{"type": "answer", "rater": "r1", "it')
    srv = _server(rate.load_study(folder))
    try:
        n = _next(srv, "r2")
        assert _answer(srv, "r2", n, {"flow": "right", "materiality": "right", "aesthetics": "right"})[0] == 200
    finally:
        srv.stop()
    answers, _, bad = rate.read_answers(folder)
    assert bad == 1 and [r["rater"] for r in answers] == ["r1", "r2"]


def test_raters_without_an_id_get_their_own_by_cookie(tmp_path, pair):
    import http.cookiejar

    srv = _server(rate.build_study(list(pair), tmp_path / "s", seed=3))
    try:
        ids = []
        for _ in range(2):
            jar = http.cookiejar.CookieJar()
            opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(jar))
            html = opener.open(srv.address + "/", timeout=10).read().decode()
            rid = next(c.value for c in jar if c.name == "tlvg_rater")
            assert f'data-rater="{rid}"' in html
            again = opener.open(srv.address + "/", timeout=10).read().decode()  # the cookie brings it back
            assert f'data-rater="{rid}"' in again
            ids.append(rid)
        assert ids[0] != ids[1]
        st, body = _get(srv.address + "/?rater=carol")
        assert f'data-rater="carol"' in body.decode()
        with pytest.raises(urllib.error.HTTPError) as e:
            _get(srv.address + "/?rater=%3Cscript%3E")
        assert e.value.code == 400
    finally:
        srv.stop()


# --- the server serves only its own files ---------------------------------------------------------------------
def test_only_registered_files_are_served(tmp_path, pair):
    a, b = pair
    folder = tmp_path / "s"
    srv = _server(rate.build_study([a, b], folder, seed=4))
    (folder / "answers.jsonl").write_text("")
    host, port = srv.httpd.server_address[:2]
    assert host == "127.0.0.1"
    n = _next(srv, "t")
    render = a.resolve() / "renders" / "view_000.png"
    bad = ["/../etc/passwd", "/%2e%2e/%2e%2e/etc/passwd", "/..%2f..%2fetc%2fpasswd", "/media/../study.json",
           "/media/%2e%2e/answers.jsonl", "/media/..%2fanswers.jsonl", "/study.json", "/answers.jsonl",
           "/rate.js/../study.json", "/assets/rate.js", "/tlvg_warp/assets/rate.html", "//etc/passwd",
           "/etc/passwd", str(render), "/media/" + str(render), "/media" + str(render), "/media/" + "0" * 24,
           n["left"] + "/", n["left"] + "/..", "/renders/view_000.png", "/%2fetc%2fpasswd", "/..\\study.json",
           "/rate.css%00.js", "/favicon.ico", "/" + "../" * 16 + "etc/passwd", "/" + "%2e%2e/" * 16 + "etc/passwd",
           "/" + "%2e%2e%2f" * 16 + "etc%2fpasswd", "/media/" + "..%2f" * 16 + "etc%2fpasswd"]
    try:
        for path in bad:
            conn = http.client.HTTPConnection(host, port, timeout=10)
            conn.request("GET", path)  # sent as is: no client-side normalization of '..'
            r = conn.getresponse()
            body = r.read()
            assert r.status == 404, (path, r.status)
            assert b"root:" not in body and b"seed" not in body
            conn.close()
        for path in ("/rate.js", "/rate.css", n["left"], n["painting"]):
            assert _get(srv.address + path)[0] == 200
            assert _get(f"http://localhost:{port}{path}")[0] == 200
            conn = http.client.HTTPConnection(host, port, timeout=10)  # a page elsewhere, its name rebound to us
            conn.request("GET", path, headers={"Host": f"attacker.example:{port}"})
            assert conn.getresponse().status == 403
            conn.close()
        conn = http.client.HTTPConnection(host, port, timeout=10)
        conn.request("GET", n["left"], headers={"Range": "bytes=0-9"})  # video seeking
        r = conn.getresponse()
        assert r.status == 206 and r.read() == (render.read_bytes()[:10] if _media_color(srv, n["left"]) == RED
                                                else (b.resolve() / "renders/view_000.png").read_bytes()[:10])
        conn.close()
    finally:
        srv.stop()


def test_media_ids_do_not_tell_the_runs_apart(tmp_path, pair):
    """A rater reading the page's URLs learns nothing: ids are hashes, the same length, no run name in them."""
    study = rate.build_study(list(pair), tmp_path / "s", seed=8)
    srv = _server(study)
    try:
        n = _next(srv, "x")
        text = json.dumps(n)
        assert "ours" not in text and "baseline" not in text and "renders" not in text
        assert len(n["left"]) == len(n["right"]) and n["left"] != n["right"]
    finally:
        srv.stop()


# --- statistics against independent closed forms --------------------------------------------------------------
@pytest.mark.parametrize("k, n", [(0, 1), (1, 1), (0, 10), (3, 10), (8, 10), (10, 10), (41, 60), (500, 1000),
                                  (7, 13), (299, 300)])
def test_wilson_matches_scipy(k, n):
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    lo, hi = rate.wilson(k, n)
    assert abs(lo - ci.low) < 1e-9 and abs(hi - ci.high) < 1e-9


def test_wilson_known_values():
    # 8 of 10: the textbook 95% Wilson interval (Newcombe 1998, Table I style values)
    lo, hi = rate.wilson(8, 10)
    assert round(lo, 4) == 0.4902 and round(hi, 4) == 0.9433
    lo, hi = rate.wilson(0, 10)  # all losses: [0, z²/(n+z²)]
    assert lo == 0.0 and abs(hi - 1.959964 ** 2 / (10 + 1.959964 ** 2)) < 1e-6
    assert all(np.isnan(rate.wilson(0, 0)))


def test_rater_bootstrap_is_the_binomial_interval_for_one_answer_each_and_wider_for_clustered_raters():
    rng = np.random.default_rng(1)
    wins = (rng.random(600) < 0.7).astype(int)  # 600 raters, one answer each: independent answers
    lo, hi = rate.rater_bootstrap(wins, np.ones(600))
    p = wins.mean()
    se = np.sqrt(p * (1 - p) / 600)
    assert abs(lo - (p - 1.96 * se)) < 0.01 and abs(hi - (p + 1.96 * se)) < 0.01
    # 40 raters who each answer 10 items all the same way: only 40 independent opinions
    w = np.repeat([10, 0], [28, 12])
    blo, bhi = rate.rater_bootstrap(w, np.full(40, 10))
    wlo, whi = rate.wilson(int(w.sum()), 400)
    assert (bhi - blo) > 2.5 * (whi - wlo)
    assert all(np.isnan(rate.rater_bootstrap([3, 1, 2, 4], [4] * 4)))  # too few raters to resample


def _cell(per_rater_wins, per=10) -> rate.Cell:
    w, n = np.array(per_rater_wins), np.full(len(per_rater_wins), per)
    return rate.Cell(int(w.sum()), int(n.sum()), len(w), rate.wilson(int(w.sum()), int(n.sum())),
                     rate.rater_bootstrap(w, n))


def test_verdict_is_a_win_only_where_the_intervals_exclude_half():
    assert _cell([8, 9, 7, 8, 8, 9, 7, 8, 8, 8]).verdict() == "A"
    assert _cell([2, 1, 3, 2, 2, 1, 3, 2, 2, 2]).verdict() == "B"
    assert _cell([5, 6, 4, 5, 5, 6, 4, 5, 5, 5]).verdict() == "none"
    # a Wilson interval that excludes 50% is not enough when the raters disagree among themselves
    split = _cell([10] * 6 + [0] * 4)
    assert split.wilson[0] > 0.5 and split.boot[0] < 0.5 and split.verdict() == "none"
    # fewer than MIN_RATERS raters: no verdict however sure the Wilson interval over their answers is
    few = _cell([10] * (rate.MIN_RATERS - 1))
    assert few.wilson[0] > 0.9 and np.isnan(few.boot[0]) and few.verdict() == "none"
    assert _cell([10] * rate.MIN_RATERS).verdict() == "A"
    assert rate.Cell(0, 0, 0, rate.wilson(0, 0), (np.nan, np.nan)).verdict() == "none"


# --- the report ---------------------------------------------------------------------------------------------------
def _scripted(srv, rater, pick, expertise=None):
    """A rater who answers every item: pick(criterion, A is left) -> 'left' / 'right'."""
    if expertise is not None:
        assert _post(f"{srv.address}/api/expertise?rater={rater}", {"expertise": expertise})[0] == 200
    while not (n := _next(srv, rater))["done"]:
        a_left = _media_color(srv, n["left"]) == RED
        assert _answer(srv, rater, n, {c: pick(c, a_left) for c in rate.CRITERION_KEYS})[0] == 200


def test_report_counts_and_intervals(tmp_path, capsys):
    a = fake_run(tmp_path / "ours", RED, n_views=5)
    b = fake_run(tmp_path / "baseline", BLUE, n_views=5)
    folder = tmp_path / "s"
    srv = _server(rate.build_study([a, b], folder, seed=11))
    side = lambda want_a, a_left: "left" if want_a == a_left else "right"  # noqa: E731
    try:
        # the professional prefers A on flow and materiality, B on aesthetics; the other always B; the third
        # (no expertise given) always A
        _scripted(srv, "pro", lambda c, al: side(c != "aesthetics", al), expertise="professional")
        _scripted(srv, "lay", lambda c, al: side(False, al), expertise="other")
        _scripted(srv, "anon", lambda c, al: side(True, al))
    finally:
        srv.stop()
    assert main(["rate", "--report", str(folder)]) == 0
    out = capsys.readouterr().out
    s = rate.summarize(folder)
    g = s["groups"]
    assert (g["all"]["flow"].wins, g["all"]["flow"].n, g["all"]["flow"].raters) == (10, 15, 3)
    assert (g["all"]["aesthetics"].wins, g["all"]["aesthetics"].n) == (5, 15)
    assert (g["professional"]["flow"].wins, g["professional"]["flow"].n) == (5, 5)
    assert (g["professional"]["aesthetics"].wins, g["other"]["materiality"].wins, g["other"]["flow"].n) == (0, 0, 5)
    assert s["undeclared"] == 1
    from scipy.stats import binomtest

    ci = binomtest(10, 15).proportion_ci(method="wilson")
    row = next(ln for ln in out.splitlines() if ln.startswith("Flow Alignment"))
    assert "all raters" in row and "66.7%" in row and f"[{100 * ci.low:.1f}, {100 * ci.high:.1f}]" in row
    assert "Flow Alignment: no winner (fewer than 5 raters)" in out  # 10 of 15 from 3 raters
    md = (folder / "report.md").read_text()
    assert "| Flow Alignment | art professionals | 5 | 1 | 100.0% |" in md
    png = cv2.imread(str(folder / "report.png"))
    assert png is not None and png.shape[1] >= 600


def test_report_of_a_clear_preference_says_who_wins(tmp_path, capsys):
    a = fake_run(tmp_path / "ours", RED, n_views=4)
    b = fake_run(tmp_path / "baseline", BLUE, n_views=4)
    folder = tmp_path / "s"
    srv = _server(rate.build_study([a, b], folder, seed=12))
    try:
        for k in range(8):  # 8 raters; 7 always pick A on flow, aesthetics split by rater
            _scripted(srv, f"r{k}", lambda c, al, k=k: ("left" if al else "right") if
                      (c == "flow" and k < 7) or (c == "aesthetics" and k % 2) else ("right" if al else "left"))
    finally:
        srv.stop()
    assert main(["rate", "--report", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "Flow Alignment: A (ours) wins: 87.5% of 32 answers from 8 raters" in out
    assert "Painterly Materiality: B (baseline) wins" in out
    assert "Aesthetic Preference: no winner" in out


# --- the command -----------------------------------------------------------------------------------------------------
def test_cli_serves_prints_the_address_and_stops_on_ctrl_c(tmp_path, pair):
    import socket

    with socket.socket() as sck:
        sck.bind(("127.0.0.1", 0))
        port = sck.getsockname()[1]
    p = subprocess.Popen([sys.executable, "-m", "tlvg_warp", "rate", str(pair[0]), str(pair[1]), "--out",
                          str(tmp_path / "s"), "--port", str(port)], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        line = p.stdout.readline()
        assert line.startswith(f"rate: http://127.0.0.1:{port}/"), line
        st, html = _get(f"http://127.0.0.1:{port}/")
        assert st == 200 and b"<html" in html
        p.send_signal(signal.SIGINT)
        assert p.wait(30) == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


# --- a real run folder ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def real_run(tmp_path_factory):
    from _demo_helpers import demo_stylize_inputs

    from tlvg_warp.stylize import run_stylize, write_outputs
    from tlvg_warp.stylize.config import config_from_dict

    _, inp = demo_stylize_inputs(3, 32, 24, every=8)
    cfg = config_from_dict({"iterations": 6, "device": "cpu", "vgg_weights": "random", "log_every": 3,
                            "orbit_frames": 4, "density.interval": 3, "comparison_views": 1, "style_height": 64,
                            "web_formats": False})
    out = tmp_path_factory.mktemp("real") / "run"
    write_outputs(out, run_stylize(inp, cfg, out, progress=False, quiet=True))
    return out


def test_a_real_run_folder_pairs_and_matches_the_fake_layout(tmp_path, real_run):
    r = rate.load_run(real_run)
    f = rate.load_run(fake_run(tmp_path / "fake", RED, n_views=3, orbit=True))
    assert sorted(r.views) == sorted(f.views) == [f"view_{i:03d}.png" for i in range(3)]
    assert all(p.parent.name == "renders" for p in (*r.views.values(), *f.views.values()))
    assert r.painting.name == f.painting.name == "style.png" and r.orbit.name == f.orbit.name == "orbit.mp4"
    assert len(r.view_names) == len(f.view_names) == 3
    assert set(r.cameras[0]) == set(f.cameras[0])  # the same cameras.json keys
    twin = tmp_path / "twin"
    shutil.copytree(real_run, twin)  # a second run of the same views
    study = rate.build_study([real_run, twin], tmp_path / "s", media="both", seed=0)
    assert study.items == [f"0/view_{i:03d}.png" for i in range(3)] + ["0/orbit.mp4"]
    srv = _server(study)
    try:
        seen = set()
        while not (n := _next(srv, "v"))["done"]:
            assert n["kind"] == ("video" if n["item"].endswith("orbit.mp4") else "image")
            body = _get(srv.address + n["left"])[1]
            view = n["item"].split("/", 1)[1]
            src = real_run / ("orbit.mp4" if view == "orbit.mp4" else f"renders/{view}")
            assert body == src.read_bytes()  # the twin's files are byte copies
            seen.add(n["item"])
            _answer(srv, "v", n, dict.fromkeys(rate.CRITERION_KEYS, "left"))
        assert seen == set(study.items)
    finally:
        srv.stop()


# --- the page in a browser --------------------------------------------------------------------------------------------
def _wait(c: Chromium, js: str, timeout=PAGE_TIMEOUT):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            v = c.eval(js)
        except RuntimeError:  # the page navigating: its context went away under the call
            v = None
        if v:
            return v
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {js}")


def _loaded(c: Chromium) -> str:
    """The item id once the page shows it with its three images loaded."""
    return _wait(c, "(() => { const s = window.rateState && rateState(); return s && !s.done && "
                    "document.body.dataset.loaded === s.item ? s.item : null; })()")


def _side_colors(c: Chromium) -> tuple:
    """The colour in the middle of the left and the right image, from a screenshot: what the rater saw."""
    img = c.screenshot()
    out = []
    for side in ("left", "right"):
        box = c.eval(f"(() => {{ const r = document.querySelector('#{side} img').getBoundingClientRect(); "
                     "return [r.left, r.top, r.width, r.height]; })()")
        x, y = int(box[0] + box[2] * 0.75), int(box[1] + box[3] * 0.75)  # away from the view's white mark
        out.append(tuple(int(v) for v in img[y, x]))
    return tuple(out)


def _reload(c: Chromium):
    """Reload the page and wait for the new document (the old one's marker gone)."""
    c.eval("window.oldPage = true")
    c.call("Page.reload")
    _wait(c, "window.oldPage === undefined && document.readyState === 'complete'")


def _is(color, ref) -> bool:
    return max(abs(a - b) for a, b in zip(color, ref)) < 40


def _click_answers(c: Chromium, picks: dict):
    for crit, side in picks.items():
        c.eval(f"document.querySelector('input[name=\"{crit}\"][value=\"{side}\"]').click()")
    assert c.eval("document.querySelector('#submit').disabled") is False
    c.eval("document.querySelector('#submit').click()")


@needs_chromium
def test_browser_answers_are_recorded_counted_and_not_shown_again(tmp_path):
    a = fake_run(tmp_path / "ours", RED, n_views=4)
    b = fake_run(tmp_path / "baseline", BLUE, n_views=4)
    folder = tmp_path / "s"
    srv = _server(rate.build_study([a, b], folder, seed=21))
    seen, a_left_seen = [], []
    try:
        with Chromium(srv.address + "/?rater=alice", 900, 900) as c:
            item = _loaded(c)
            assert c.eval("document.querySelector('#submit').disabled") is True  # nothing chosen yet
            c.eval("document.querySelector('input[name=\"expertise\"][value=\"professional\"]').click()")
            _wait(c, "document.querySelector('#expertise-saved').textContent.startsWith('saved')")
            for k in range(4):
                if k == 2:  # the rater stops and comes back (a reload): the answered items stay answered
                    _reload(c)
                    item = _loaded(c)
                    assert item not in seen, (item, seen)
                    assert c.eval("document.querySelector('#progress').textContent") == "item 3 of 4"
                    assert c.eval("document.querySelector('input[name=\"expertise\"]:checked').value") \
                        == "professional"
                left, right = _side_colors(c)
                a_left = _is(left, RED)
                assert a_left != _is(left, BLUE) and _is(right, BLUE if a_left else RED), (left, right)
                assert _is(_side_colors_painting(c), GREEN)
                seen.append(item)
                a_left_seen.append(a_left)
                # flow: the red one (A); materiality: always the left one; aesthetics: the blue one (B)
                _click_answers(c, {"flow": "left" if a_left else "right", "materiality": "left",
                                   "aesthetics": "right" if a_left else "left"})
                if k < 3:
                    item = _wait(c, f"(() => {{ const s = rateState(); return s && s.item !== '{item}' && "
                                    "document.body.dataset.loaded === s.item ? s.item : null; })()")
            _wait(c, "!document.querySelector('#done').hidden")
            assert c.eval("document.querySelector('#study').hidden") is True
            _reload(c)  # done stays done
            _wait(c, "window.rateState && rateState() && rateState().done && "
                     "!document.querySelector('#done').hidden")
    finally:
        srv.stop()
    assert len(set(seen)) == 4 and sorted(seen) == sorted(rate.load_study(folder).items)
    assert sum(a_left_seen) == 2  # balanced sides for this rater
    answers, expertise, _ = rate.read_answers(folder)
    assert expertise == {"alice": "professional"} and [r["item"] for r in answers] == seen
    assert [r["left"] == "A" for r in answers] == a_left_seen  # the log's sides are the ones on screen
    s = rate.summarize(folder)
    g = s["groups"]
    assert (g["all"]["flow"].wins, g["all"]["flow"].n) == (4, 4)
    assert g["all"]["materiality"].wins == sum(a_left_seen)
    assert g["all"]["aesthetics"].wins == 0
    assert g["professional"]["flow"].n == 4 and g["other"]["flow"].n == 0
    assert s["left"]["materiality"].wins == 4


def _side_colors_painting(c: Chromium) -> tuple:
    img = c.screenshot()
    box = c.eval("(() => { const r = document.querySelector('#painting').getBoundingClientRect(); "
                 "return [r.left, r.top, r.width, r.height]; })()")
    return tuple(int(v) for v in img[int(box[1] + box[3] / 2), int(box[0] + box[2] / 2)])


@needs_chromium
def test_browser_plays_the_orbit_videos_of_a_real_run(tmp_path, real_run):
    twin = tmp_path / "twin"
    shutil.copytree(real_run, twin)
    study = rate.build_study([real_run, twin], tmp_path / "s", media="orbit", seed=0)
    assert study.items == ["0/orbit.mp4"]
    srv = _server(study)
    try:
        with Chromium(srv.address + "/?rater=viewer", 800, 700) as c:
            assert _loaded(c) == "0/orbit.mp4"  # both videos decoded their first frame
            size = c.eval("[...document.querySelectorAll('#pair video')].map(v => [v.videoWidth, v.videoHeight])")
            cams = json.loads((real_run / "cameras.json").read_text())
            assert size == [[cams[0]["width"], cams[0]["height"]]] * 2
            t0 = c.eval("document.querySelector('#left video').currentTime")
            _wait(c, f"document.querySelector('#left video').currentTime > {t0} + 0.05")  # it plays
    finally:
        srv.stop()
