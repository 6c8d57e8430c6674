"""Per-criterion 1-10 scores of the VLM judge (paper Table 1: win rate, baseline score, ours score) against a
local stub whose scores are a function of the images it receives, and the preflight that stops before sending."""
import base64
import json
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np
import pytest

from tlvg_warp.errors import InputError
from tlvg_warp.eval import judge

N_VIEWS = 5
EXACT = 1e-12  # means of small integers computed the same way: only float rounding differs


def score_of(img):  # the stub's rule: brightness -> flow, contrast -> materiality, constant aesthetics
    return {"flow_alignment": 1 + round(9 * img.mean() / 255), "materiality": 1 + min(9, round(img.std() / 5)),
            "aesthetics": 5}


def _decode(url):
    return cv2.imdecode(np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)


class Handler(BaseHTTPRequestHandler):
    def do_POST(self):  # noqa: N802
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        imgs = [_decode(p["image_url"]["url"]) for p in body["messages"][0]["content"] if p["type"] == "image_url"]
        sa, sb = score_of(imgs[1]), score_of(imgs[2])
        ans = {c: ("A" if sa[c] > sb[c] else "B" if sa[c] < sb[c] else "tie") for c in judge.CRITERIA}
        ans["authenticity"] = {"A": 5, "B": 5}
        ans["scores"] = {c: {"A": sa[c], "B": sb[c]} for c in judge.CRITERIA}
        out = json.dumps({"choices": [{"message": {"content": json.dumps(ans)}}]}).encode()
        self.send_response(200)
        self.send_header("Content-Length", str(len(out)))
        self.end_headers()
        self.wfile.write(out)

    def log_message(self, *a):
        pass


@pytest.fixture(scope="module")
def server():
    srv = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{srv.server_address[1]}/v1"
    srv.shutdown()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("r")
    rng = np.random.default_rng(1)
    imgs = {}
    for r in ("A", "B"):
        (root / r / "renders").mkdir(parents=True)
        for v in range(N_VIEWS):
            img = np.clip(rng.normal(rng.uniform(60, 200), rng.uniform(2, 40), (16, 16, 3)), 0, 255).astype(np.uint8)
            cv2.imwrite(str(root / r / "renders" / f"v{v}.png"), img)
            imgs[(r, v)] = img
    cv2.imwrite(str(root / "p.png"), np.full((20, 24, 3), 128, np.uint8))
    return root, imgs


def test_scores_per_criterion_aggregate_like_table_1(server, runs):
    root, imgs = runs
    res = judge.run_judge(root / "A", root / "B", ["m1", "m2"], server, style=root / "p.png", seed=3, workers=2)
    for agg in (res["panel"], res["per_model"]["m1"]):
        assert agg["scored"] == agg["valid"] > 0
        for c in judge.CRITERIA:
            for r in ("A", "B"):  # oracle: the stub's rule applied to each run's own images, whatever the shuffle
                want = np.mean([score_of(imgs[(r, v)])[c] for v in range(N_VIEWS)])
                assert agg["scores"][c][r.lower()] == pytest.approx(want, abs=EXACT)
        for r in ("A", "B"):  # Table 1's Average: the mean over the three criteria of the stub's per-view rule
            want = np.mean([np.mean([score_of(imgs[(r, v)])[c] for c in judge.CRITERIA]) for v in range(N_VIEWS)])
            assert agg["scores"]["average"][r.lower()] == pytest.approx(want, abs=1e-9)
    table = judge.format_table(res)
    assert "B score" in table and f"{res['panel']['scores']['flow_alignment']['a']:4.2f}" in table
    avg = next(x for x in table.splitlines() if x.startswith("Average"))
    a, b = res["panel"]["scores"]["average"]["a"], res["panel"]["scores"]["average"]["b"]
    assert avg.split()[-2:] == [f"{b:4.2f}", f"{a:4.2f}"]
    assert a != res["panel"]["authenticity"]["a"]  # the stub's authenticity is 5: not what the row shows


def test_parse_rejects_out_of_range_scores():
    bad = {"flow_alignment": "A", "materiality": "B", "aesthetics": "tie", "authenticity": {"A": 3, "B": 4},
           "scores": {c: {"A": 11, "B": 2} for c in judge.CRITERIA}}
    with pytest.raises(ValueError, match="scores"):
        judge.parse_verdict(json.dumps(bad))


def test_preflight_stops_before_sending():
    with pytest.raises(InputError, match="api.example.com.*no API key"):
        judge.preflight("https://api.example.com/v1", None)
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(InputError, match=f"127.0.0.1:{port}.*does not answer"):
        judge.preflight(f"http://127.0.0.1:{port}/v1", None)
