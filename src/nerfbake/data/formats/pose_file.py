"""Camera pose files: a transforms-style JSON of poses to render (``teacher render``, ``octree render``), not a
dataset (no images)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfbake.data.cameras import Camera
from nerfbake.data.errors import DatasetError
from nerfbake.data.formats.jsonio import read_json


def read_pose_file(path: Path) -> list[Camera]:
    """Cameras from a transforms-style JSON: ``camera_angle_x`` or ``fl_x``/``fl_y``, ``w``/``h`` (or
    ``width``/``height``), optional ``cx``/``cy``, and ``frames`` with OpenGL ``transform_matrix`` (or ``poses``)."""
    path = Path(path)
    meta = read_json(path)
    w = meta.get("w", meta.get("width"))
    h = meta.get("h", meta.get("height"))
    if w is None or h is None:
        raise DatasetError(f"{path}: give the image size as w and h")
    w, h = int(w), int(h)
    if "fl_x" in meta:
        fx = float(meta["fl_x"])
        fy = float(meta.get("fl_y", fx))
    elif "camera_angle_x" in meta:
        fx = fy = 0.5 * w / np.tan(0.5 * float(meta["camera_angle_x"]))
    else:
        raise DatasetError(f"{path}: give a focal length as fl_x or camera_angle_x")
    poses = meta.get("poses") or [f.get("transform_matrix") for f in meta.get("frames", [])]
    if not poses:
        raise DatasetError(f"{path}: no poses (a 'frames' list with transform_matrix, or 'poses')")
    cams = []
    for i, p in enumerate(poses):
        m = np.asarray(p, dtype=np.float64)
        if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
            raise DatasetError(f"{path}: pose {i} must be a finite 4x4 camera-to-world matrix")
        cams.append(Camera(m, w, h, fx, fy, float(meta.get("cx", w / 2)), float(meta.get("cy", h / 2))))
    return cams
