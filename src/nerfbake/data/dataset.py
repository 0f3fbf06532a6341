"""A posed image collection in one shape, whatever format it came from.

Readers (``nerfbake.data.formats``) return a :class:`Dataset` whose cameras are already in the OpenGL
convention, normalised, and scaled to the requested downscale. Pixels are read only when asked for.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nerfbake.data.cameras import Camera
from nerfbake.data.errors import DatasetError
from nerfbake.data.images import load_image_uint8, to_float
from nerfbake.data.normalization import Normalization, camera_layout

WHITE = (1.0, 1.0, 1.0)


@dataclass
class Frame:
    """One image: where its pixels are, and its camera at the loaded scale."""

    name: str
    image_path: Path
    camera: Camera
    # Set when the stored image is larger than the camera (downscale on load), else None.
    load_size: tuple[int, int] | None = None


@dataclass
class Dataset:
    format: str
    root: Path
    frames: list[Frame]
    splits: dict[str, list[int]]
    normalization: Normalization = field(default_factory=Normalization)
    bounds: tuple[float, float] | None = None
    background: tuple[float, float, float] | None = None  # composite RGBA over this; None = images are opaque
    downscale: float = 1.0
    extras: dict = field(default_factory=dict)  # format-specific facts worth reporting (aabb_scale, ...)
    points: np.ndarray | None = None  # sparse SfM points (N, 3) in the normalised frame, where the format has them

    def __post_init__(self) -> None:
        if not self.frames:
            raise DatasetError(f"{self.root}: the dataset has no images with poses")
        for split, idx in self.splits.items():
            bad = [i for i in idx if not 0 <= i < len(self.frames)]
            if bad:
                raise DatasetError(f"{self.root}: split {split!r} refers to missing frames {bad[:5]}")

    def __len__(self) -> int:
        return len(self.frames)

    def split(self, name: str) -> list[int]:
        if name not in self.splits:
            raise DatasetError(f"{self.root}: no split {name!r}; this dataset has {', '.join(self.splits)}")
        return self.splits[name]

    def cameras(self, split: str | None = None) -> list[Camera]:
        idx = range(len(self.frames)) if split is None else self.split(split)
        return [self.frames[i].camera for i in idx]

    def image(self, index: int, keep_alpha: bool = False) -> np.ndarray:
        """Float32 (H, W, 3) image of frame ``index`` in [0, 1], RGBA composited on the background.

        With ``keep_alpha`` an RGBA source also returns its alpha as a 4th channel (for masks)."""
        frame = self.frames[index]
        arr = load_image_uint8(frame.image_path, frame.load_size)
        cam = frame.camera
        if arr.shape[0] != cam.height or arr.shape[1] != cam.width:
            raise DatasetError(
                f"{frame.image_path}: image is {arr.shape[1]}x{arr.shape[0]} but its camera says {cam.width}x{cam.height}; "
                "fix the intrinsics (w/h) or pass the matching --downscale"
            )
        return to_float(arr, self.background, keep_alpha)

    def training_frames(self) -> list[Frame]:
        return [self.frames[i] for i in self.split("train")] if "train" in self.splits else self.frames

    def scene_kind(self) -> tuple[str, str]:
        """(kind, why): what a teacher should model, decided from the training cameras and the sparse points.

        * ``object-centric``: a bounded box: a Blender scene whose cameras stand outside its box, or a capture whose
          sparse points' box holds no camera and which its cameras surround (:func:`object_box`);
        * ``forward-facing``: cameras that look one way (LLFF);
        * ``unbounded-360``: everything else (cameras all around, or inside, a scene that goes on to infinity).
        The last two are contracted."""
        train = self.training_frames()
        if self.format == "blender":
            lo, hi = self.extras.get("aabb", ([-1.5] * 3, [1.5] * 3))
            if cameras_inside(train, lo, hi):
                return "unbounded-360", "a Blender scene whose training cameras stand inside its box (an indoor capture)"
            return "object-centric", "a Blender scene: cameras outside its bounded box"
        layout, why = camera_layout(np.stack([f.camera.c2w for f in train]))
        norm = self.normalization
        if norm.overridden and norm.method == "forward-facing":
            return "forward-facing", norm.why
        if norm.overridden and norm.method == "object-centric" and layout == "forward-facing":
            layout, why = "360", f"{norm.why} (the cameras alone suggest forward-facing: {why})"
        if layout == "forward-facing":
            return "forward-facing", why
        if object_box(train, self.points) is not None:
            return "object-centric", why + "; the box of the sparse points holds no camera and the cameras surround it"
        if self.points is None or len(self.points) < 50:
            return "unbounded-360", why + "; no sparse points to bound an object by"
        return "unbounded-360", why + "; the cameras stand among the sparse points (a room or garden)"

    def info(self) -> dict:
        """The summary printed by ``nerfbake data info``."""
        cam = self.frames[0].camera
        kind, why = self.scene_kind()
        return {
            "scene_kind": kind,
            "scene_kind_why": why,
            "format": self.format,
            "root": str(self.root),
            "splits": {k: len(v) for k, v in self.splits.items()},
            "num_images": len(self.frames),
            "width": cam.width,
            "height": cam.height,
            "fx": cam.fx,
            "fy": cam.fy,
            "cx": cam.cx,
            "cy": cam.cy,
            "camera_model": cam.model,
            "distortion": {k: v for k, v in cam.distortion.items() if v},
            "downscale": self.downscale,
            "bounds": None if self.bounds is None else [float(b) for b in self.bounds],
            "normalization": self.normalization.to_json(),
            "background": None if self.background is None else list(self.background),
            **({"extras": self.extras} if self.extras else {}),
        }


def every_nth_split(names: list[str], every: int = 8) -> dict[str, list[int]]:
    """The LLFF/mip-NeRF 360 protocol: sort by name, hold out every ``every``-th image for testing."""
    order = sorted(range(len(names)), key=lambda i: names[i])
    test = sorted(order[k] for k in range(0, len(order), every))
    held = set(test)
    return {"train": [i for i in range(len(names)) if i not in held], "test": test}


def finish_frames(
    frames: list[Frame], normalization: Normalization, downscale: float
) -> list[Frame]:
    """Apply normalisation and downscale to every frame's camera (``load_size`` records the decode size)."""
    out = []
    for f in frames:
        cam = replace(f.camera, c2w=normalization.apply_to_pose(f.camera.c2w))
        load_size = None
        if downscale != 1:
            cam = cam.scaled(downscale)
            load_size = (cam.width, cam.height)
        out.append(replace(f, camera=cam, load_size=load_size))
    return out


