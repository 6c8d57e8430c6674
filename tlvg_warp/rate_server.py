"""The web page of the user study (tlvg_warp.eval.rate): Python's ThreadingHTTPServer, no other dependency.

It serves exactly: the page (/), its script and style (/rate.js, /rate.css), the study's media by opaque id
(/media/<id>: the paintings, renders and orbit videos the study registered), and a small JSON API
(/api/next, /api/answer, /api/expertise). Any other path, including ones that climb out with ``..`` (plain or
percent-encoded) or name a file by its path, is a 404: nothing is looked up on disk by a name from the URL.

A rater is identified by ``?rater=ID`` in the URL or, failing that, by a cookie the page sets on the first visit.
The same id continues where it stopped (its order of items and sides are fixed by the study's seed and the id;
what it answered is read back from answers.jsonl at start), and an item it answered is never shown to it again.
"""
from __future__ import annotations

import json
import mimetypes
import re
import secrets
import sys
import threading
import time
from http import cookies
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from .errors import InputError
from .eval.rate import (CRITERIA, CRITERION_KEYS, EXPERTISE, ORBIT, RATER_ID, AnswerLog, Study, _now,
                        read_answers)

ASSETS = Path(__file__).resolve().parent / "assets"
PAGE_FILES = {"/rate.js": ("rate.js", "text/javascript; charset=utf-8"),
              "/rate.css": ("rate.css", "text/css; charset=utf-8")}
MEDIA_PATH = re.compile(r"/media/([0-9a-f]{24})")
MAX_BODY = 16 << 10  # bytes of a POST body
COOKIE = "tlvg_rater"
DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8765
PORT_TRIES = 20  # a busy port moves to the next free one (the printed address says which)
CSP = "default-src 'self'; img-src 'self'; media-src 'self'; style-src 'self'; script-src 'self'; " \
      "frame-ancestors 'none'"


