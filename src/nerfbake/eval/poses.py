"""Comparing recovered camera poses with ground truth: a similarity alignment and rotation angles (used by the
structure-from-motion tests and benchmark)."""
from __future__ import annotations

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising |s R src + t - dst|^2 (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(xd.T @ xs / len(src))
    fix = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        fix[2, 2] = -1
    rot = u @ fix @ vt
    scale = np.trace(np.diag(d) @ fix) / ((xs ** 2).sum() / len(src))
    return scale, rot, mu_d - scale * rot @ mu_s


def angle_deg(r: np.ndarray) -> float:
    """Rotation angle of a 3x3 rotation matrix, in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))
