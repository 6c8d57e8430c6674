"""The two value types everything passes around: a set of Gaussians and a pinhole camera (SPEC §1)."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch

from .errors import InputError

SH_C0 = 0.28209479177387814  # real SH band-0 constant: color = SH_C0 * dc + 0.5


def sh_coeffs(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_of(k: int) -> int:
    d = int(round(math.sqrt(k))) - 1
    if (d + 1) ** 2 != k or not 0 <= d <= 3:
        raise InputError(f"sh has {k} coefficients per channel; expected 1, 4, 9 or 16 (degree 0..3)")
    return d


@dataclass
class Gaussians:
    """3D Gaussians, parameters stored before activation (SPEC §1)."""

    means: torch.Tensor  # [N, 3] world positions
    quats: torch.Tensor  # [N, 4] w, x, y, z (normalized inside the renderer)
    log_scales: torch.Tensor  # [N, 3]
    opacity_logits: torch.Tensor  # [N] opacity = sigmoid(logit)
    sh: torch.Tensor  # [N, K, 3] K = (degree + 1)^2, DC first

    FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")

    def __post_init__(self):
        self.validate()

    # -- shape and type checks -------------------------------------------------------------
    def validate(self) -> None:
        tensors = {f: getattr(self, f) for f in self.FIELDS}
        for name, t in tensors.items():
            if not isinstance(t, torch.Tensor):
                raise InputError(f"Gaussians.{name} must be a torch.Tensor, got {type(t).__name__}")
        n = self.means.shape[0] if self.means.dim() >= 1 else -1
        expect = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
        for name, shape in expect.items():
            if tuple(tensors[name].shape) != shape:
                raise InputError(f"Gaussians.{name} has shape {tuple(tensors[name].shape)}, expected {list(shape)}")
        if self.sh.dim() != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise InputError(f"Gaussians.sh has shape {tuple(self.sh.shape)}, expected [{n}, K, 3]")
        sh_degree_of(self.sh.shape[1])
        dtypes = {t.dtype for t in tensors.values()}
        if len(dtypes) != 1 or next(iter(dtypes)) not in (torch.float32, torch.float64):
            raise InputError(f"Gaussians tensors must all be float32 or all float64, got {sorted(map(str, dtypes))}")
        devices = {t.device for t in tensors.values()}
        if len(devices) != 1:
            raise InputError(f"Gaussians tensors are on mixed devices: {sorted(map(str, devices))}")

    # -- convenience -------------------------------------------------------------------------
    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(self.sh.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    def map(self, fn) -> "Gaussians":
        """A new Gaussians with ``fn`` applied to every tensor."""
        return Gaussians(**{f: fn(getattr(self, f)) for f in self.FIELDS})

    def detach(self) -> "Gaussians":
        return self.map(lambda t: t.detach())

    def clone(self) -> "Gaussians":
        return self.map(lambda t: t.detach().clone())

    def to(self, device=None, dtype=None) -> "Gaussians":
        return self.map(lambda t: t.to(device=device, dtype=dtype))

    def subset(self, index) -> "Gaussians":
        return self.map(lambda t: t[index])

    def with_sh_degree(self, degree: int) -> "Gaussians":
        """Truncate (or zero-pad) the SH coefficients to ``degree``."""
        k = sh_coeffs(degree)
        sh = self.sh[:, :k]
        if sh.shape[1] < k:
            pad = sh.new_zeros(sh.shape[0], k - sh.shape[1], 3)
            sh = torch.cat([sh, pad], dim=1)
        return dataclasses.replace(self, sh=sh)

    def nbytes(self) -> int:
        """Bytes of the parameters as float32 (what a PLY stores, without normals)."""
        return self.num * (3 + 4 + 3 + 1 + 3 * self.sh.shape[1]) * 4

    @staticmethod
    def from_colors(means, rgb, scale, opacity=0.5, degree=0) -> "Gaussians":
        """Isotropic Gaussians of the given linear colors in [0,1] (for tests and initialization)."""
        means = torch.as_tensor(means)
        n, dt = means.shape[0], means.dtype
        sh = torch.zeros(n, sh_coeffs(degree), 3, dtype=dt, device=means.device)
        sh[:, 0] = (torch.as_tensor(rgb, dtype=dt, device=means.device) - 0.5) / SH_C0
        scale = torch.as_tensor(scale, dtype=dt, device=means.device).expand(n)
        quats = torch.zeros(n, 4, dtype=dt, device=means.device)
        quats[:, 0] = 1
        op = torch.as_tensor(opacity, dtype=dt, device=means.device).expand(n).clamp(1e-6, 1 - 1e-6)
        return Gaussians(means, quats, torch.log(scale)[:, None].repeat(1, 3), torch.logit(op).contiguous(), sh)


@dataclass
class Camera:
    """Pinhole camera, OpenCV axes (x right, y down, z forward); ``world_to_camera`` is 4x4."""

    world_to_camera: torch.Tensor  # [4, 4] float64, CPU
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 0.01
    far: float = 1e10
    name: str = ""

    def __post_init__(self):
        m = torch.as_tensor(np.asarray(self.world_to_camera, dtype=np.float64) if not isinstance(
            self.world_to_camera, torch.Tensor) else self.world_to_camera.detach().cpu().double())
        if tuple(m.shape) != (4, 4):
            raise InputError(f"Camera.world_to_camera has shape {tuple(m.shape)}, expected [4, 4]")
        self.world_to_camera = m.contiguous()
        vals = [self.fx, self.fy, self.cx, self.cy, self.near, self.far]
        self.fx, self.fy, self.cx, self.cy, self.near, self.far = (float(v) for v in vals)
        if not torch.isfinite(m).all() or not all(math.isfinite(v) for v in vals[:5]):
            raise InputError(f"Camera {self.name or ''} has non-finite values".replace("  ", " "))
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(f"Camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) != self.width or int(self.height) != self.height:
            raise InputError(f"Camera size must be integers, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"Camera image size must be positive, got {self.width}x{self.height}")
        if not 0 < self.near < self.far:
            raise InputError(f"Camera needs 0 < near < far, got near={self.near}, far={self.far}")

    @property
    def R(self) -> torch.Tensor:  # [3, 3]
        return self.world_to_camera[:3, :3]

    @property
    def t(self) -> torch.Tensor:  # [3]
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> torch.Tensor:  # [3] camera position in world
        return -self.R.T @ self.t

    @property
    def K(self) -> torch.Tensor:  # [3, 3]
        return torch.tensor([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=torch.float64)

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``1/factor`` (pixel-center preserving)."""
        w, h = max(1, round(self.width / factor)), max(1, round(self.height / factor))
        sx, sy = w / self.width, h / self.height
        return dataclasses.replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy,
                                   width=w, height=h)

    @staticmethod
    def look_at(eye, target, up=(0.0, 0.0, 1.0), fov_deg=60.0, width=64, height=48, **kw) -> "Camera":
        """A camera at ``eye`` looking at ``target`` (``up`` is the world direction that appears up)."""
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)  # OpenCV: x right = forward x up, y down = forward x right
        if np.linalg.norm(x) < 1e-9:
            x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 0.0, 1.0]))
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        m = np.eye(4)
        m[:3, :3] = R
        m[:3, 3] = -R @ eye
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
        return Camera(torch.from_numpy(m), f, f, width / 2, height / 2, width, height, **kw)
