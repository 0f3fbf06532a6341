"""Scene normalisation: a similarity transform recorded with the dataset so outputs map back to the input frame.

``p_normalized = scale * (R @ p + t)`` with ``transform = [[R, t], [0, 1]]`` (R a rotation). Poses are
transformed as c2w' = [[R·R_c, scale·(R·o + t)]]; depths and bounds multiply by ``scale``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nerfbake.data.errors import DatasetError

NORMALIZATIONS = ("auto", "forward-facing", "object-centric", "none")  # the --normalize choices; auto: from the cameras
NORMALIZE_HELP = ("scene normalisation: auto decides from the cameras (forward-facing or 360/object-centric; nerfbake "
                  "data info says which and why); the others override it (not for Blender scenes)")
TREE_NORMALIZE_HELP = "the --normalize the tree's teacher was trained with (the tree lives in its frame)"


@dataclass
class Normalization:
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    scale: float = 1.0
    method: str = "none"
    why: str = "chosen by the caller"  # how the method was chosen (``auto`` says what it saw in the cameras)
    overridden: bool = False  # named by the user (--normalize) instead of decided from the cameras

    def apply_to_pose(self, c2w: np.ndarray) -> np.ndarray:
        out = self.transform @ c2w
        out[:3, 3] *= self.scale
        return out

    def apply_to_points(self, points: np.ndarray) -> np.ndarray:
        return self.scale * (points @ self.transform[:3, :3].T + self.transform[:3, 3])

    def invert_points(self, points: np.ndarray) -> np.ndarray:
        return (points / self.scale - self.transform[:3, 3]) @ self.transform[:3, :3]

    def to_json(self) -> dict:
        return {"method": self.method, "why": self.why, "transform": self.transform.tolist(), "scale": float(self.scale),
                "overridden": self.overridden}


def average_pose(c2ws: np.ndarray) -> np.ndarray:
    """LLFF's mean pose: mean centre, mean viewing axis (+Z back) and mean up, orthonormalised."""
    center = c2ws[:, :3, 3].mean(0)
    back = _unit(c2ws[:, :3, 2].sum(0))
    up = c2ws[:, :3, 1].sum(0)
    right = _unit(np.cross(up, back))
    up = np.cross(back, right)
    out = np.eye(4)
    out[:3, :3] = np.stack([right, up, back], axis=1)
    out[:3, 3] = center
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def forward_facing(c2ws: np.ndarray, near: float, bd_factor: float = 0.75) -> Normalization:
    """NeRF's LLFF recentring: the average pose becomes the identity and the nearest bound 1/bd_factor."""
    return Normalization(np.linalg.inv(average_pose(c2ws)), 1.0 / (near * bd_factor), "forward-facing")


def focus_point(c2ws: np.ndarray) -> np.ndarray:
    """Least-squares point nearest to every camera's optical axis (where inward-facing captures look)."""
    dirs = -c2ws[:, :3, 2]
    origins = c2ws[:, :3, 3]
    eye = np.eye(3)[None]
    proj = eye - dirs[:, :, None] * dirs[:, None, :]
    a = proj.sum(0)
    b = (proj @ origins[:, :, None]).sum(0)[:, 0]
    return np.linalg.lstsq(a, b, rcond=None)[0]


def object_centric(c2ws: np.ndarray) -> Normalization:
    """360° re-centring: mean camera up becomes +Z, the cameras' focus point the origin, cameras inside [-1, 1]^3.

    The focus point falls back to the mean camera centre when the cameras do not look at a common point
    (e.g. walking through rooms), which keeps every camera inside the cube either way.
    """
    up = _unit(c2ws[:, :3, 1].sum(0))
    rot = _rotation_between(up, np.array([0.0, 0.0, 1.0]))
    centers = c2ws[:, :3, 3]
    center = focus_point(c2ws) if len(c2ws) >= 2 else centers.mean(0)
    spread = np.abs(centers - centers.mean(0)).max() + 1e-9
    if not np.isfinite(center).all() or np.abs(center - centers.mean(0)).max() > 2 * spread:
        center = centers.mean(0)
    transform = np.eye(4)
    transform[:3, :3] = rot
    transform[:3, 3] = -rot @ center
    extent = np.abs((centers - center) @ rot.T).max()
    return Normalization(transform, 1.0 / max(extent, 1e-9), "object-centric")


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation taking unit vector a to unit vector b (Rodrigues)."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1 + 1e-9:  # opposite: rotate pi about any axis orthogonal to a
        axis = _unit(np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0]))
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


# Cameras whose viewing directions agree this well (length of their mean unit vector) look one way: a
# forward-facing capture (LLFF's fern: 0.99). Captures around a scene are far below (bonsai: 0.1; the synthetic
# rooms 0.3; lego's hemisphere 0.2); a half orbit (instant-ngp's fox) ~0.8.
FORWARD_FACING_RESULTANT = 0.9
METHODS = ("auto", "forward-facing", "object-centric", "none")


def camera_layout(c2ws: np.ndarray) -> tuple[str, str]:
    """("forward-facing" | "360", why) from the cameras alone: do their viewing directions agree?"""
    dirs = -c2ws[:, :3, 2]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    resultant = float(np.linalg.norm(dirs.mean(0)))
    if resultant > FORWARD_FACING_RESULTANT:
        return "forward-facing", (f"the {len(c2ws)} cameras look one way (mean viewing direction length "
                                  f"{resultant:.2f} > {FORWARD_FACING_RESULTANT})")
    return "360", (f"the {len(c2ws)} cameras look in many directions (mean viewing direction length {resultant:.2f} "
                   f"<= {FORWARD_FACING_RESULTANT})")


def choose(method: str, c2ws: np.ndarray, source, near: float | None = None) -> Normalization:
    """The normalisation named by ``method`` for these poses (``forward-facing`` needs the nearest bound).

    ``auto`` decides from the cameras (:func:`camera_layout`): forward-facing captures get LLFF's recentring when
    the nearest bound is known, everything else the 360° re-centring; the reason is kept in ``Normalization.why``."""
    if method == "auto":
        layout, why = camera_layout(c2ws)
        if layout == "forward-facing" and near is None:
            method, why = "object-centric", why + "; no depth bounds for forward-facing recentring"
        else:
            method = "forward-facing" if layout == "forward-facing" else "object-centric"
        norm = choose(method, c2ws, source, near)
        norm.why, norm.overridden = why, False
        return norm
    if method == "forward-facing" and near is not None:
        chosen = forward_facing(c2ws, near)
    elif method == "object-centric":
        chosen = object_centric(c2ws)
    elif method == "none":
        chosen = Normalization()
    else:
        chosen = None
    if chosen is not None:
        chosen.why, chosen.overridden = f"--normalize {method}", True
        return chosen
    allowed = "auto, forward-facing, object-centric, none" if near is not None else "auto, object-centric, none"
    raise DatasetError(f"{source}: unknown normalisation {method!r} ({allowed})")
