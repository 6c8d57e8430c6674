"""Files a user points at are data, never code. A crafted checkpoint.pt whose pickle would run a shell command
(``os.system("touch MARKER")`` on unpickling) is put into a real run folder and handed to every command that
opens a run (evaluate, view, stylize --resume, reconstruct --resume); a crafted reference cache (an npz holding
such an object) to evaluate; crafted VGG weights to stylize. Each must end in one line, exit 2, and the marker
file must never appear (the oracle: the command did not run). A checkpoint written by the current code resumes,
and its pickle names nothing but torch's own rebuilders (read with pickletools, which executes nothing).

The viewer's server binds 127.0.0.1 by default and serves only its own client files: requests for ``../``,
percent-encoded ``..`` and absolute paths get 404 and none of /etc/passwd, while its index page is served."""
from __future__ import annotations

import argparse
import http.client
import os
import pickle
import pickletools
import shutil
import socket
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from test_malformed_inputs import S, valid  # noqa: F401 (the fixture of small valid inputs)
from tlvg_warp.cli import main
from _io_helpers import run_cli

ITERS = 4


def _has_flag(command: str, flag: str) -> bool:
    import importlib

    parser = argparse.ArgumentParser()
    importlib.import_module(f"tlvg_warp.commands.{command}").add_arguments(parser)
    return any(flag in a.option_strings for a in parser._actions)


KEEP = [f for f in ("--keep-checkpoint",) if _has_flag("stylize", f)]  # a finished run may drop its checkpoint


class _Command:
    """Unpickling this runs ``touch PATH`` (what a malicious run folder would do)."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return os.system, (f"touch '{self.marker}'",)


def _stylize_argv(valid, out, *extra):
    return ["stylize", "--scene", str(valid / S), "--data", str(valid / "colmap_bin"), "--out", str(out),
            "--vgg-weights", "random", "--device", "cpu", "--quiet", "--iterations", str(ITERS),
            "--set", "orbit_frames=1", "--set", "comparison_views=1", *KEEP, *extra]


@pytest.fixture(scope="module")
def run_dir(valid, tmp_path_factory):
    """A finished stylization run of the current code (checkpoint.pt, renders, cameras.json, ...)."""
    out = tmp_path_factory.mktemp("runs") / "run"
    assert main(_stylize_argv(valid, out)) == 0
    return out


@pytest.fixture(scope="module")
def rec_dir(valid, tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "rec"
    keep = [f for f in ("--keep-checkpoint",) if _has_flag("reconstruct", f)]
    assert main(["reconstruct", str(valid / "colmap_bin"), "--out", str(out), "--iterations", "4",
                 "--device", "cpu", "--quiet", *keep]) == 0
    return out


def _globals_named(path: Path) -> set:
    """The module.name of every object the checkpoint's pickle imports (opcode scan; nothing is executed)."""
    with zipfile.ZipFile(path) as z:
        data = z.read(next(n for n in z.namelist() if n.endswith("data.pkl")))
    names, strings = set(), []
    for op, arg, _ in pickletools.genops(data):
        if op.name == "GLOBAL":
            names.add(arg.replace(" ", "."))
        elif op.name == "STACK_GLOBAL":
            names.add(f"{strings[-2]}.{strings[-1]}")
        elif isinstance(arg, str):
            strings.append(arg)
    return names


def _craft(ck: Path, marker: Path, how: str) -> None:
    """Replace ``ck`` by a checkpoint that keeps the real one's keys (so only its code can make it fail) plus an
    object whose unpickling runs a command: written by torch.save (zip) or as a bare pickle."""
    real = torch.load(ck, map_location="cpu", weights_only=True)
    real["note"] = _Command(marker)
    real["sources"] = dict(real.get("sources") or {}, extra=_Command(marker))
    if how == "zip":
        torch.save(real, ck)
    else:
        with open(ck, "wb") as f:
            pickle.dump(real, f, protocol=4)




def _one_line_refusal(rc, err, culprit):
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("[evaluate")]  # evaluate's progress lines
    assert rc == 2, (rc, err)
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert str(culprit) in lines[0], (culprit, lines[0])


def test_checkpoint_of_current_code_is_plain_data(run_dir, rec_dir):
    for ck in (run_dir / "checkpoint.pt", rec_dir / "checkpoint.pt"):
        names = _globals_named(ck)
        assert names, "the scan must see torch's tensor rebuilders"
        assert all(n.split(".")[0] in ("torch", "collections") for n in names), names
        torch.load(ck, map_location="cpu", weights_only=True)  # torch's data-only loader accepts it


