"""LLFF: ``poses_bounds.npy`` (N, 17) = [3x5 pose|hwf, near, far] with rotation columns [down, right, back].

Images come from ``images_F/`` when that folder matches the requested downscale F (the focal is scaled by
F), otherwise from ``images/`` with on-load downscaling. Test views: every 8th of the sorted names.
Normalisation ``auto``: ``forward-facing`` (NeRF's recentring with bd_factor 0.75) when the cameras look one way,
else ``object-centric`` (360° captures such as mip-NeRF 360's, which ship in this form too).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfbake.data.cameras import Camera, pose_problem
from nerfbake.data.dataset import Dataset, Frame, check_downscale, every_nth_split, finish_frames
from nerfbake.data.errors import DatasetError
from nerfbake.data.images import IMAGE_EXTENSIONS, image_size
from nerfbake.data.normalization import choose as choose_normalization


def llff_to_opengl(poses: np.ndarray) -> np.ndarray:
    """(N,3,4) [down, right, back | t] -> (N,4,4) OpenGL c2w [right, up, back | t]."""
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, 0] = poses[:, :, 1]
    out[:, :3, 1] = -poses[:, :, 0]
    out[:, :3, 2] = poses[:, :, 2]
    out[:, :3, 3] = poses[:, :, 3]
    return out


def list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix in IMAGE_EXTENSIONS and not p.name.startswith("."))


def pick_image_folder(root: Path, downscale: float) -> tuple[Path, float, float]:
    """Choose among ``images/`` and ``images_F/``: the largest F <= downscale, the rest done on load.

    When only smaller copies exist (fern ships just ``images_8``) the smallest is used and the effective
    downscale becomes its factor. Returns (folder, factor still to apply on load, effective downscale)."""
    available = {1.0: root / "images"} if (root / "images").is_dir() else {}
    for d in root.glob("images_*"):
        tail = d.name.split("_", 1)[1]
        if d.is_dir() and tail.isdigit() and int(tail) > 0:
            available[float(tail)] = d
    if not available:
        raise DatasetError(f"{root}: no images/ or images_N/ folder next to poses_bounds.npy")
    usable = [f for f in available if f <= downscale]
    factor = max(usable) if usable else min(available)
    effective = max(downscale, factor)
    return available[factor], effective / factor, effective


def read_llff(root: Path, downscale: float = 1.0, normalize: str = "auto") -> Dataset:
    root = Path(root)
    downscale = check_downscale(downscale, root)
    pb_path = root / "poses_bounds.npy"
    try:
        arr = np.load(pb_path)
    except FileNotFoundError:
        raise DatasetError(f"{pb_path}: file is missing") from None
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{pb_path}: not a readable .npy file ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or not np.isfinite(arr).all():
        raise DatasetError(f"{pb_path}: expected a finite (N, 17) array of poses and bounds, got shape {arr.shape}")
    poses = arr[:, :15].reshape(-1, 3, 5)
    bounds = arr[:, 15:17]
    h_full, w_full, focal_full = poses[0, :, 4]

    folder, load_factor, downscale = pick_image_folder(root, downscale)
    paths = list_images(folder)
    if len(paths) != len(poses):
        raise DatasetError(
            f"{folder}: {len(paths)} images but {pb_path.name} has {len(poses)} poses; the counts must match "
            "(remove extra images or regenerate poses_bounds.npy)"
        )
    w, h = image_size(paths[0])
    # The folder's own scale relative to the hwf column (images_8 is 1/8 of the full-size focal).
    folder_scale = w / w_full
    if abs(h / h_full - folder_scale) > 0.02:
        raise DatasetError(f"{paths[0]}: image is {w}x{h}, which is not a scaled copy of the {w_full:.0f}x{h_full:.0f} in {pb_path.name}")
    f = focal_full * folder_scale
    c2ws = llff_to_opengl(poses[:, :, :4])
    for i, c2w in enumerate(c2ws):
        problem = pose_problem(c2w)
        if problem:
            raise DatasetError(f"{pb_path}: pose {i}: {problem}")
    if not (np.all(bounds > 0) and np.all(poses[:, :, 4] > 0)):
        raise DatasetError(f"{pb_path}: near/far bounds and the height, width, focal column must be positive")
    norm = choose_normalization(normalize, c2ws, root, near=float(bounds.min()))
    frames = [
        Frame(name=p.name, image_path=p, camera=Camera(c2w, w, h, f, f, w / 2.0, h / 2.0, "SIMPLE_PINHOLE"))
        for p, c2w in zip(paths, c2ws)
    ]
    frames = finish_frames(frames, norm, load_factor)
    splits = every_nth_split([p.name for p in paths])
    scaled_bounds = (float(bounds.min() * norm.scale), float(bounds.max() * norm.scale))
    return Dataset(
        "llff", root, frames, splits, norm, bounds=scaled_bounds, background=None, downscale=downscale,
        extras={"image_dir": folder.name, "per_image_bounds": (bounds * norm.scale).tolist()},
    )
