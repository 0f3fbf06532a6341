"""COLMAP ``sparse/0`` models (binary or text) read through pycolmap.

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
    model = cam.model.name
    if model not in _PARAMS:
        raise DatasetError(
            f"{source}: camera {cam.camera_id} uses the {model} model, which nerfbake does not read; "
            f"supported: {', '.join(_PARAMS)} (undistort the images with colmap image_undistorter)"
        )
    fx, fy, cx, cy, dist = _PARAMS[model]([float(v) for v in cam.params])
    return fx, fy, cx, cy, dist, model


def read_colmap(root: Path, downscale: float = 1.0, normalize: str = "auto") -> Dataset:
    import pycolmap

    root = Path(root)
    downscale = check_downscale(downscale, root)
    sparse = find_sparse_dir(root)
    if sparse is None:
        raise DatasetError(f"{root}: no COLMAP model (sparse/0/cameras.bin and images.bin, or the .txt versions)")
    if not (sparse / "points3D.bin").is_file() and not (sparse / "points3D.txt").is_file():
        # pycolmap needs all three files; an empty points file is a valid model without points.
        raise DatasetError(f"{sparse}: points3D.bin/.txt is missing (pycolmap needs it; an empty points3D.txt will do)")
    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError with C++ text
        raise DatasetError(f"{sparse}: cannot read the COLMAP model ({str(exc).splitlines()[0] if str(exc) else exc})") from None
    images = sorted(rec.images.values(), key=lambda im: im.name)
    if not images:
        raise DatasetError(f"{sparse}: the COLMAP model has no registered images")
    folder, load_factor, downscale = pick_image_folder(root, downscale)
    frames, c2ws = [], []
    for im in images:
        if not im.has_pose:
            continue
        cam_obj = rec.cameras[im.camera_id]
        fx, fy, cx, cy, dist, model = colmap_camera(cam_obj, sparse)
        w2c = np.eye(4)
        w2c[:3, :4] = im.cam_from_world().matrix() if callable(im.cam_from_world) else im.cam_from_world.matrix()
        c2w = opencv_to_opengl(np.linalg.inv(w2c))
        path = folder / im.name
        if not path.is_file():
            raise DatasetError(f"{path}: image file is missing (named in {sparse}/images)")
        # Pre-downscaled folders hold images smaller than the COLMAP camera: scale its intrinsics first.
        base = Camera(c2w, cam_obj.width, cam_obj.height, fx, fy, cx, cy, model, dist)
        if folder.name != "images":
            base = base.scaled(float(folder.name.split("_")[-1]))
        frames.append(Frame(name=im.name, image_path=path, camera=base))
        c2ws.append(c2w)
    pts = np.stack([p.xyz for p in rec.points3D.values()]) if rec.num_points3D() > 0 else np.zeros((0, 3))
    raw_bounds = depth_bounds(frames, pts)  # forward-facing recentring scales by the nearest depth
    norm = choose_normalization(normalize, np.stack(c2ws), root, near=None if raw_bounds is None else raw_bounds[0])
    frames = finish_frames(frames, norm, load_factor)
    pts = norm.apply_to_points(pts)
    bounds = depth_bounds(frames, pts)
    return Dataset("colmap", root, frames, every_nth_split([f.name for f in frames]), norm, bounds=bounds,
                   background=None, downscale=downscale, extras={"sparse_dir": str(sparse)}, points=pts)


def read_points3d_binary(path: Path) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Read COLMAP ``points3D.bin`` without the rest of the model (LLFF captures ship it alone).

    Returns xyz (P, 3), rgb (P, 3) uint8 and, per point, the image ids of its track.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: file is missing") from None
    try:
        (count,) = np.frombuffer(raw, "<u8", 1, 0)
        off = 8
        xyz = np.empty((count, 3))
        rgb = np.empty((count, 3), np.uint8)
        tracks = []
        point = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("err", "<f8"), ("n", "<u8")])
        for i in range(count):
            rec = np.frombuffer(raw, point, 1, off)[0]
            off += point.itemsize
            xyz[i], rgb[i] = rec["xyz"], rec["rgb"]
            track = np.frombuffer(raw, "<i4", 2 * int(rec["n"]), off).reshape(-1, 2)
            off += track.nbytes
            tracks.append(track[:, 0].copy())
    except ValueError:
        raise DatasetError(f"{path}: truncated or not a COLMAP points3D.bin file") from None
    return xyz, rgb, tracks