def test_checkpoint_of_current_code_resumes(valid, run_dir, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    rc, err = run_cli(["stylize", "--resume", str(run), "--iterations", str(ITERS + 2), "--quiet", *KEEP], capsys)
    assert rc == 0, err
    ck = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert ck["iteration"] == ITERS + 2


@pytest.mark.parametrize("how", ["zip", "pickle"])
@pytest.mark.parametrize("command", ["evaluate", "view", "resume", "reconstruct_resume"])
def test_crafted_checkpoint_never_runs(valid, run_dir, rec_dir, tmp_path, capsys, monkeypatch, command, how):
    src = rec_dir if command == "reconstruct_resume" else run_dir
    run = tmp_path / "shared run"
    shutil.copytree(src, run)
    (run / "sources.json").unlink(missing_ok=True)  # a run written before there was one: read from the checkpoint
    marker = tmp_path / "MARKER"
    _craft(run / "checkpoint.pt", marker, how)
    before = (run / "checkpoint.pt").read_bytes()
    if command == "view":  # the server would block: stop right after loading (a refusal never gets there)
        import tlvg_warp.commands.view as view

        monkeypatch.setattr(view, "open_viewer", lambda *a, **k: None)
        monkeypatch.setattr(view, "serve_forever", lambda *a, **k: 0)
    argv = {"evaluate": ["evaluate", str(run), "--cache", str(tmp_path / "cache"), "--device", "cpu"],
            "view": ["view", str(run)],
            "resume": ["stylize", "--resume", str(run), "--iterations", str(ITERS + 2), "--quiet"],
            "reconstruct_resume": ["reconstruct", str(valid / "colmap_bin"), "--resume", str(run), "--iterations", "6",
                                   "--quiet"]}[command]
    rc, err = run_cli(argv, capsys)
    assert not marker.exists(), "the checkpoint's code ran"
    _one_line_refusal(rc, err, run / "checkpoint.pt")
    assert "refused" in err
    assert (run / "checkpoint.pt").read_bytes() == before


def test_unrestricted_unpickling_of_the_crafted_file_would_run_it(run_dir, tmp_path):
    """The control: the crafted checkpoint is really dangerous (so the refusals above refused something)."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    marker = tmp_path / "MARKER"
    _craft(run / "checkpoint.pt", marker, "zip")
    torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert marker.exists()


def test_checkpoint_with_numpy_objects_is_refused_with_the_reason(run_dir, tmp_path, capsys):
    """A checkpoint holding numpy arrays (not plain data: numpy's reconstructor is a code path) is refused and
    the line names what it holds; nothing in it is constructed."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    ck = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=True)
    ck["rng_state"] = np.arange(4)
    torch.save(ck, run / "checkpoint.pt")
    rc, err = run_cli(["stylize", "--resume", str(run), "--iterations", str(ITERS + 2), "--quiet"], capsys)
    _one_line_refusal(rc, err, run / "checkpoint.pt")
    assert "numpy" in err and "refused" in err


def test_crafted_reference_cache_never_runs(run_dir, tmp_path, capsys):
    """evaluate writes its reference cache on the first call; a cache entry replaced by an npz with a pickled
    object is refused (one line naming it) on the next, and the object is never unpickled."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    cache = tmp_path / "cache"
    argv = ["evaluate", str(run), "--cache", str(cache), "--device", "cpu", "--out", str(tmp_path / "ev")]
    rc, err = run_cli(argv, capsys)
    assert rc == 0, err
    entries = list(cache.glob("*.npz"))
    assert len(entries) == 1
    marker = tmp_path / "MARKER"
    with np.load(entries[0]) as z:
        arrs = dict(z)
    arrs["color0"] = np.array([_Command(marker)], dtype=object)
    with open(entries[0], "wb") as f:
        np.savez(f, **arrs)
    rc, err = run_cli(argv, capsys)
    assert not marker.exists()
    _one_line_refusal(rc, err, entries[0])
    with np.load(entries[0], allow_pickle=True) as z:  # the control: unrestricted loading would run it
        z["color0"]
    assert marker.exists()


def test_crafted_vgg_weights_neverrun_cli(valid, tmp_path, capsys):
    marker = tmp_path / "MARKER"
    w = tmp_path / "vgg16.pth"
    torch.save({"features.0.weight": torch.zeros(64, 3, 3, 3), "x": _Command(marker)}, w)
    out = tmp_path / "out"
    argv = _stylize_argv(valid, out)
    argv[argv.index("random")] = str(w)
    rc, err = run_cli(argv, capsys)
    assert not marker.exists()
    _one_line_refusal(rc, err, w)
    assert not out.exists()


# --- the viewer's server --------------------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(port: int, path: str) -> tuple[int, bytes]:
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    c.putrequest("GET", path, skip_host=False, skip_accept_encoding=True)  # the path goes out exactly as written
    c.endheaders()
    r = c.getresponse()
    body = r.read()
    c.close()
    return r.status, body


def _own_address() -> str | None:
    """An address of this machine other than loopback, when it has one."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))  # no packet is sent (UDP connect only picks the route)
            a = s.getsockname()[0]
        return None if a.startswith("127.") else a
    except OSError:
        return None


def test_viewer_binds_loopback_and_serves_only_its_files():
    pytest.importorskip("viser", reason="the viewer needs viser")
    from tlvg_warp.commands import view
    from tlvg_warp.viewer import DEFAULT_HOST, SceneViewer

    parser = argparse.ArgumentParser()
    view.add_arguments(parser)
    assert parser.parse_args(["x"]).host == "127.0.0.1" == DEFAULT_HOST
    port = _free_port()
    v = SceneViewer(port=port)
    try:
        port = v.server.get_port()
        assert v.server.get_host() == "127.0.0.1"
        status, body = _get(port, "/")
        assert status == 200 and b"<html" in body.lower()  # the control: its own page is served
        secret = Path("/etc/passwd").read_bytes()[:16] if Path("/etc/passwd").is_file() else b"root:"
        for path in ("/../../etc/passwd", "/../../../../../../etc/passwd", "/%2e%2e/%2e%2e/etc/passwd",
                     "/%2E%2E%2F%2E%2E%2Fetc%2Fpasswd", "/..%2f..%2f..%2fetc%2fpasswd", "//etc/passwd",
                     "/%2Fetc%2Fpasswd", "/etc/passwd", "/..\\..\\etc\\passwd", "/assets/../../../etc/passwd",
                     f"/{Path(__file__).resolve()}", "/../" + Path(__file__).name):
            status, body = _get(port, path)
            assert status == 404, (path, status)
            assert secret not in body and b"import" not in body, path
        addr = _own_address()
        if addr is not None:  # bound to loopback: other machines cannot connect
            with pytest.raises(OSError):
                socket.create_connection((addr, port), timeout=2).close()
    finally:
        v.stop()


# --- judge checks its inputs before the network --------------------------------------------------------------
def _judge_inputs(root: Path):
    import cv2

    for r in ("a", "b"):
        (root / r / "renders").mkdir(parents=True)
        for i in range(3):
            assert cv2.imwrite(str(root / r / "renders" / f"view_{i:03d}.png"),
                               np.full((24, 32, 3), 40 * i + (r == "b") * 20, np.uint8))
    assert cv2.imwrite(str(root / "painting.png"), np.full((64, 64, 3), 90, np.uint8))


@pytest.mark.parametrize("corrupt", ["a/renders/view_001.png", "b/renders/view_002.png", "painting.png"])
def test_judge_names_a_corrupt_input_before_contacting_the_endpoint(tmp_path, capsys, corrupt):
    """A listening socket stands for the endpoint: with a corrupt render (cut short) or painting, judge ends in one
    line naming that file and the socket never sees a connection; with the file intact the endpoint is reached
    (the control: the socket does see one)."""
    _judge_inputs(tmp_path)
    bad = tmp_path / corrupt
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) * 2 // 3])
    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen(8)
        srv.setblocking(False)
        url = f"http://127.0.0.1:{srv.getsockname()[1]}/v1"
        argv = ["judge", "--a", str(tmp_path / "a"), "--b", str(tmp_path / "b"), "--models", "m", "--base-url", url,
                "--style", str(tmp_path / "painting.png"), "--out", str(tmp_path / "judged"), "--quiet",
                "--retries", "0", "--timeout", "2"]
        rc, err = run_cli(argv, capsys)
        _one_line_refusal(rc, err, bad)
        with pytest.raises(BlockingIOError):
            srv.accept()  # nothing connected
        assert not (tmp_path / "judged").exists()
        bad.write_bytes(data)
        run_cli(argv, capsys)  # the endpoint answers nothing useful; what matters is that it was contacted
        conn, _ = srv.accept()
        conn.close()


def test_judge_with_a_corrupt_render_and_an_unreachable_endpoint_names_the_render(tmp_path, capsys):
    _judge_inputs(tmp_path)
    bad = tmp_path / "a" / "renders" / "view_000.png"
    bad.write_bytes(bad.read_bytes()[:-30])
    with socket.socket() as s:  # a port with nothing listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    rc, err = run_cli(["judge", "--a", str(tmp_path / "a"), "--b", str(tmp_path / "b"), "--models", "m",
                    "--base-url", f"http://127.0.0.1:{port}/v1", "--style", str(tmp_path / "painting.png"),
                    "--quiet"], capsys)
    _one_line_refusal(rc, err, bad)
    assert "does not answer" not in err
