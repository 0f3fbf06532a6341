"""COLMAP's sparse model files (``cameras``, ``images``, ``points3D``; ``.bin`` or ``.txt``) parsed with bounds checks.

The layouts are COLMAP's documented ones (``src/colmap/scene/reconstruction_io.cc``): little-endian counts as
uint64, ids as uint32 (points as uint64), doubles for every real value, image names NUL-terminated. pycolmap reads
the same files but hangs or aborts on a corrupt one (a count field of 2^60 is taken at its word), so datasets are
read here: every count is checked against the bytes left, every value for finiteness, and any inconsistency is a
:class:`DatasetError` naming the file. ``nerfbake process`` still uses pycolmap for structure from motion.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfbake.data.errors import DatasetError
from nerfbake.render.rotations import quaternion_matrix

# COLMAP model id -> (name, number of parameters)
MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
PARAM_COUNT = dict(MODELS.values())


@dataclass
class ColmapCamera:
    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    image_id: int
    name: str
    camera_id: int
    qvec: np.ndarray  # (w, x, y, z), world -> camera rotation
    tvec: np.ndarray

    def world_to_camera(self) -> np.ndarray:
        """4x4 OpenCV world-to-camera matrix."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = quaternion_matrix(np.asarray(self.qvec, np.float64)), self.tvec
        return m


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: np.ndarray  # (P, 3) xyz
    colors: np.ndarray  # (P, 3) uint8
    tracks: list[np.ndarray]  # per point, the ids of the images that see it


