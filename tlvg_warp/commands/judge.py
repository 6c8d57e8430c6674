"""`python -m tlvg_warp judge --a RUN_A --b RUN_B --models m1,m2`: the VLM-as-a-Judge panel (paper §4.3.2)."""
from __future__ import annotations

import os
import socket
import sys
from pathlib import Path
from urllib.parse import urlparse

from ..errors import InputError, one_line
from ..fileio import write_json

DEFAULT_BASE_URL = "https://api.openai.com/v1"


def add_arguments(p):
    p.add_argument("--a", required=True, metavar="RUN_A", help="run folder (renders/ + config.yaml) or folder of images; win rates are for this one")
    p.add_argument("--b", required=True, metavar="RUN_B", help="the other run (e.g. the baseline); images paired with --a by file name")
    p.add_argument("--models", required=True, help="comma-separated judge model names, e.g. gpt-4o,claude-3-5-sonnet")
    p.add_argument("--base-url", default=os.environ.get("OPENAI_BASE_URL", DEFAULT_BASE_URL),
                   help="OpenAI-compatible API root; requests go to {base-url}/chat/completions (default $OPENAI_BASE_URL or %(default)s)")
    p.add_argument("--api-key", default=None, help="bearer key (default $OPENAI_API_KEY; not needed for localhost)")
    p.add_argument("--style", default=None, help="the painting, when neither run folder names one")
    p.add_argument("--out", default=None, help="output folder for judge.json (default RUN_A/judge_vs_<RUN_B name>)")
    p.add_argument("--seed", type=int, default=0, help="seed of the A/B order (default %(default)s)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds per request (default %(default)s)")
    p.add_argument("--retries", type=int, default=3, help="retries per answer before it counts as invalid (default %(default)s)")
    p.add_argument("--backoff", type=float, default=2.0, help="first retry delay in seconds, doubling after (default %(default)s)")
    p.add_argument("--max-views", type=int, default=None, help="judge at most N views, evenly spaced")
    p.add_argument("--workers", type=int, default=4, help="concurrent requests (default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no per-request progress lines")


CONNECT_TIMEOUT_S = 10.0
LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")


def check_endpoint(base_url: str, key, timeout: float) -> None:
    """Stop before any request (and before judge.json is written) when the endpoint cannot work: not an http(s)
    URL, no key for a remote endpoint, or nothing accepting connections at its host and port. One line that
    names the endpoint (never the key)."""
    u = urlparse(base_url)
    if u.scheme not in ("http", "https") or not u.hostname:
        raise InputError(f"judge endpoint {base_url!r} is not an http(s) URL (e.g. {DEFAULT_BASE_URL})")
    try:
        port = u.port or (443 if u.scheme == "https" else 80)
    except ValueError:
        raise InputError(f"judge endpoint {base_url} has an invalid port") from None
    if not key and u.hostname not in LOCAL_HOSTS:
        raise InputError(f"no API key for the judge endpoint {base_url}: pass --api-key or set OPENAI_API_KEY; "
                         "nothing was sent")
    try:
        socket.create_connection((u.hostname, port), timeout=timeout).close()
    except OSError as e:
        raise InputError(f"judge endpoint {base_url} does not answer ({one_line(e.strerror or e)} at "
                         f"{u.hostname}:{port}); nothing was sent") from None


def run(args) -> int:
    # lazy: CLI startup
    from ..eval import judge
    for flag, v in (("--retries", args.retries), ("--timeout", args.timeout), ("--backoff", args.backoff)):
        if v < 0 or (flag == "--timeout" and v == 0):
            raise InputError(f"{flag} must be positive, got {v}")
    if args.max_views is not None and args.max_views < 1:
        raise InputError(f"--max-views must be at least 1, got {args.max_views}")
    judge.resolve_inputs(args.a, args.b, args.style, args.max_views)  # bad input fails before any request
    key = args.api_key or os.environ.get("OPENAI_API_KEY")
    check_endpoint(args.base_url, key, min(args.timeout, CONNECT_TIMEOUT_S))
    out = Path(args.out) if args.out else Path(args.a) / f"judge_vs_{Path(args.b).resolve().name}"
    result = judge.run_judge(args.a, args.b, args.models.split(","), args.base_url, key, style=args.style,
                             seed=args.seed, timeout=args.timeout, retries=args.retries, backoff=args.backoff,
                             max_views=args.max_views, workers=args.workers,
                             log=None if args.quiet else judge.stderr_log)
    write_json(out / "judge.json", result)
    print(judge.format_table(result))
    print(f"wrote {out / 'judge.json'}")
    if result["panel"]["valid"] == 0:
        print("error: no judge answer was usable (see records[].errors in judge.json)", file=sys.stderr)
        return 1
    return 0
