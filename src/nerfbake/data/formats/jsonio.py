"""Reading JSON pose files with errors that name the file and the field."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nerfbake.data.cameras import pose_problem
from nerfbake.data.errors import DatasetError


def read_json(path: Path) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path}: file is missing")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return data


def frames_of(data: dict, path: Path) -> list[dict]:
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: has no 'frames' list (or it is empty); each frame needs file_path and transform_matrix")
    return frames


def pose_of(frame: dict, path: Path, index: int) -> np.ndarray:
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except KeyError:
        raise DatasetError(f"{path}: frame {index} has no 'transform_matrix'") from None
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' is not a numeric matrix") from None
    if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' must be a finite 4x4 matrix, got shape {m.shape}")
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1.0]])
    problem = pose_problem(m)
    if problem:
        raise DatasetError(f"{path}: frame {index} 'transform_matrix': {problem}")
    return m


def number(data: dict, key: str, path: Path, where: str = "") -> float:
    try:
        v = float(data[key])
    except KeyError:
        raise DatasetError(f"{path}: missing {key!r}{where}") from None
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {key!r}{where} is not a number") from None
    if not np.isfinite(v):
        raise DatasetError(f"{path}: {key!r}{where} is not finite")
    return v


def resolve_image(root: Path, file_path: str, path: Path, index: int) -> Path:
    """A frame's image path; Blender files omit the extension, so try the usual ones."""
    if not isinstance(file_path, str) or not file_path:
        raise DatasetError(f"{path}: frame {index} has no 'file_path'")
    p = (root / file_path).resolve() if not Path(file_path).is_absolute() else Path(file_path)
    if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".exr"):
        return p
    for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG"):
        if p.with_name(p.name + ext).is_file():
            return p.with_name(p.name + ext)
    return p.with_name(p.name + ".png")