class RateServer:
    """The study's server, running in a background thread once constructed; ``stop()`` ends it."""

    def __init__(self, study: Study, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, log_requests=False):
        self.study = study
        study.register_media()
        self.log = AnswerLog(study.folder)
        answers, self.expertise, _ = read_answers(study.folder)
        self.answered: dict = {}
        for r in answers:
            self.answered.setdefault(r["rater"], set()).add(r["item"])
        self.lock = threading.Lock()
        self.shown: dict = {}  # (rater, item) -> time.monotonic() when the item was sent to the rater
        self._orders: dict = {}
        self.log_requests = log_requests
        self.httpd = _bind(host, port, _handler(self))
        # bound to this machine only: refuse requests that name another host (a web page elsewhere that makes
        # the browser resolve its own name to 127.0.0.1 must not read or post to the study)
        self.local_only = host in ("127.0.0.1", "localhost", "::1")
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="rate-server", daemon=True)
        self.thread.start()

    @property
    def address(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{'[' + host + ']' if ':' in host else host}:{port}"

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()

    # --- the rater's state ---------------------------------------------------------------------------------
    def _order(self, rater: str) -> tuple:
        if rater not in self._orders:
            self._orders[rater] = (self.study.order(rater), self.study.a_left(rater))
        return self._orders[rater]

    def next_item(self, rater: str) -> dict:
        """The payload of the rater's next item (or ``done``). Call with the lock held."""
        order, a_left = self._order(rater)
        done = self.answered.get(rater, set())
        out = {"rater": rater, "total": len(order), "answered": len(done & set(order)),
               "expertise": self.expertise.get(rater),
               "criteria": [{"key": k, "name": n, "question": q} for k, n, q in CRITERIA]}
        pos = next((i for i, it in enumerate(order) if it not in done), None)
        if pos is None:
            return dict(out, done=True)
        item = order[pos]
        painting, fa, fb = self.study.item_files(item)
        left, right = (fa, fb) if a_left[pos] else (fb, fa)
        self.shown.setdefault((rater, item), time.monotonic())
        media = lambda f: "/media/" + self.study.media_id(f)  # noqa: E731
        return dict(out, done=False, item=item, position=pos, painting=media(painting), left=media(left),
                    right=media(right), kind="video" if item.endswith("/" + ORBIT) else "image")

    def answer(self, rater: str, body: dict) -> tuple:
        """Record one answer; (HTTP status, payload with the next item)."""
        choice = body.get("choice")
        if not isinstance(choice, dict) or any(choice.get(c) not in ("left", "right") for c in CRITERION_KEYS):
            return 400, {"error": "choose left or right for every criterion: " + ", ".join(CRITERION_KEYS)}
        with self.lock:
            order, a_left = self._order(rater)
            item, pos = body.get("item"), body.get("position")
            if not isinstance(pos, int) or not 0 <= pos < len(order) or order[pos] != item:
                return 400, {"error": "unknown item", "next": self.next_item(rater)}
            if item in self.answered.get(rater, set()):
                return 409, {"error": "already answered", "next": self.next_item(rater)}
            k, view = item.split("/", 1)
            pair = self.study.pairs[int(k)]
            sides = ("A", "B") if a_left[pos] else ("B", "A")
            shown = self.shown.pop((rater, item), None)
            rec = {"type": "answer", "time": _now(), "rater": rater, "item": item, "pair": int(k), "view": view,
                   "position": pos, "a": pair["a_name"], "b": pair["b_name"], "left": sides[0], "right": sides[1],
                   "choice": {c: choice[c] for c in CRITERION_KEYS},
                   "winner": {c: sides[0] if choice[c] == "left" else sides[1] for c in CRITERION_KEYS},
                   "expertise": self.expertise.get(rater),
                   "seconds": None if shown is None else round(time.monotonic() - shown, 2)}
            self.log.append(rec)  # on disk before the rater sees the next item
            self.answered.setdefault(rater, set()).add(item)
            return 200, {"ok": True, "next": self.next_item(rater)}

    def set_expertise(self, rater: str, body: dict) -> tuple:
        value = body.get("expertise")
        if value not in EXPERTISE and value is not None:
            return 400, {"error": f"expertise is one of {', '.join(EXPERTISE)} or null"}
        with self.lock:
            self.log.append({"type": "rater", "time": _now(), "rater": rater, "expertise": value})
            self.expertise[rater] = value
        return 200, {"ok": True, "expertise": value}


def _bind(host: str, port: int, handler) -> ThreadingHTTPServer:
    last = None
    for p in ([0] if port == 0 else range(port, port + PORT_TRIES)):
        try:
            httpd = ThreadingHTTPServer((host, p), handler)
            httpd.daemon_threads = True
            return httpd
        except OSError as e:
            last = e
            if e.errno not in (98, 48):  # only "address in use" moves on (EADDRINUSE on Linux and macOS)
                break
    raise InputError(f"cannot serve on {host}:{port} ({getattr(last, 'strerror', None) or last})")


def _page(rater: str) -> bytes:
    html = (ASSETS / "rate.html").read_text(encoding="utf-8")
    return html.replace("{{RATER}}", rater).encode()  # the id matched RATER_ID: no markup in it


def _handler(srv: RateServer):
    class Handler(BaseHTTPRequestHandler):
        server_version = "tlvg-rate"
        sys_version = ""

        def log_message(self, fmt, *args):  # noqa: D401 - quiet unless asked
            if srv.log_requests:
                sys.stderr.write("rate: " + fmt % args + "\n")

        # --- responses --------------------------------------------------------------------------------------
        def _send(self, status, body: bytes, ctype: str, extra=()):
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("Content-Security-Policy", CSP)
            self.send_header("Referrer-Policy", "no-referrer")
            for k, v in extra:
                self.send_header(k, v)
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _json(self, status, obj):
            self._send(status, json.dumps(obj).encode(), "application/json", [("Cache-Control", "no-store")])

        def _not_found(self):
            self._send(404, b"not found\n", "text/plain; charset=utf-8")

        # --- the rater ------------------------------------------------------------------------------------
        def _rater(self, query: dict):
            """(id or None, whether the id given was malformed)."""
            given = query.get("rater", [None])[0]
            if given is None:
                jar = cookies.SimpleCookie()
                try:
                    jar.load(self.headers.get("Cookie", ""))
                except cookies.CookieError:
                    pass
                given = jar[COOKIE].value if COOKIE in jar else None
            if given is None:
                return None, False
            return (given, False) if RATER_ID.fullmatch(given) else (None, True)

        # --- routes -----------------------------------------------------------------------------------------
        def do_HEAD(self):
            self.do_GET()

        def _foreign_host(self) -> bool:
            if not srv.local_only:
                return False
            host = self.headers.get("Host", "")
            name = host.rsplit(":", 1)[0] if not host.startswith("[") else host.split("]")[0] + "]"
            if name in ("127.0.0.1", "localhost", "[::1]"):
                return False
            self._send(403, b"this study is served to this machine only\n", "text/plain; charset=utf-8")
            return True

        def do_GET(self):
            if self._foreign_host():
                return None
            url = urlsplit(self.path)
            path, query = url.path, parse_qs(url.query)
            if path == "/":
                rater, bad = self._rater(query)
                if bad:
                    return self._send(400, b"bad rater id (letters, digits, '_', '-', '.'; at most 64)\n",
                                      "text/plain; charset=utf-8")
                rater = rater or "r" + secrets.token_hex(6)
                cookie = f"{COOKIE}={rater}; Path=/; Max-Age=31536000; SameSite=Strict"
                return self._send(200, _page(rater), "text/html; charset=utf-8",
                                  [("Set-Cookie", cookie), ("Cache-Control", "no-store")])
            if path in PAGE_FILES:
                name, ctype = PAGE_FILES[path]
                return self._send(200, (ASSETS / name).read_bytes(), ctype, [("Cache-Control", "no-cache")])
            m = MEDIA_PATH.fullmatch(path)
            if m:
                f = srv.study.media_file(m.group(1))
                return self._media(f) if f is not None and f.is_file() else self._not_found()
            if path == "/api/next":
                rater, _ = self._rater(query)
                if rater is None:
                    return self._json(400, {"error": "no rater id"})
                with srv.lock:
                    return self._json(200, srv.next_item(rater))
            return self._not_found()

        def do_POST(self):
            if self._foreign_host():
                return None
            url = urlsplit(self.path)
            if url.path not in ("/api/answer", "/api/expertise"):
                return self._not_found()
            rater, _ = self._rater(parse_qs(url.query))
            if rater is None:
                return self._json(400, {"error": "no rater id"})
            try:
                n = int(self.headers.get("Content-Length", "0"))
            except ValueError:
                n = -1
            if not 0 < n <= MAX_BODY:
                return self._json(400, {"error": "a JSON body of at most 16 KB"})
            try:
                body = json.loads(self.rfile.read(n))
            except (ValueError, UnicodeDecodeError):
                body = None
            if not isinstance(body, dict):
                return self._json(400, {"error": "the body is not a JSON object"})
            status, out = (srv.answer if url.path == "/api/answer" else srv.set_expertise)(rater, body)
            return self._json(status, out)

        def _media(self, f: Path):
            size = f.stat().st_size
            ctype = mimetypes.guess_type(f.name)[0] or "application/octet-stream"
            extra = [("Accept-Ranges", "bytes"), ("Cache-Control", "private, max-age=3600")]
            rng = re.fullmatch(r"bytes=(\d*)-(\d*)", self.headers.get("Range", "").strip())
            if rng and (rng.group(1) or rng.group(2)):  # one byte range (video seeking)
                if rng.group(1):
                    start = int(rng.group(1))
                    end = min(int(rng.group(2)), size - 1) if rng.group(2) else size - 1
                else:
                    start, end = max(0, size - int(rng.group(2))), size - 1
                if start >= size or start > end:
                    return self._send(416, b"", ctype, [("Content-Range", f"bytes */{size}")])
                with open(f, "rb") as fh:
                    fh.seek(start)
                    data = fh.read(end - start + 1)
                return self._send(206, data, ctype, extra + [("Content-Range", f"bytes {start}-{end}/{size}")])
            return self._send(200, f.read_bytes(), ctype, extra)

    return Handler


__all__ = ["RateServer", "DEFAULT_HOST", "DEFAULT_PORT"]
