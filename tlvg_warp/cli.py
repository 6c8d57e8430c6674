"""`python -m tlvg_warp <command>`: each command lives in tlvg_warp/commands/<name>.py with
``add_arguments(parser)`` and ``run(args) -> int``. Bad input (InputError) exits 2 with one line."""
from __future__ import annotations

import argparse
import importlib
import sys

from .errors import InputError

COMMANDS = {
    "stylize": "flow-guided stylization of a 3DGS scene (the default demo when given nothing)",
    "reconstruct": "fit a 3DGS scene to posed photos",
    "evaluate": "metrics for a stylization run (and optionally a second one to compare)",
    "judge": "VLM-as-a-judge pairwise comparison of two runs",
    "bench": "speed against accuracy (`bench raster` for the rasterizer alone)",
    "stability": "drive the pipeline into the places where stylization breaks",
}


def _load(name):
    return importlib.import_module(f"tlvg_warp.commands.{name}")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(prog="python -m tlvg_warp", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    available = {}
    for name, help_ in COMMANDS.items():
        try:
            mod = _load(name)
        except ModuleNotFoundError as e:
            if e.name != f"tlvg_warp.commands.{name}":
                raise
            continue
        p = sub.add_parser(name, help=help_, description=help_)
        mod.add_arguments(p)
        available[name] = mod
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(available[args.command].run(args) or 0)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