def depth_bounds(frames: list[Frame], points: np.ndarray) -> tuple[float, float] | None:
    """(near, far) of a scene from its sparse points (normalised frame): the 0.1 and 99.9 percentiles of the depths
    of the points (a sample of) the cameras see, in front of them and inside their image, as LLFF's poses_bounds
    (which takes each image's own points). Counting the points beside a camera, outside its view, put bonsai's
    near bound at 0.006 (cameras on a unit ring; 0.68 counting only what each camera sees). None without such points."""
    if len(points) == 0:
        return None
    depths = []
    for f in frames[:: max(1, len(frames) // 20)]:
        uv, d = f.camera.project(points)
        with np.errstate(invalid="ignore"):
            seen = (d > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < f.camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < f.camera.height)
        depths.append(d[seen])
    d = np.concatenate(depths)
    return (float(np.percentile(d, 0.1)), float(np.percentile(d, 99.9))) if d.size else None


def object_box(frames: list[Frame], points: np.ndarray | None, pad: float = 0.05,
               max_resultant: float = 0.9) -> tuple[np.ndarray, np.ndarray] | None:
    """The box of an object-centred capture, or None where the capture is not one.

    Object-centred: the box of the sparse points holds no camera, and the cameras surround it: the unit vectors
    from its centre to them do not all point one way (their mean is shorter than ``max_resultant``; a
    forward-facing capture such as LLFF's is near 1, a hemisphere of views around an object ~0.6). Such a scene
    is better modelled inside that box, with rays that leave it ending on a learned background, than contracted
    to infinity (see ``scene_box``).

    The box: the extent of the points that have neighbours (the mean distance to their 4 nearest is at most 10x
    the median of that over all points: stray matches far away are left out, but the top of an object, whose
    points are rare next to a textured floor's, is kept), padded by ``pad`` of its size. Cutting geometry off is
    worse than a box with empty space, which the occupancy grid skips."""
    if points is None or len(points) < 50:
        return None
    dist, _ = cKDTree(points).query(points, k=5)  # the first neighbour is the point itself
    spread = dist[:, 1:].mean(axis=1)
    kept = points[spread <= 10 * np.median(spread)]
    lo, hi = kept.min(axis=0), kept.max(axis=0)
    size = hi - lo
    if not (size > 0).all():
        return None
    lo, hi = lo - pad * size, hi + pad * size
    centres = np.stack([f.camera.c2w[:3, 3] for f in frames])
    if ((centres > lo) & (centres < hi)).all(axis=1).any():
        return None
    to_cams = centres - (lo + hi) / 2
    to_cams /= np.linalg.norm(to_cams, axis=1, keepdims=True)
    if np.linalg.norm(to_cams.mean(0)) >= max_resultant:
        return None
    return lo, hi


def cameras_inside(frames, lo, hi) -> bool:
    """Whether most of these frames' cameras stand inside the box ``lo``..``hi``."""
    origins = np.stack([f.camera.origin for f in frames])
    return bool((((origins > np.asarray(lo)) & (origins < np.asarray(hi))).all(1)).mean() > 0.5)


def check_downscale(downscale: float, source: Path) -> float:
    if not np.isfinite(downscale) or downscale < 1:
        raise DatasetError(f"{source}: --downscale must be a number >= 1, got {downscale}")
    return float(downscale)
