"""`python -m tlvg_warp rate RUN_A RUN_B [RUN_C RUN_D ...] --out STUDY_DIR`: the user study in the browser
(blind pairwise rating of runs on Flow Alignment, Painterly Materiality and Aesthetic Preference);
`rate --report STUDY_DIR`: the win rates with 95% intervals, split by expertise. See docs/rate.md."""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..eval import rate
from ..rate_server import DEFAULT_HOST, DEFAULT_PORT, RateServer
from .view import serve_forever


def add_arguments(p):
    p.epilog = ("Pairs of run folders: the first of each pair is A (e.g. ours), the second B (e.g. the baseline); "
                "every answer goes to STUDY_DIR/answers.jsonl at once. Send raters the printed address (with "
                "--host 0.0.0.0 for other machines); each rater may add ?rater=NAME. Then: rate --report "
                "STUDY_DIR.")
    p.add_argument("runs", nargs="*", metavar="RUN",
                   help="run folders in pairs: RUN_A RUN_B [RUN_C RUN_D ...] (their renders/ of the same views)")
    p.add_argument("--out", default=None, metavar="STUDY_DIR",
                   help="the study folder: study.json, answers.jsonl (the same folder again continues the study)")
    p.add_argument("--report", default=None, metavar="STUDY_DIR",
                   help="no server: print the win rates of a study, write STUDY_DIR/report.md and report.png")
    p.add_argument("--media", default="views", choices=["views", "orbit", "both"],
                   help="what raters compare: the renders of each view (default), the two orbit.mp4 videos, or both")
    p.add_argument("--max-views", type=int, default=None, metavar="N",
                   help="at most N views per pair, evenly spaced (default: every view)")
    p.add_argument("--style", default=None, metavar="IMAGE",
                   help="the painting to show (default: the run's style.png or its config.yaml style)")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the order and sides of the items (default: random, kept in study.json)")
    p.add_argument("--host", default=DEFAULT_HOST,
                   help=f"address to bind (default {DEFAULT_HOST}: this machine only; 0.0.0.0 for the network)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT,
                   help=f"port (default {DEFAULT_PORT}; a busy port moves to the next free one)")


def run(args) -> int:
    if args.report is not None:
        if args.runs or args.out is not None:
            raise InputError("--report STUDY_DIR takes no run folders and no --out")
        s = rate.write_report(args.report)
        print(rate.format_table(s))
        print()
        for line in rate.verdict_lines(s):
            print(line)
        folder = Path(args.report)
        print(f"wrote {folder / rate.REPORT_MD} and {folder / rate.REPORT_PNG}")
        return 0
    if args.out is None:
        raise InputError("rate needs --out STUDY_DIR (or --report STUDY_DIR)")
    if args.max_views is not None and args.max_views < 1:
        raise InputError(f"--max-views must be at least 1, not {args.max_views}")
    study = rate.build_study(args.runs, args.out, media=args.media, max_views=args.max_views, style=args.style,
                             seed=args.seed)
    srv = RateServer(study, args.host, args.port)
    answers, _, _ = rate.read_answers(study.folder)
    lines = [f"rate: {srv.address}/  ({len(study.pairs)} pair{'s' if len(study.pairs) != 1 else ''}, "
             f"{len(study.items)} items per rater; {len(answers)} answers so far in "
             f"{Path(study.folder) / rate.ANSWERS_FILE})"]
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        lines.append(f"  bound to {args.host}: anyone who can reach this machine can open the page")
    lines.append(f"  report: python -m tlvg_warp rate --report {study.folder}")
    return serve_forever(srv, lines=lines)
