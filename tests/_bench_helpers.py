"""Benchmark scripts (benchmarks/*.py are not a package) loaded by path for the tests of their pure parts."""
import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_benchmark(filename: str):
    """benchmarks/``filename`` as a module, registered in sys.modules only while it runs (dataclasses look their
    module up there), so loading it leaves no name behind."""
    spec = importlib.util.spec_from_file_location(f"{Path(filename).stem}_bench", BENCHMARKS / filename)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.modules.pop(spec.name, None)
    return mod
