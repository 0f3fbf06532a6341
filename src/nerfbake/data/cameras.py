"""Pinhole cameras with lens distortion, in the OpenGL/Blender convention.

Poses are camera-to-world 4x4 with +X right, +Y up and the camera looking down -Z. Intrinsics are in
pixels with pixel centres at +0.5. Distortion follows COLMAP/OpenCV on normalised image coordinates
(x right, y down): radial k1..k4 (k3 as in OpenCV's 5-parameter model) and tangential p1, p2.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

# Camera models we read, and which distortion parameters each one uses.
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": (),
    "PINHOLE": (),
    "SIMPLE_RADIAL": ("k1",),
    "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2"),
    "FULL_RADIAL_OPENCV": ("k1", "k2", "p1", "p2", "k3"),  # transforms.json with k3 (nerfstudio's "OPENCV" + k3)
}
DISTORTION_KEYS = ("k1", "k2", "k3", "p1", "p2")


@dataclass
class Camera:
    """One camera: pose (4,4) c2w OpenGL, intrinsics in pixels at this image size, distortion coefficients."""

    c2w: np.ndarray
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str = "PINHOLE"
    distortion: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.c2w = np.asarray(self.c2w, dtype=np.float64)
        if self.c2w.shape == (3, 4):
            self.c2w = np.vstack([self.c2w, [0.0, 0.0, 0.0, 1.0]])
        if self.c2w.shape != (4, 4) or not np.isfinite(self.c2w).all():
            raise ValueError(f"camera pose must be a finite 4x4 (or 3x4) matrix, got shape {self.c2w.shape}")
        if self.model not in CAMERA_MODELS:
            raise ValueError(f"unknown camera model {self.model!r}; supported: {', '.join(CAMERA_MODELS)}")
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera needs positive size and focal length, got {self.width}x{self.height} f=({self.fx},{self.fy})")

    @property
    def has_distortion(self) -> bool:
        return any(abs(self.distortion.get(k, 0.0)) > 0 for k in DISTORTION_KEYS)

    @property
    def origin(self) -> np.ndarray:
        return self.c2w[:3, 3]

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image downscaled by ``factor`` (intrinsics divide, distortion is unitless)."""
        w, h = int(round(self.width / factor)), int(round(self.height / factor))
        sx, sy = w / self.width, h / self.height
        return replace(self, width=w, height=h, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy,
                       c2w=self.c2w.copy(), distortion=dict(self.distortion))

    def intrinsics_matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N,3) -> pixel coordinates (N,2) (distorted) and depth along the viewing axis (N,)."""
        w2c = np.linalg.inv(self.c2w)
        pc = points @ w2c[:3, :3].T + w2c[:3, 3]
        depth = -pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = pc[:, 0] / depth, -pc[:, 1] / depth  # OpenCV normalised coordinates
        xd, yd = distort(x, y, self.distortion)
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1), depth


def _coeffs(dist: dict) -> tuple:
    """(k1, k2, k3, k4, p1, p2) as floats, or as per-ray tensors when the dict holds tensors."""
    return tuple(dist.get(k, 0.0) if isinstance(dist.get(k), torch.Tensor) else float(dist.get(k, 0.0))
                 for k in ("k1", "k2", "k3", "k4", "p1", "p2"))


def distort(x, y, dist: dict[str, float]):
    """Apply OpenCV radial-tangential distortion to normalised coordinates (works on numpy and torch)."""
    k1, k2, k3, k4, p1, p2 = _coeffs(dist)
    if not any(isinstance(k, torch.Tensor) or k for k in (k1, k2, k3, k4, p1, p2)):
        return x, y
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def undistort(xd: torch.Tensor, yd: torch.Tensor, dist: dict[str, float], iterations: int = 10):
    """Invert :func:`distort` by Newton's method (as COLMAP and nerfstudio do); torch tensors in, out."""
    k1, k2, k3, k4, p1, p2 = _coeffs(dist)
    if not any(isinstance(k, torch.Tensor) or k for k in (k1, k2, k3, k4, p1, p2)):
        return xd, yd
    x, y = xd.clone(), yd.clone()
    for _ in range(iterations):
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
        d_rad = k1 + r2 * (2 * k2 + r2 * (3 * k3 + r2 * 4 * k4))  # d(rad)/d(r2)
        fx = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        fy = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
        # Jacobian of the distortion map.
        a = rad + 2 * x * x * d_rad + 2 * p1 * y + 6 * p2 * x
        b = 2 * x * y * d_rad + 2 * p1 * x + 2 * p2 * y
        c = 2 * x * y * d_rad + 2 * p2 * y + 2 * p1 * x
        d = rad + 2 * y * y * d_rad + 2 * p2 * x + 6 * p1 * y
        det = a * d - b * c
        det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
        x = x - (d * fx - b * fy) / det
        y = y - (-c * fx + a * fy) / det
    return x, y


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """Flip camera axes Y and Z: OpenCV/COLMAP c2w (x right, y down, z forward) <-> OpenGL c2w."""
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[..., :3, 1:3] *= -1
    return out


def pose_problem(c2w: np.ndarray) -> str | None:
    """Why a camera-to-world matrix cannot be a camera pose (non-finite, absurdly large, a rotation part that is
    not a rotation up to a loose scale), or None. Garbage poses otherwise reach least-squares fits that hang."""
    m = np.asarray(c2w, dtype=np.float64)
    if m.shape[-2:] not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
        return "not a finite 3x4 or 4x4 matrix"
    if np.abs(m[:3, 3]).max() > 1e7:
        return f"camera position {m[:3, 3].tolist()} is implausibly far from the origin"
    if np.abs(m[:3, :3]).max() > 2.0:
        return "its 3x3 rotation part has entries beyond +-2 (a rotation's are within +-1)"
    norms = np.linalg.norm(m[:3, :3], axis=0)
    if not np.all((norms > 0.5) & (norms < 2.0)) or abs(np.linalg.det(m[:3, :3] / norms)) < 0.9:
        return "its 3x3 rotation part is not a rotation (columns of length 1, orthogonal)"
    return None
