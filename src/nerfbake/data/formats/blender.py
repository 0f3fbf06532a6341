"""NeRF-synthetic / Blender: ``transforms_{train,val,test}.json``, RGBA PNGs composited on white.

Focal length = 0.5·W / tan(0.5·camera_angle_x); poses are already OpenGL c2w. No normalisation (the
scenes live in [-1.5, 1.5]^3 by construction); near/far 2 and 6 as in NeRF.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from nerfbake.data.cameras import Camera
from nerfbake.data.dataset import WHITE, Dataset, Frame, check_downscale, finish_frames
from nerfbake.data.errors import DatasetError
from nerfbake.data.formats.jsonio import frames_of, number, pose_of, read_json, resolve_image
from nerfbake.data.images import image_size
from nerfbake.data.normalization import Normalization

SPLITS = ("train", "val", "test")


def read_blender(root: Path, downscale: float = 1.0, background=WHITE) -> Dataset:
    root = Path(root)
    downscale = check_downscale(downscale, root)
    frames: list[Frame] = []
    splits: dict[str, list[int]] = {}
    size = None
    for split in SPLITS:
        path = root / f"transforms_{split}.json"
        if not path.is_file():
            if split == "train":
                raise DatasetError(f"{path}: file is missing (a Blender dataset needs at least transforms_train.json)")
            continue
        meta = read_json(path)
        angle_x = number(meta, "camera_angle_x", path)
        if not 0 < angle_x < math.pi:
            raise DatasetError(f"{path}: camera_angle_x must be in (0, pi) radians, got {angle_x}")
        start = len(frames)
        for i, fr in enumerate(frames_of(meta, path)):
            image_path = resolve_image(root, fr.get("file_path", ""), path, i)
            if size is None:
                size = image_size(image_path)
            elif not image_path.is_file():
                raise DatasetError(f"{image_path}: image file is missing (listed in {path.name}, frame {i})")
            w, h = size
            focal = 0.5 * w / math.tan(0.5 * angle_x)
            cam = Camera(pose_of(fr, path, i), w, h, focal, focal, w / 2.0, h / 2.0, "PINHOLE")
            frames.append(Frame(name=f"{split}/{image_path.stem}", image_path=image_path, camera=cam))
        splits[split] = list(range(start, len(frames)))
    norm = Normalization(why="Blender scenes keep their own frame")
    frames = finish_frames(frames, norm, downscale)
    bounds, extras = (2.0, 6.0), {}
    if "near" in meta and "far" in meta:  # optional keys (nerfbake synth's indoor scenes write them)
        bounds = (number(meta, "near", path), number(meta, "far", path))
    if "aabb" in meta:
        box = np.asarray(meta["aabb"], dtype=np.float64)
        if box.shape != (2, 3) or not np.isfinite(box).all() or (box[1] <= box[0]).any():
            raise DatasetError(f"{path}: aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max")
        extras["aabb"] = box.tolist()
    return Dataset("blender", root, frames, splits, norm, bounds=bounds, background=background, downscale=downscale,
                   extras=extras)
