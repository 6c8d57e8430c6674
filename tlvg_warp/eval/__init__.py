"""Evaluation (SPEC §4, paper §4.3): the VLM judge panel and the speed–quality (Pareto) chart."""
import os
from pathlib import Path

# What the command line needs when it builds its parser (help texts and defaults), kept here so that building it
# loads none of the evaluation (commands/evaluate.py imports eval/engine.py, which loads OpenCV and Warp, in run).
MAX_REPORT_VIEWS = 4  # views shown as thumbnails (evenly spaced)
CPU_MAX_VIEWS = 12  # evaluate's default view count on a CPU (a demo run's 24 views took 38 s there, 12 take under 30)
CAM_TOL = 1e-4  # cameras.json round trip (float32 positions): runs of the same views agree far closer
DEFAULT_EVAL_HEIGHT = 256  # style/content size (the style loss's working height, SPEC §3)
MIN_EVAL_HEIGHT = 64  # smaller views are enlarged to this (VGG's relu4 needs a few cells)


def default_cache() -> Path:
    """Where `evaluate` keeps the references it built (TLVG_EVAL_CACHE overrides)."""
    return Path(os.environ.get("TLVG_EVAL_CACHE", Path.home() / ".cache" / "tlvg_warp" / "eval_refs"))
