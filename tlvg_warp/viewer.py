"""The interactive browser viewer: a viser server (https://viser.studio, the web viewer gsplat and
nerfstudio use; its client is bundled in the wheel, so it works offline) showing Gaussian scenes as splats,
a dropdown to switch between them (stylized / un-stylized), and the training cameras as frustums.

``splat_arrays`` converts our Gaussians (SPEC §1) to viser's inputs, vectorized: covariance R S Sᵀ Rᵀ with R
from the normalized w,x,y,z quaternion and S = diag(exp(log_scales)); rgb = clamp(SH_C0·dc + 0.5, 0, 1)
(band 0 only: viser's splats carry no view-dependent colour); opacity = sigmoid(logit).
``SceneViewer`` is the server; ``python -m tlvg_warp view`` and ``stylize --view`` drive it."""
from __future__ import annotations

import contextlib
import io
import math
import threading

import numpy as np
import torch

from .errors import InputError
from .types import SH_C0, Camera, Gaussians

DEFAULT_HOST = "127.0.0.1"  # local only: pass --host 0.0.0.0 to serve other machines
DEFAULT_PORT = 8080  # viser's default; a busy port moves to the next free one (the printed address says which)
UP_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
DEFAULT_UP = "-y"  # COLMAP / INRIA scenes: image y points down, so world up is usually -y
FRUSTUM_SCALE = 0.05  # frustum depth as a fraction of the cameras' distance to the scene center
FRUSTUM_COLOR = (40, 40, 40)
CENTRAL = 0.5  # the starting view keeps frustums out of this central part of the image (in half-widths)
INSTALL_HINT = "the viewer needs viser: pip install viser (or pip install -e '.[viewer]')"


# --- conversion ------------------------------------------------------------------------------------------------
def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] w,x,y,z (any norm; a zero quaternion is the identity, as in the renderer) -> [N, 3, 3]."""
    n = q.norm(dim=-1, keepdim=True)
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype, device=q.device).expand_as(q)
    q = torch.where(n > 1e-12, q / n.clamp_min(1e-30), ident)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


@torch.no_grad()
def splat_arrays(g: Gaussians) -> dict:
    """Gaussians -> viser's add_gaussian_splats inputs (float32 numpy): centers [N,3], covariances [N,3,3],
    rgbs [N,3] in [0,1], opacities [N,1]. Computed in float64, on the Gaussians' device."""
    means = g.means.detach().double()
    R = quat_to_rotmat(g.quats.detach().double())
    s2 = torch.exp(2.0 * g.log_scales.detach().double())  # S Sᵀ = diag(scale²)
    cov = (R * s2[:, None, :]) @ R.transpose(1, 2)  # R diag(s²) Rᵀ
    rgb = (SH_C0 * g.sh.detach()[:, 0, :].double() + 0.5).clamp(0.0, 1.0)
    op = torch.sigmoid(g.opacity_logits.detach().double())[:, None]
    return {k: np.ascontiguousarray(v.cpu().numpy(), np.float32)
            for k, v in (("centers", means), ("covariances", cov), ("rgbs", rgb), ("opacities", op))}


def camera_pose(cam: Camera):
    """(camera-to-world rotation [3,3], center [3]) in OpenCV axes, as viser's frustums expect."""
    w2c = cam.world_to_camera.detach().double().cpu().numpy()
    R = w2c[:3, :3].T
    return R, -R @ w2c[:3, 3]


def rotmat_to_wxyz(R: np.ndarray) -> np.ndarray:
    from .train.optim import rotmat_to_quat  # lazy: the command line imports this module at startup

    return rotmat_to_quat(R[None])[0]


