"""The CUDA warm-up of `python -m tlvg_warp` (tlvg_warp/warmup.py): which command lines start it, that it does
nothing without a driver, and that the package imports without torch so that the warm-up can overlap that import;
the end of a GPU command without the interpreter's teardown (warmup.leave); Warp's runtime started once when two
threads' first uses meet (launch.init_warp)."""
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
    # the warm-up would have started (the threads' names are printed as they start: a GPU command ends by os._exit)
    code = ("import runpy, sys, threading\n"
            "start = threading.Thread.start\n"
            "threading.Thread.start = lambda self: (print(self.name, flush=True), start(self))[1]\n"
            f"sys.argv = ['tlvg_warp', 'stylize', '--no-such-flag', *{flags!r}]\n"
            "runpy.run_module('tlvg_warp', run_name='__main__')\n")
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert r.returncode == 2, r.stderr
    assert ("cuda-warmup" in r.stdout.split()) is started


def test_a_gpu_command_ends_without_the_teardown_and_keeps_its_output(tmp_path):
    # an exit handler stands for the interpreter's teardown: it runs after `evaluate` and not after `stylize`, whose
    # buffered output (stdout is a pipe here) must still arrive, with main's return code
    code = ("import atexit, sys\nfrom tlvg_warp.warmup import leave\n"
            "atexit.register(lambda: open(sys.argv[1], 'w').close())\n"
            "print('written', end='')\nleave(3, [sys.argv[2]])\n")
    env = {k: v for k, v in os.environ.items() if k not in ("CUDA_VISIBLE_DEVICES", "PYTHONUNBUFFERED", "WORLD_SIZE")}
    for command, teardown in (("stylize", False), ("evaluate", True)):
        marker = tmp_path / command
        r = subprocess.run([sys.executable, "-c", code, str(marker), command], capture_output=True, text=True, env=env)
        assert (r.returncode, r.stdout) == (3, "written"), (command, r.stderr)
        assert marker.exists() is teardown, command


def test_a_profiled_gpu_command_ends_normally_so_that_the_profile_is_written(tmp_path):
    script = tmp_path / "command.py"
    script.write_text("from tlvg_warp.warmup import leave\nleave(0, ['stylize'])\n")
    prof = tmp_path / "out.prof"
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    r = subprocess.run([sys.executable, "-m", "cProfile", "-o", str(prof), str(script)], capture_output=True,
                       text=True, env=env)
    assert r.returncode == 0, r.stderr
    import pstats
    assert any(name == "leave" for _, _, name in pstats.Stats(str(prof)).stats)


def test_leave_maps_main_results_to_exit_codes(monkeypatch):
    codes = []

    class Exited(Exception):
        pass

    def record(code):
        codes.append(code)
        raise Exited
    monkeypatch.setattr(warmup.os, "_exit", record)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    for result in (None, 0, 2):
        with pytest.raises(Exited):
            warmup.leave(result, ["stylize"])
    assert codes == [0, 0, 2]
    with pytest.raises(SystemExit) as e:
        warmup.leave(2, ["evaluate"])
    assert e.value.code == 2
    monkeypatch.setenv("WORLD_SIZE", "2")  # a torchrun rank: torch's teardown leaves its process group
    with pytest.raises(SystemExit) as e:
        warmup.leave(0, ["stylize"])
    assert e.value.code == 0 and codes == [0, 0, 2]


def test_two_first_uses_start_warp_once(monkeypatch):
    # Warp's runtime is up in this process already: a slow stand-in for wp.init shows whether a second thread's
    # init_warp during the first one's waits for it (one start, finished when it returns) or starts Warp again
    import threading
    import time

    from tlvg_warp import launch
    calls, done = [], threading.Event()

    def slow_init():
        calls.append(threading.current_thread().name)
        time.sleep(0.3)
        done.set()
    monkeypatch.setattr(launch.wp, "init", slow_init)
    monkeypatch.setattr(launch, "cuda_driver_present", lambda: True)
    monkeypatch.setattr(launch, "_initialized", False)
    t = threading.Thread(target=launch.init_warp, name="first")
    t.start()
    while not calls:
        time.sleep(0.005)
    launch.init_warp()
    assert done.is_set() and calls == ["first"]
    t.join(5)
    launch.init_warp()
    assert calls == ["first"]
