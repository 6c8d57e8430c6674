"""`python -m tlvg_warp study STUDY.yaml`: configs x scenes x paintings, resumable, one ruler for every run,
the paper's Table 1 per scene, the ablation table, the speed-quality chart (eval/study.py has the format).

Under `torchrun --nproc-per-node N [--nnodes M ...] -m tlvg_warp study STUDY.yaml` the jobs are spread over the
ranks (eval/study.py: run_study): each rank runs whole jobs on its own GPU (CUDA_VISIBLE_DEVICES narrowed to
its LOCAL_RANK's GPU), the ranks talk over gloo only (job claims go through files in the study folder, which
must be on a filesystem every machine shares), and the main rank writes the table."""
from __future__ import annotations

import os
from pathlib import Path

import torch

from ..errors import InputError


def add_arguments(p):
    p.add_argument("study", metavar="STUDY.yaml", help="the study (configs, scenes, paintings; see eval/study.py)")
    p.add_argument("--out", default=None, help="study folder (default: the YAML's out)")
    p.add_argument("--device", default=None, help="cpu | cuda | auto (default: the YAML's device)")
    p.add_argument("--iterations", type=int, default=None, help="force this many steps on every config (default: "
                   "the YAML's iterations; null there: each config's own schedule)")
    p.add_argument("--seeds", type=int, default=None, help="stylizations per (scene, painting, config) (default: "
                   "the YAML's seeds, else 3)")
    p.add_argument("--only-configs", default=None, metavar="A,B",
                   help="run and tabulate only these configs of the YAML (comma-separated), e.g. tlvg,abcgs")
    p.add_argument("--vgg-weights", default=None, metavar="PATH|hed|random",
                   help="override the YAML's vgg_weights: a path, 'hed' or 'random' (smoke runs)")
    p.add_argument("--judge", action="store_true", help="add the VLM panel (ours vs baseline) to the report")
    p.add_argument("--judge-url", default=None, help="OpenAI-compatible endpoint (default: YAML judge.base_url)")
    p.add_argument("--judge-models", default=None, help="comma-separated models (default: YAML judge.models)")
    p.add_argument("--api-key", default=None, help="judge key (default $OPENAI_API_KEY; never logged)")


def run(args) -> int:
    # lazy: CLI startup
    from ..distributed import isolate_local_gpu
    from ..eval.study import load_study, run_study

    isolate_local_gpu()  # before anything touches CUDA: this rank sees its own GPU only (under torchrun)
    st = load_study(args.study)
    if args.out:
        st.out = Path(args.out)
    if args.device:
        st.device = args.device
    if args.iterations is not None:
        if args.iterations < 1:
            raise InputError(f"--iterations must be >= 1, got {args.iterations}")
        st.iterations = args.iterations
    if args.seeds is not None:
        if args.seeds < 1:
            raise InputError(f"--seeds must be >= 1, got {args.seeds}")
        st.seeds = args.seeds
    if args.only_configs:
        # lazy: CLI startup
        from ..eval.study import only_configs

        only_configs(st, [c.strip() for c in args.only_configs.split(",") if c.strip()])
    if args.vgg_weights is not None:
        st.vgg_weights = args.vgg_weights
    jc = None
    if args.judge:
        # lazy: CLI startup
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
    # lazy: CLI startup
    from ..distributed import Dist
    from ..eval.study import resolve_device

    dist = Dist.from_env("cpu")  # gloo: the ranks exchange job claims and results, never tensors
    if dist.world > 1 and resolve_device(st.device).startswith("cuda"):
        if not torch.cuda.is_available():
            raise InputError(f"rank {dist.rank}: device {st.device!r} but no GPU for LOCAL_RANK {dist.local_rank} "
                             "(launch at most one process per GPU: --nproc-per-node <= GPUs)")
    try:
        res = run_study(st, jc, dist=dist)
    finally:
        dist.shutdown()
    if res is None:  # not the main rank: the main rank reports
        return 0
    print(f"wrote {st.out / 'study.json'}, study.csv and study.html ({res['wall_s']} s)"
          + (f" with {dist.world} ranks" if dist.world > 1 else ""))
    failed = [k for k, v in res["status"].items() if v.startswith("failed")]
    if failed:
        print(f"failed runs: {', '.join(failed)}")
        return 1
    return 0
