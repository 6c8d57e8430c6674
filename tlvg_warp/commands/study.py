"""`python -m tlvg_warp study STUDY.yaml`: configs x scenes x paintings, resumable, one ruler for every run,
the paper's Table 1 per scene, the ablation table, the speed-quality chart (eval/study.py has the format)."""
from __future__ import annotations

import os
from pathlib import Path

from ..errors import InputError


def add_arguments(p):
    p.add_argument("study", metavar="STUDY.yaml", help="the study (configs, scenes, paintings; see eval/study.py)")
    p.add_argument("--out", default=None, help="study folder (default: the YAML's out)")
    p.add_argument("--device", default=None, help="cpu | cuda | auto (default: the YAML's device)")
    p.add_argument("--iterations", type=int, default=None, help="override the YAML's iterations")
    p.add_argument("--vgg-weights", default=None, help="override the YAML's vgg_weights ('random': smoke runs)")
    p.add_argument("--judge", action="store_true", help="add the VLM panel (ours vs baseline) to the report")
    p.add_argument("--judge-url", default=None, help="OpenAI-compatible endpoint (default: YAML judge.base_url)")
    p.add_argument("--judge-models", default=None, help="comma-separated models (default: YAML judge.models)")
    p.add_argument("--api-key", default=None, help="judge key (default $OPENAI_API_KEY; never logged)")


def run(args) -> int:
    from ..eval.study import load_study, run_study

    st = load_study(args.study)
    if args.out:
        st.out = Path(args.out)
    if args.device:
        st.device = args.device
    if args.iterations is not None:
        if args.iterations < 1:
            raise InputError(f"--iterations must be >= 1, got {args.iterations}")
        st.iterations = args.iterations
    if args.vgg_weights is not None:
        st.vgg_weights = args.vgg_weights
    jc = None
    if args.judge:
        from ..eval.judge import preflight

        url = args.judge_url or st.judge.get("base_url")
        models = args.judge_models.split(",") if args.judge_models else list(st.judge.get("models") or [])
        if not url or not models:
            raise InputError("--judge needs an endpoint and models (--judge-url/--judge-models or the YAML's judge)",
                             args.study)
        if not st.ours or not st.baseline:
            raise InputError("--judge needs 'ours' and 'baseline' in the study", args.study)
        key = args.api_key or os.environ.get("OPENAI_API_KEY")
        preflight(url, key)
        jc = {"base_url": url, "models": models, "api_key": key, "max_views": st.judge.get("max_views")}
    res = run_study(st, jc)
    print(f"wrote {st.out / 'study.json'}, study.csv and study.html ({res['wall_s']} s)")
    failed = [k for k, v in res["status"].items() if v.startswith("failed")]
    if failed:
        print(f"failed runs: {', '.join(failed)}")
        return 1
    return 0
