"""One module per CLI command: add_arguments(parser), run(args) -> int.

cli.py imports every command module to build its parser, so a command imports the library it runs inside its
functions ("lazy: CLI startup"): ``--help`` and a bad flag stay fast."""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError

KEEP_CHECKPOINT_HELP = ("keep checkpoint.pt after the run finishes (to extend it later with --resume); by default it "
                        "is removed once the outputs are written. A run that stops early (Ctrl-C, divergence, a "
                        "kill) always keeps it")


def check_resumable(run) -> None:
    """--resume of a folder whose run finished (its outputs are there) without --keep-checkpoint: one line that
    says why there is nothing to resume from."""
    p = Path(run)
    if p.is_dir() and not (p / "checkpoint.pt").exists() and (p / "metrics.json").is_file():
        raise InputError("this run finished and its checkpoint.pt was removed, so it cannot be resumed or extended "
                         "(run with --keep-checkpoint to keep it)", p)


def peak_memory_note(metrics: dict) -> str:
    """The run's last line's peak GPU memory clause, from metrics.json's ``peak_gpu_mib``; empty on the CPU."""
    mib = metrics.get("peak_gpu_mib")
    return f", peak GPU memory {mib / 1024:.2f} GiB" if mib else ""
