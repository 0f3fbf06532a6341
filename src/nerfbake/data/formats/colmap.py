"""COLMAP ``sparse/0`` models (binary or text), parsed by :mod:`colmap_model` with bounds checks.

World-to-camera OpenCV poses become OpenGL c2w; camera models SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL
and OPENCV are supported (others are refused by name). Images live in ``images/`` (``images_F/`` for a
matching downscale). Test views: every 8th of the sorted names. Normalisation: ``auto`` (forward-facing or 360° from the cameras).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfbake.data.cameras import Camera, opencv_to_opengl
from nerfbake.data.dataset import Dataset, Frame, check_downscale, depth_bounds, every_nth_split, finish_frames
from nerfbake.data.errors import DatasetError
from nerfbake.data.formats.colmap_model import read_model
from nerfbake.data.formats.llff import pick_image_folder
from nerfbake.data.normalization import choose as choose_normalization

# COLMAP parameter order per model -> (fx, fy, cx, cy, distortion dict).
_PARAMS = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], {}),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], {}),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], {"k1": p[3]}),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], {"k1": p[3], "k2": p[4]}),
    "OPENCV": lambda p: (p[0], p[1], p[2], p[3], {"k1": p[4], "k2": p[5], "p1": p[6], "p2": p[7]}),
}


def find_sparse_dir(root: Path) -> Path | None:
    """The folder holding cameras.* and images.* (sparse/0, sparse, colmap/sparse/0 or root itself)."""
    for cand in (root / "sparse" / "0", root / "sparse", root / "colmap" / "sparse" / "0", root):
        for ext in (".bin", ".txt"):
            if (cand / f"cameras{ext}").is_file() and (cand / f"images{ext}").is_file():
                return cand
    return None


def colmap_camera(cam, source: Path) -> tuple[float, float, float, float, dict, str]:
    """Intrinsics of a camera read here (model name) or by pycolmap (``nerfbake process``: a model enum)."""
    model = getattr(cam.model, "name", cam.model)
    if model not in _PARAMS:
        raise DatasetError(
            f"{source}: camera {cam.camera_id} uses the {model} model, which nerfbake does not read; "
            f"supported: {', '.join(_PARAMS)} (undistort the images with colmap image_undistorter)"
        )
    fx, fy, cx, cy, dist = _PARAMS[model]([float(v) for v in cam.params])
    return fx, fy, cx, cy, dist, model


def read_colmap(root: Path, downscale: float = 1.0, normalize: str = "auto") -> Dataset:
    root = Path(root)
    downscale = check_downscale(downscale, root)
    sparse = find_sparse_dir(root)
    if sparse is None:
        raise DatasetError(f"{root}: no COLMAP model (sparse/0/cameras.bin and images.bin, or the .txt versions)")
    rec = read_model(sparse)
    images = sorted(rec.images.values(), key=lambda im: im.name)
    if not images:
        raise DatasetError(f"{sparse}: the COLMAP model has no registered images")
    folder, load_factor, downscale = pick_image_folder(root, downscale)
    frames, c2ws = [], []
    for im in images:
        cam_obj = rec.cameras[im.camera_id]
        fx, fy, cx, cy, dist, model = colmap_camera(cam_obj, sparse)
        c2w = opencv_to_opengl(np.linalg.inv(im.world_to_camera()))
        path = folder / im.name
        if not path.is_file():
            raise DatasetError(f"{path}: image file is missing (named in {sparse}/images)")
        # Pre-downscaled folders hold images smaller than the COLMAP camera: scale its intrinsics first.
        base = Camera(c2w, cam_obj.width, cam_obj.height, fx, fy, cx, cy, model, dist)
        if folder.name != "images":
            base = base.scaled(float(folder.name.split("_")[-1]))
        frames.append(Frame(name=im.name, image_path=path, camera=base))
        c2ws.append(c2w)
    pts = rec.points
    raw_bounds = depth_bounds(frames, pts)  # forward-facing recentring scales by the nearest depth
    norm = choose_normalization(normalize, np.stack(c2ws), root, near=None if raw_bounds is None else raw_bounds[0])
    frames = finish_frames(frames, norm, load_factor)
    pts = norm.apply_to_points(pts)
    bounds = depth_bounds(frames, pts)
    return Dataset("colmap", root, frames, every_nth_split([f.name for f in frames]), norm, bounds=bounds,
                   background=None, downscale=downscale, extras={"sparse_dir": str(sparse)}, points=pts)