class _Bytes:
    """A cursor over a file's bytes whose reads fail with the file's name instead of running past the end."""

    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def left(self) -> int:
        return len(self.data) - self.at

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if size > self.left():
            raise DatasetError(f"{self.path}: truncated at byte {self.at} (needs {size} more); re-export the model")
        out = struct.unpack_from(fmt, self.data, self.at)
        self.at += size
        return out

    def count(self, min_record: int, what: str) -> int:
        (n,) = self.take("<Q")
        if n * min_record > self.left():
            raise DatasetError(f"{self.path}: announces {n} {what} but holds only {self.left()} more bytes; the file is "
                               "corrupt or truncated")
        return n

    def cstring(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise DatasetError(f"{self.path}: an image name runs to the end of the file (truncated)")
        raw, self.at = self.data[self.at:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise DatasetError(f"{self.path}: an image name at byte {end - len(raw)} is not UTF-8") from None

    def finish(self) -> None:
        if self.left():
            raise DatasetError(f"{self.path}: {self.left()} unexpected bytes after the last record")


def _finite(path: Path, values, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise DatasetError(f"{path}: {what} holds NaN or infinite values")
    return arr


def _camera(path, camera_id, model, width, height, params) -> ColmapCamera:
    if not (1 <= width <= 1 << 20 and 1 <= height <= 1 << 20):
        raise DatasetError(f"{path}: camera {camera_id} has size {width} x {height}")
    return ColmapCamera(camera_id, model, int(width), int(height), _finite(path, params, f"camera {camera_id}'s parameters"))


def _image(path, image_id, q, t, camera_id, name) -> ColmapImage:
    q = _finite(path, q, f"image {image_id}'s rotation")
    if not name:
        raise DatasetError(f"{path}: image {image_id} has an empty name")
    if not 1e-8 < np.abs(q).max() < 1e8:
        raise DatasetError(f"{path}: image {image_id} ({name}) has a degenerate rotation quaternion {q.tolist()}")
    t = _finite(path, t, f"image {image_id}'s translation")
    if np.abs(t).max() > 1e7:
        raise DatasetError(f"{path}: image {image_id} ({name}) has an implausible translation {t.tolist()}")
    return ColmapImage(image_id, name, camera_id, q, t)


def read_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    b = _Bytes(path)
    cams = {}
    for _ in range(b.count(24, "cameras")):
        camera_id, model_id, width, height = b.take("<IiQQ")
        if model_id not in MODELS:
            raise DatasetError(f"{path}: camera {camera_id} has unknown model id {model_id}")
        name, n = MODELS[model_id]
        cams[camera_id] = _camera(path, camera_id, name, width, height, b.take(f"<{n}d"))
    b.finish()
    return cams


def read_images_binary(path: Path) -> dict[int, ColmapImage]:
    b = _Bytes(path)
    images = {}
    for _ in range(b.count(72, "images")):
        image_id, *qt, camera_id = b.take("<I7dI")
        name = b.cstring()
        n_points = b.count(24, "2D points")
        b.at += 24 * n_points  # keypoints: not needed here
        images[image_id] = _image(path, image_id, qt[:4], qt[4:], camera_id, name)
    b.finish()
    return images


def read_points3d_binary(path: Path) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """xyz (P, 3), rgb (P, 3) uint8 and, per point, the image ids of its track (LLFF captures ship this file alone)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: file is missing")
    b = _Bytes(path)
    n = b.count(51, "points")
    xyz, rgb, tracks = np.empty((n, 3)), np.empty((n, 3), np.uint8), []
    for i in range(n):
        _, x, y, z, r, g, bl, _, length = b.take("<Q3d3BdQ")
        if 8 * length > b.left():
            raise DatasetError(f"{path}: point {i} announces a track of {length} but the file ends first")
        track = np.frombuffer(b.data, "<i4", 2 * length, b.at).reshape(-1, 2)
        b.at += 8 * length
        xyz[i], rgb[i] = (x, y, z), (r, g, bl)
        tracks.append(track[:, 0].copy())
    b.finish()
    return _finite(path, xyz, "a point's position"), rgb, tracks


def _text_lines(path: Path) -> list[str]:
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a text file (COLMAP's .txt models are plain text)") from None
    return [line.strip() for line in text.splitlines() if not line.lstrip().startswith("#")]


def _numbers(path: Path, words: list[str], kind, lineno: int) -> list:
    try:
        return [kind(w) for w in words]
    except ValueError:
        raise DatasetError(f"{path}: line {lineno} is not a COLMAP record: {' '.join(words)[:80]!r}") from None


def read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    cams = {}
    for lineno, line in enumerate(_text_lines(path), 1):
        if not line:
            continue
        w = line.split()
        if len(w) < 4 or w[1] not in PARAM_COUNT or len(w) != 4 + PARAM_COUNT[w[1]]:
            raise DatasetError(f"{path}: line {lineno} is not 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...' with a known "
                               f"model's parameters: {line[:80]!r}")
        camera_id, width, height = _numbers(path, [w[0], w[2], w[3]], int, lineno)
        cams[camera_id] = _camera(path, camera_id, w[1], width, height, _numbers(path, w[4:], float, lineno))
    return cams


def read_images_text(path: Path) -> dict[int, ColmapImage]:
    """Two lines per image (the second, its 2D points, may be empty)."""
    lines = _text_lines(path)
    images, i = {}, 0
    while i < len(lines):
        if not lines[i]:
            i += 1
            continue
        w = lines[i].split(maxsplit=9)
        if len(w) != 10:
            raise DatasetError(f"{path}: line {i + 1} is not 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME': "
                               f"{lines[i][:80]!r}")
        image_id, camera_id = _numbers(path, [w[0], w[8]], int, i + 1)
        qt = _numbers(path, w[1:8], float, i + 1)
        images[image_id] = _image(path, image_id, qt[:4], qt[4:], camera_id, w[9])
        i += 2
    return images


def read_points3d_text(path: Path) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    xyz, rgb, tracks = [], [], []
    for lineno, line in enumerate(_text_lines(path), 1):
        if not line:
            continue
        w = line.split()
        if len(w) < 8 or (len(w) - 8) % 2:
            raise DatasetError(f"{path}: line {lineno} is not 'POINT3D_ID X Y Z R G B ERROR TRACK...': {line[:80]!r}")
        xyz.append(_numbers(path, w[1:4], float, lineno))
        rgb.append(np.clip(_numbers(path, w[4:7], int, lineno), 0, 255))
        tracks.append(np.asarray(_numbers(path, w[8::2], int, lineno), dtype=np.int64))
    pts = _finite(path, np.reshape(xyz, (-1, 3)), "a point's position")
    return pts, np.reshape(rgb, (-1, 3)).astype(np.uint8), tracks


def read_model(sparse: Path) -> ColmapModel:
    """The model in ``sparse`` (binary preferred when both forms are there); points3D may be absent."""
    sparse = Path(sparse)
    ext = ".bin" if (sparse / "cameras.bin").is_file() and (sparse / "images.bin").is_file() else ".txt"
    binary = ext == ".bin"
    cameras = (read_cameras_binary if binary else read_cameras_text)(sparse / f"cameras{ext}")
    images = (read_images_binary if binary else read_images_text)(sparse / f"images{ext}")
    points_file = sparse / f"points3D{ext}"
    if points_file.is_file():
        points, colors, tracks = (read_points3d_binary if binary else read_points3d_text)(points_file)
    else:
        points, colors, tracks = np.zeros((0, 3)), np.zeros((0, 3), np.uint8), []
    for im in images.values():
        if im.camera_id not in cameras:
            raise DatasetError(f"{sparse / f'images{ext}'}: image {im.name} uses camera {im.camera_id}, which "
                               f"{sparse / f'cameras{ext}'} does not define")
    return ColmapModel(cameras, images, points, colors, tracks)
