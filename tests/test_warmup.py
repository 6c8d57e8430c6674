"""The CUDA warm-up of `python -m tlvg_warp` (tlvg_warp/warmup.py): which command lines start it, that it does
nothing without a driver, and that the package imports without torch so that the warm-up can overlap that import."""
import os
import subprocess
import sys

import pytest

from tlvg_warp import warmup


@pytest.mark.parametrize("argv, expected", [
    (["stylize"], True),
    (["stylize", "--scene", "a.ply", "--device", "cuda"], True),
    (["reconstruct", "data/fern"], True),
    (["stylize", "--device", "cpu"], False),
    (["stylize", "--device=cpu"], False),
    (["stylize", "--set", "device=cpu"], False),
    (["stylize", "--help"], False),
    (["evaluate", "run_a", "run_b"], False),
    (["view", "run_a"], False),
    ([], False),
])
def test_which_command_lines_warm_cuda(argv, expected, monkeypatch):
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert warmup.wants_gpu(argv) is expected


def test_no_visible_device_means_no_warm_up(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert not warmup.wants_gpu(["stylize"])
    assert warmup.start_cuda_warmup(["stylize"]) is None


def test_without_a_driver_the_thread_ends_quietly(monkeypatch):
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.setattr(warmup, "_LIBCUDA", "libcuda-that-is-not-here.so")
    assert warmup.retain_primary_context(0) is False
    t = warmup.start_cuda_warmup(["stylize"])
    assert t is not None
    t.join(10)
    assert not t.is_alive()


def test_the_package_imports_without_torch():
    # the warm-up overlaps the import of torch only if `python -m tlvg_warp` reaches it before torch comes in
    code = ("import sys, tlvg_warp, tlvg_warp.cli, tlvg_warp.warmup; print('torch' in sys.modules); "
            "from tlvg_warp import Camera; print(Camera.__module__, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "tlvg_warp.types", "True"]


@pytest.mark.parametrize("flags, started", [([], True), (["--device", "cpu"], False)])
def test_python_m_tlvg_warp_starts_it_before_the_command(flags, started):
    # `python -m tlvg_warp` (__main__.py) is where the warm-up is wired in: a bad flag ends the command at once, after
    # the warm-up would have started
    code = ("import runpy, sys, threading\n"
            "names, start = [], threading.Thread.start\n"
            "threading.Thread.start = lambda self: (names.append(self.name), start(self))[1]\n"
            f"sys.argv = ['tlvg_warp', 'stylize', '--no-such-flag', *{flags!r}]\n"
            "try:\n    runpy.run_module('tlvg_warp', run_name='__main__')\nexcept SystemExit as e:\n    code = e.code\n"
            "print(code, 'cuda-warmup' in names)")
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    assert out.split() == ["2", str(started)]
