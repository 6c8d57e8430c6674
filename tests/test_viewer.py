"""The browser viewer: the Gaussians -> viser conversion against an independent computation
(scipy's Rotation, numpy), what `view` loads from a run folder / scene file, the live hook of run_stylize, and
a headless Chromium that loads the page from a viewer the test starts and checks the canvas is drawn:
the splat colour covers the view, an empty scene shows none of it, and the dropdown's other scene replaces it.
Chromium is Debian's `chromium` (CI installs it in .ci/run); without it the browser tests skip."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("viser", reason="the viewer needs viser: pip install -e '.[viewer]'")

from tlvg_warp.commands.view import load_view, open_viewer  # noqa: E402
from tlvg_warp.io.ply import save_ply  # noqa: E402
from tlvg_warp.types import SH_C0, Camera, Gaussians  # noqa: E402
from tlvg_warp.viewer import SceneViewer, camera_pose, splat_arrays  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _browser import Chromium, find_chromium  # noqa: E402

CONV_TOL = 1e-5  # float32 outputs of a float64 computation, relative to the largest entry
needs_chromium = pytest.mark.skipif(find_chromium() is None,
                                    reason="no chromium on PATH (apt-get install -y chromium; CI installs it)")
SHOT_W, SHOT_H = 480, 360  # small: SwiftShader renders every pixel on the CPU
RENDER_TIMEOUT = 40.0  # seconds for the page to load, connect and draw (about 10 s on 2 cores)
RED, BLUE = (1.0, 0.05, 0.05), (0.05, 0.1, 1.0)
COVER_MIN = 0.05  # the splat colour covers at least this fraction of the view when drawn
COVER_EMPTY_MAX = 0.002  # ... and at most this in an empty scene (the GUI panel has no saturated red or blue)


def _random_gaussians(n=500, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=dtype) * 3.0  # not unit: the conversion normalizes
    return Gaussians(torch.randn(n, 3, generator=g, dtype=dtype), q,
                     torch.randn(n, 3, generator=g, dtype=dtype) * 0.8 - 1.0,
                     torch.randn(n, generator=g, dtype=dtype) * 3.0,
                     torch.randn(n, 4, 3, generator=g, dtype=dtype) * 2.0)


# --- conversion ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_conversion_matches_scipy_rotation_and_numpy(dtype):
    from scipy.spatial.transform import Rotation

    g = _random_gaussians(dtype=dtype)
    a = splat_arrays(g)
    q = g.quats.double().numpy()
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy: x, y, z, w (it normalizes too)
    s = np.exp(g.log_scales.double().numpy())
    cov = np.einsum("nij,nj,nkj->nik", R, s ** 2, R)
    rgb = np.clip(SH_C0 * g.sh.double().numpy()[:, 0, :] + 0.5, 0, 1)
    op = 1.0 / (1.0 + np.exp(-g.opacity_logits.double().numpy()))
    assert a["centers"].shape == (g.num, 3) and a["covariances"].shape == (g.num, 3, 3)
    assert a["rgbs"].shape == (g.num, 3) and a["opacities"].shape == (g.num, 1)
    assert all(v.dtype == np.float32 and v.flags.c_contiguous for v in a.values())
    scale = np.abs(cov).max(axis=(1, 2), keepdims=True)
    assert (np.abs(a["covariances"] - cov) <= CONV_TOL * scale).all()  # per Gaussian, relative to its size
    np.testing.assert_allclose(a["centers"], g.means.double().numpy(), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(a["rgbs"], rgb, atol=1e-6)
    np.testing.assert_allclose(a["opacities"][:, 0], op, atol=1e-6)
    assert a["rgbs"].min() == 0.0 and a["rgbs"].max() == 1.0  # the random DC reaches both clamps


def test_conversion_axis_aligned_and_zero_quaternion():
    """Identity rotation: the covariance is diag(scale²); a quarter turn about z swaps x and y; a zero
    quaternion is the identity (as in the renderer)."""
    ls = torch.log(torch.tensor([[0.1, 0.2, 0.3]] * 3, dtype=torch.float64))
    h = 0.5 ** 0.5
    q = torch.tensor([[1.0, 0, 0, 0], [h, 0, 0, h], [0, 0, 0, 0]], dtype=torch.float64)
    g = Gaussians(torch.zeros(3, 3, dtype=torch.float64), q, ls, torch.zeros(3, dtype=torch.float64),
                  torch.zeros(3, 1, 3, dtype=torch.float64))
    c = splat_arrays(g)["covariances"]
    np.testing.assert_allclose(c[0], np.diag([0.01, 0.04, 0.09]), atol=1e-7)
    np.testing.assert_allclose(c[1], np.diag([0.04, 0.01, 0.09]), atol=1e-7)
    np.testing.assert_allclose(c[2], c[0], atol=1e-7)
    np.testing.assert_allclose(splat_arrays(g)["rgbs"], 0.5, atol=1e-7)  # dc 0 -> grey
    np.testing.assert_allclose(splat_arrays(g)["opacities"], 0.5, atol=1e-7)


def test_camera_pose_is_the_center_and_camera_to_world():
    cam = Camera.look_at((2.0, -1.0, 0.5), (0.0, 0.0, 0.0), up=(0, 0, 1), fov_deg=50, width=64, height=48)
    R, pos = camera_pose(cam)
    np.testing.assert_allclose(pos, [2.0, -1.0, 0.5], atol=1e-6)
    fwd = -np.array([2.0, -1.0, 0.5]) / np.linalg.norm([2.0, -1.0, 0.5])
    np.testing.assert_allclose(R[:, 2], fwd, atol=1e-6)  # OpenCV: the camera looks along its +z
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)


# --- what `view` loads -----------------------------------------------------------------------------------------
def _blob_scene(color, n=60, radius=0.5, seed=0):
    """Large opaque splats of one colour around the origin: they cover the middle of the view."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.25
    dc = (torch.tensor(color) - 0.5) / SH_C0
    return Gaussians(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), float(np.log(radius / 3))),
                     torch.full((n,), 6.0), dc.reshape(1, 1, 3).repeat(n, 1, 1))