def _bounds(g: Gaussians):
    """The 5-95 % quantile box of the means: far-away background and stray splats do not stretch it."""
    m = g.means.detach().double().cpu()
    if m.shape[0] > 200_000:
        m = m[:: m.shape[0] // 200_000]
    if m.shape[0] == 0:
        return np.zeros(3), np.zeros(3)
    q = torch.quantile(m, torch.tensor([0.01, 0.99], dtype=torch.float64), dim=0).numpy()
    return q[0], q[1]


def scene_center(g: Gaussians) -> np.ndarray:
    """The middle of the 1-99 % box of the means (the subject, not the background)."""
    lo, hi = _bounds(g)
    return (lo + hi) / 2


def up_from_cameras(cams) -> np.ndarray:
    """World up as the cameras see it: minus the mean of their image-down (OpenCV +y) axes."""
    down = np.mean([camera_pose(c)[0][:, 1] for c in cams], axis=0)
    n = np.linalg.norm(down)
    return -down / n if n > 1e-9 else np.array(UP_AXES[DEFAULT_UP], np.float64)


def _fov_y(cam: Camera) -> float:
    return 2.0 * math.atan(cam.height / (2.0 * cam.fy))


# --- the server ------------------------------------------------------------------------------------------------
class SceneViewer:
    """A viser server with named scenes (one visible at a time, chosen in the "Scene" dropdown), optional
    training-camera frustums ("Training cameras" checkbox) and live updates (``update``; thread-safe)."""

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, title: str = "tlvg_warp"):
        try:
            import viser  # lazy: optional (the [viewer] extra)
        except ImportError:
            raise InputError(INSTALL_HINT) from None
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its own address box; ours is one line
            self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.server.gui.configure_theme(control_layout="floating", control_width="medium", show_logo=False,
                                        show_share_button=False)
        self._lock = threading.Lock()
        self.scenes: dict = {}  # name -> splat handle
        self.counts: dict = {}  # name -> number of Gaussians shown
        self.frustums: list = []
        self._dropdown = None
        self._status = None
        self._visible = None
        self._notes = []

    @property
    def address(self) -> str:
        host = self.server.get_host()
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{shown}:{self.server.get_port()}"

    # -- scenes --------------------------------------------------------------------------------------------------
    def set_scene(self, name: str, g: Gaussians) -> None:
        """Add the scene ``name`` or replace its splats (live updates)."""
        a = splat_arrays(g)
        with self._lock:
            visible = self._visible is None or self._visible == name
            self.scenes[name] = self.server.scene.add_gaussian_splats(f"/scenes/{name}", visible=visible, **a)
            self.counts[name] = g.num
            if self._visible is None:
                self._visible = name
            self._refresh_gui()

    update = set_scene

    def show(self, name: str) -> None:
        """Make ``name`` the visible scene (what the dropdown does)."""
        with self._lock:
            if name not in self.scenes:
                raise KeyError(name)
            self._visible = name
            for n, h in self.scenes.items():
                h.visible = n == name
            if self._dropdown is not None and self._dropdown.value != name:
                self._dropdown.value = name
            self._refresh_status()

    def note(self, text: str) -> None:
        """A line of markdown under the controls (e.g. why the un-stylized scene is missing)."""
        self._notes.append(self.server.gui.add_markdown(text, order=100 + len(self._notes)))

    def set_status(self, text: str) -> None:
        with self._lock:
            self._status_text = text
            self._refresh_status()

    def _refresh_gui(self) -> None:
        names = list(self.scenes)
        if self._dropdown is None:
            self._dropdown = self.server.gui.add_dropdown("Scene", names, initial_value=self._visible, order=0)
            self._dropdown.on_update(lambda ev: self.show(ev.target.value) if ev.target.value != self._visible
                                     else None)
        elif tuple(self._dropdown.options) != tuple(names):
            self._dropdown.options = names
            self._dropdown.value = self._visible
        self._refresh_status()

    def _refresh_status(self) -> None:
        text = f"**{self._visible}**: {self.counts.get(self._visible, 0):,} Gaussians"
        extra = getattr(self, "_status_text", None)
        if extra:
            text += f"  \n{extra}"
        if self._status is None:
            self._status = self.server.gui.add_markdown(text, order=1)
        else:
            self._status.content = text

    # -- cameras -------------------------------------------------------------------------------------------------
    def add_cameras(self, cams, center=None) -> None:
        """The training cameras as frustums (OpenCV axes), sized relative to their distance to ``center``."""
        cams = list(cams)
        if not cams:
            return
        poses = [camera_pose(c) for c in cams]
        centers = np.stack([p for _, p in poses])
        ref = centers.mean(0) if center is None else np.asarray(center, np.float64)
        dist = float(np.median(np.linalg.norm(centers - ref, axis=1)))
        scale = FRUSTUM_SCALE * (dist if dist > 1e-9 else 1.0)
        for i, (cam, (R, pos)) in enumerate(zip(cams, poses)):
            self.frustums.append(self.server.scene.add_camera_frustum(
                f"/cameras/{i:04d}", fov=_fov_y(cam), aspect=cam.width / cam.height, scale=scale,
                thickness=0.03 * scale, color=FRUSTUM_COLOR, wxyz=rotmat_to_wxyz(R), position=pos))
        box = self.server.gui.add_checkbox(f"Training cameras ({len(cams)})", True, order=2)

        @box.on_update
        def _(ev):
            for f in self.frustums:
                f.visible = ev.target.value

    # -- where the browser starts ----------------------------------------------------------------------------------
    def frame(self, center, up, cams=None, radius: float | None = None) -> None:
        """The starting view (and "Reset View"): ``initial_view``."""
        up = np.asarray(up, np.float64)
        up = up / np.linalg.norm(up)
        self.server.scene.set_up_direction(tuple(float(v) for v in up))
        view = initial_view(center, up, cams, radius)
        ic = self.server.initial_camera
        if view["fov"] is not None:
            ic.fov = view["fov"]
        ic.position, ic.look_at = view["position"], view["look_at"]
        ic.up = tuple(float(v) for v in up)

    def stop(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()


def _obstructed(R: np.ndarray, pos: np.ndarray, cam: Camera, centers: np.ndarray, depth: float, own: int) -> bool:
    """Whether a frustum (camera center) other than ``own`` lies in front of the subject (0 < z < ``depth``) and
    projects into the CENTRAL part of the view of a camera at (R, pos) with ``cam``'s intrinsics."""
    for j, c in enumerate(centers):
        if j == own:
            continue
        x, y, z = R.T @ (c - pos)
        if not 1e-9 < z < depth:
            continue
        u, v = cam.fx * x / z / (cam.width / 2), cam.fy * y / z / (cam.height / 2)
        if abs(u) < CENTRAL and abs(v) < CENTRAL:
            return True
    return False


def initial_view(center, up, cams=None, radius: float | None = None) -> dict:
    """Where the browser starts: {"position", "look_at", "fov" (None: viser's)}.

    With cameras: the pose of a training camera itself (the first one whose view of the subject no other
    frustum stands in front of, in the central part of the image; else the first), looking along its axis. From
    a camera's own center its frustum shrinks to the image border, so the subject is seen as in its photo.
    Without: from ``radius`` away, above and to the side (relative to ``up``), looking at ``center``."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    center = np.asarray(center, np.float64)
    cams = list(cams or [])
    if cams:
        poses = [camera_pose(c) for c in cams]
        centers = np.stack([p for _, p in poses])
        pick = 0
        for i, (R, pos) in enumerate(poses):
            depth = float(np.dot(center - pos, R[:, 2]))
            if depth > 1e-9 and not _obstructed(R, pos, cams[i], centers, depth, i):
                pick = i
                break
        R, pos = poses[pick]
        depth = float(np.dot(center - pos, R[:, 2]))
        look = pos + (depth if depth > 1e-9 else 1.0) * R[:, 2]
        return {"position": pos, "look_at": look, "fov": _fov_y(cams[pick]), "camera": pick}
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    r = radius if radius and radius > 0 else 1.0
    side = side + np.cross(up, side)  # a three-quarter view
    side /= np.linalg.norm(side)
    return {"position": center + 0.8 * r * (0.95 * side + 0.3 * up), "look_at": center, "fov": None, "camera": None}


def scene_radius(g: Gaussians, center=None) -> float:
    """A viewing distance that frames the subject: the diagonal of the 1-99 % box of the means."""
    lo, hi = _bounds(g)
    d = float(np.linalg.norm(hi - lo))
    return d if d > 1e-9 else 1.0
