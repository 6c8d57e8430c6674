"""Warp's initialization on a machine without a CUDA driver prints no driver warning, and passes on anything else
Warp writes to stderr."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _stderr_of(code: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("TLVG_WARP_VERBOSE", None)
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    return p.stderr


def test_no_driver_warning_from_init_warp():
    """Without a loadable driver, a bare wp.init() prints Warp's warning (the oracle: the thing to hide is there)
    while init_warp() prints nothing about it; with a driver neither prints it."""
    from tlvg_warp.launch import NO_DRIVER, cuda_driver_present

    ours = _stderr_of("from tlvg_warp.launch import init_warp; init_warp()")
    assert NO_DRIVER not in ours
    if cuda_driver_present():
        pytest.skip("this machine has a CUDA driver: Warp prints no driver warning to hide")
    bare = _stderr_of("import warp as wp; wp.config.quiet = True; wp.init()")
    assert NO_DRIVER in bare


def test_without_lines_drops_only_the_named_line(capfd):
    """C-level writes to descriptor 2 are captured; lines with the text are dropped, the others passed on."""
    from tlvg_warp.launch import without_lines

    def noisy():
        os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU off.\n")
        os.write(2, b"some other problem\n")
        return 7

    assert without_lines(noisy, "Could not find or load the NVIDIA CUDA driver") == 7
    err = capfd.readouterr().err
    assert "some other problem" in err and "NVIDIA CUDA driver" not in err


def test_importing_every_module_leaves_warp_uninitialized():
    """Kernels are built by cached factories on first use, so importing any module of the package (kernels/
    included) neither initializes Warp nor builds a kernel."""
    code = ("import importlib, sys\n"
            f"names = {_module_names()!r}\n"
            "for n in names:\n"
            "    importlib.import_module(n)\n"
            "import warp._src.context as c\n"
            "assert c.runtime is None, 'Warp was initialized'\n"
            "print(len(names))\n")
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300, cwd=REPO)
    assert p.returncode == 0, p.stderr
    assert int(p.stdout.split()[-1]) > 60


def _module_names() -> list[str]:
    names = []
    for p in sorted((REPO / "tlvg_warp").rglob("*.py")):
        parts = p.relative_to(REPO).with_suffix("").parts
        if "__pycache__" in parts or parts[-1] == "__main__":  # (__main__ runs the command line)
            continue
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    names += ["tlvg_warp.kernels" + ("" if p.stem == "__init__" else "." + p.stem)
              for p in sorted((REPO / "kernels").glob("*.py"))]
    return names