def _cameras(n=6, r=2.5):
    return [Camera.look_at((r * np.cos(a), r * np.sin(a), 0.8), (0.0, 0.0, 0.0), up=(0, 0, 1), fov_deg=50,
                           width=64, height=48, name=f"view_{k:03d}")
            for k, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False))]


def _make_run(root: Path, with_sources=True) -> Path:
    from tlvg_warp.train.reconstruct import cameras_json
    from types import SimpleNamespace

    run = root / "run"
    run.mkdir()
    save_ply(_blob_scene(RED), run / "stylized.ply")
    cams = _cameras()
    (run / "cameras.json").write_text(json.dumps(cameras_json(SimpleNamespace(cameras=cams,
                                                                               names=[c.name for c in cams]))))
    if with_sources:
        save_ply(_blob_scene(BLUE), root / "input.ply")
        torch.save({"sources": {"scene": str(root / "input.ply")}}, run / "checkpoint.pt")
    return run


def test_load_run_finds_the_unstylized_scene_and_cameras(tmp_path):
    run = _make_run(tmp_path)
    c = load_view(run)
    assert list(c["scenes"]) == ["stylized", "un-stylized"]
    assert c["scenes"]["stylized"].num == 60 and len(c["cameras"]) == 6
    dc = c["scenes"]["un-stylized"].sh[:, 0].mean(0) * SH_C0 + 0.5
    np.testing.assert_allclose(dc.numpy(), BLUE, atol=1e-5)
    for cam, ref in zip(c["cameras"], _cameras()):
        np.testing.assert_allclose(camera_pose(cam)[1], camera_pose(ref)[1], atol=1e-5)


def test_load_run_without_sources_says_so(tmp_path):
    run = _make_run(tmp_path, with_sources=False)
    c = load_view(run)
    assert list(c["scenes"]) == ["stylized"]
    assert any("does not record its un-stylized scene" in n and "--original" in n for n in c["notes"])
    save_ply(_blob_scene(BLUE), tmp_path / "orig.ply")
    c2 = load_view(run, original=tmp_path / "orig.ply")  # --original
    assert list(c2["scenes"]) == ["stylized", "un-stylized"]


@pytest.mark.parametrize("ext", [".ply", ".compressed.ply", ".spz"])
def test_load_scene_file_any_format(tmp_path, ext):
    from tlvg_warp.io.splat_formats import save_compressed_ply, save_spz

    g = _blob_scene(RED)
    f = tmp_path / f"scene{ext}"
    {".ply": save_ply, ".compressed.ply": save_compressed_ply, ".spz": save_spz}[ext](g, f)
    c = load_view(f)
    assert list(c["scenes"]) == [f.name] and c["scenes"][f.name].num == g.num and c["cameras"] == []


def test_missing_path_is_an_input_error(tmp_path):
    from tlvg_warp.errors import InputError

    with pytest.raises(InputError, match="no such run folder"):
        load_view(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="stylized.ply"):
        load_view(tmp_path / "empty")


# --- the viewer server (no browser) ----------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_viewer_scenes_switch_and_frustums(tmp_path):
    run = _make_run(tmp_path)
    v = open_viewer(load_view(run), "127.0.0.1", _free_port())
    try:
        assert v.address.startswith("http://127.0.0.1:")
        assert v.scenes["stylized"].visible and not v.scenes["un-stylized"].visible
        v.show("un-stylized")
        assert v.scenes["un-stylized"].visible and not v.scenes["stylized"].visible
        assert v._dropdown.value == "un-stylized"
        assert len(v.frustums) == 6
        for f, cam in zip(v.frustums, _cameras()):
            R, pos = camera_pose(cam)
            np.testing.assert_allclose(f.position, pos, atol=1e-5)
            w, x, y, z = f.wxyz
            from scipy.spatial.transform import Rotation
            np.testing.assert_allclose(Rotation.from_quat([x, y, z, w]).as_matrix(), R, atol=1e-5)
        v.update("stylized", _blob_scene(RED, n=10))  # a live update replaces the splats
        assert v.counts["stylized"] == 10 and not v.scenes["stylized"].visible
    finally:
        v.stop()


