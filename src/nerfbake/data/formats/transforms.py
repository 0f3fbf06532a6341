"""instant-ngp / nerfstudio ``transforms.json``: OpenGL c2w per frame, shared or per-frame intrinsics.

Intrinsics: fl_x/fl_y (or camera_angle_x/y), cx, cy, w, h, distortion k1 k2 k3 p1 p2; per-frame values
override the top-level ones. Splits: ``train_filenames``/``val_filenames``/``test_filenames`` when present,
otherwise every 8th of the sorted names. ``aabb_scale`` is kept in the extras. Normalisation ``auto`` (forward-facing or 360° from the cameras).
Near/far bounds come from the sparse point cloud of ``ply_file_path`` (nerfstudio's key; ``nerfbake process``
writes it) when there is one: the teacher's near plane then keeps it from explaining each view with floaters
just in front of its camera.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from nerfbake.data.cameras import CAMERA_MODELS, Camera
from nerfbake.data.dataset import Dataset, Frame, check_downscale, depth_bounds, every_nth_split, finish_frames
from nerfbake.data.errors import DatasetError
from nerfbake.data.formats.ply import read_ply_points
from nerfbake.data.formats.jsonio import frames_of, pose_of, read_json, resolve_image
from nerfbake.data.images import image_size
from nerfbake.data.normalization import choose as choose_normalization

_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                   "k1", "k2", "k3", "k4", "p1", "p2", "camera_model")


def _intrinsics(fields: dict, path: Path, where: str, image_path: Path) -> Camera:
    def num(key, default=None):
        v = fields.get(key, default)
        if v is None:
            return None
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise DatasetError(f"{path}: {key!r}{where} is not a number") from None
        if not math.isfinite(v):
            raise DatasetError(f"{path}: {key!r}{where} is not finite")
        return v

    w, h = num("w"), num("h")
    if w is None or h is None:
        w, h = image_size(image_path)
    fx, fy = num("fl_x"), num("fl_y")
    if not (w >= 1 and h >= 1):
        raise DatasetError(f"{path}: image size {w} x {h}{where} is not positive; fix 'w'/'h'")
    for key, size in (("camera_angle_x", w), ("camera_angle_y", h)):
        angle = num(key)
        if angle is not None and not 0 < angle < math.pi:
            raise DatasetError(f"{path}: {key!r}{where} must be in (0, pi) radians, got {angle}")
        if angle is not None and (fx if key.endswith("x") else fy) is None:
            f = 0.5 * size / math.tan(0.5 * angle)
            fx, fy = (f, fy) if key.endswith("x") else (fx, f)
    if fx is None and fy is None:
        raise DatasetError(f"{path}: no focal length{where}; give fl_x/fl_y or camera_angle_x")
    fx, fy = fx or fy, fy or fx
    if not (fx > 0 and fy > 0):
        raise DatasetError(f"{path}: focal length fl_x {fx} / fl_y {fy}{where} must be positive")
    dist = {k: num(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
    model = str(fields.get("camera_model", "OPENCV" if any(dist.values()) else "PINHOLE"))
    if model == "OPENCV" and (dist["k3"] or dist["k4"]):
        model = "FULL_RADIAL_OPENCV"
    if model not in CAMERA_MODELS:
        raise DatasetError(f"{path}: unknown camera_model {model!r}{where}; supported: {', '.join(CAMERA_MODELS)}")
    return Camera(np.eye(4), int(w), int(h), fx, fy, num("cx", w / 2.0), num("cy", h / 2.0), model,
                  {k: v for k, v in dist.items() if v})


def read_transforms(root: Path, downscale: float = 1.0, normalize: str = "auto") -> Dataset:
    root = Path(root)
    downscale = check_downscale(downscale, root)
    path = root / "transforms.json"
    meta = read_json(path)
    top = {k: meta[k] for k in _INTRINSIC_KEYS if k in meta}
    frames: list[Frame] = []
    shared: Camera | None = None
    for i, fr in enumerate(frames_of(meta, path)):
        image_path = resolve_image(root, fr.get("file_path", ""), path, i)
        if not image_path.is_file():
            raise DatasetError(f"{image_path}: image file is missing (frame {i} of {path})")
        own = {k: fr[k] for k in _INTRINSIC_KEYS if k in fr}
        if own or shared is None:
            cam = _intrinsics({**top, **own}, path, f" (frame {i})" if own else "", image_path)
            if not own:
                shared = cam
        else:
            cam = shared
        c2w = pose_of(fr, path, i)
        frames.append(Frame(name=str(fr["file_path"]), image_path=image_path,
                            camera=Camera(c2w, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.model, dict(cam.distortion))))
    c2ws = np.stack([f.camera.c2w for f in frames])
    raw_points = raw_bounds = None
    if meta.get("ply_file_path") and (root / meta["ply_file_path"]).is_file():
        raw_points = read_ply_points(root / meta["ply_file_path"])
        raw_bounds = depth_bounds(frames, raw_points)  # forward-facing recentring scales by the nearest depth
    norm = choose_normalization(normalize, c2ws, root, near=None if raw_bounds is None else raw_bounds[0])
    frames = finish_frames(frames, norm, downscale)
    splits = _explicit_splits(meta, frames, path) or every_nth_split([f.name for f in frames])
    extras = {k: meta[k] for k in ("aabb_scale", "scale", "offset") if k in meta}
    bounds = points = None
    if raw_points is not None:
        points = norm.apply_to_points(raw_points)
        bounds = depth_bounds(frames, points)
    return Dataset("transforms", root, frames, splits, norm, bounds=bounds, background=None, downscale=downscale,
                   extras=extras, points=points)


def _explicit_splits(meta: dict, frames: list[Frame], path: Path) -> dict[str, list[int]] | None:
    lists = {s: meta[f"{s}_filenames"] for s in ("train", "val", "test") if f"{s}_filenames" in meta}
    if not lists:
        return None
    index = {}
    for i, f in enumerate(frames):
        index[f.name] = i
        index[f.name.lstrip("./")] = i
        index[f.image_path.name] = i
    out = {}
    for split, names in lists.items():
        missing = [n for n in names if n not in index and str(n).lstrip("./") not in index]
        if missing:
            raise DatasetError(f"{path}: {split}_filenames names {missing[0]!r}, which is not a frame's file_path")
        out[split] = [index.get(n, index.get(str(n).lstrip("./"))) for n in names]
    return out