def test_run_stylize_calls_on_progress():
    from tlvg_warp.io import builtin_painting, demo_dataset
    from tlvg_warp.stylize import StylizeConfig, run_stylize
    from tlvg_warp.stylize.pipeline import StylizeInputs

    ds = demo_dataset(n_views=2, width=32, height=24)
    g = ds.gaussians.subset(torch.arange(0, ds.gaussians.num, 8))
    inp = StylizeInputs(g, list(ds.cameras), list(ds.names), [ds.image(i) for i in range(2)], builtin_painting(),
                        tuple(ds.background), {"demo": True})
    cfg = StylizeConfig(iterations=6, device="cpu", vgg_weights="random", log_every=2, orbit_frames=2,
                        comparison_views=1, style_height=64)
    seen = []
    res = run_stylize(inp, cfg, None, progress=False, quiet=True,
                      on_progress=lambda step, gs: seen.append((step, gs.num, gs.means.requires_grad)))
    assert [s for s, _, _ in seen] == sorted({s for s, _, _ in seen}) and seen[-1][0] == 6
    steps = {s for s, _, _ in seen}
    assert {2, 4, 6} <= steps <= set(range(1, 7))  # every log_every steps (and at phase ends)
    assert not any(rg for _, _, rg in seen) and seen[-1][1] == res.gaussians.num


# --- the browser -------------------------------------------------------------------------------------------------
def _cover(img: np.ndarray, color) -> float:
    """Fraction of pixels of the splat's hue: the dominant channel bright, the other two dark (viser's GUI
    blue and its orange "software WebGL" notice are not saturated enough to count)."""
    x = img.astype(np.int16)
    k = int(np.argmax(color))
    others = [c for c in range(3) if c != k]
    return float(((x[..., k] > 150) & (x[..., others].max(-1) < 90)).mean())


@needs_chromium
def test_browser_draws_the_splats_and_switches_scene(tmp_path):
    run = _make_run(tmp_path)
    t0 = time.monotonic()
    empty = SceneViewer("127.0.0.1", _free_port())
    empty.frame((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), _cameras())
    try:
        with Chromium(empty.address + "/", SHOT_W, SHOT_H) as c:  # the empty scene: the page and grid only
            blank, ok = c.wait_for(lambda im: im.std() > 3, timeout=RENDER_TIMEOUT)
            assert ok, "the viewer page did not draw"
    finally:
        empty.stop()
    assert _cover(blank, RED) < COVER_EMPTY_MAX and _cover(blank, BLUE) < COVER_EMPTY_MAX

    v = open_viewer(load_view(run), "127.0.0.1", _free_port())
    try:
        with Chromium(v.address + "/", SHOT_W, SHOT_H) as c:
            red, ok = c.wait_for(lambda im: _cover(im, RED) > COVER_MIN, timeout=RENDER_TIMEOUT)
            assert ok, f"stylized splats not drawn: red covers {_cover(red, RED):.4f} of the view"
            assert np.abs(red.astype(np.int16) - blank.astype(np.int16)).mean() > 5  # not the empty scene
            v.show("un-stylized")  # what the dropdown does
            blue, ok = c.wait_for(lambda im: _cover(im, BLUE) > COVER_MIN and _cover(im, RED) < COVER_EMPTY_MAX,
                                  timeout=RENDER_TIMEOUT)
            assert ok, f"switch failed: blue {_cover(blue, BLUE):.4f}, red {_cover(blue, RED):.4f}"
    finally:
        v.stop()
    assert time.monotonic() - t0 < 120


def _deaf_to_sigint():  # as a parent that ignores and blocks SIGINT (both are inherited through exec)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})


@pytest.mark.parametrize("parent", ["plain", "sigint_ignored_and_blocked"])
def test_cli_view_prints_the_address_and_stops_on_ctrl_c(tmp_path, parent):
    run = _make_run(tmp_path)
    port = _free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([sys.executable, "-m", "tlvg_warp", "view", str(run), "--port", str(port)],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                         preexec_fn=_deaf_to_sigint if parent != "plain" else None)
    try:
        line = ""
        t0 = time.monotonic()
        while "viewer:" not in line and time.monotonic() - t0 < 60:
            line = p.stdout.readline()
            if not line and p.poll() is not None:
                break
        assert line.startswith(f"viewer: http://127.0.0.1:{port}"), line
        import urllib.request
        html = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10).read()
        assert b"<html" in html.lower()
        masks = [ln for ln in Path(f"/proc/{p.pid}/status").read_text().splitlines()
                 if ln.startswith(("SigBlk", "SigIgn", "SigCgt"))] if Path(f"/proc/{p.pid}/status").exists() else []
        p.send_signal(signal.SIGINT)
        try:
            rc = p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            rest = p.stdout.read()
            raise AssertionError(f"view did not stop on SIGINT within 30 s; signal masks before: {masks}; "
                                 f"its output: {rest[-2000:]!r}") from None
        assert rc == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
