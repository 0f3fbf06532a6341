"""Image intake for ``nerfbake process``: the photos of a folder, or the sharpest frames of a video.

Folder intake keeps every readable image (EXIF orientation applied, unreadable files reported and skipped)
and groups them by the camera that took them (EXIF make, model, focal length and image size), so SfM can
share one camera per group. Video intake splits the video into evenly spaced windows and keeps the sharpest
frame of each (largest variance of the Laplacian). Both write into a destination folder and return
:class:`Intake`, which says what was kept, where it came from and what was skipped.
"""
from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from nerfbake.data.errors import DatasetError

# Extensions a user's photo folder may hold (case-insensitive); other files (sidecars, .DS_Store) are ignored.
PHOTO_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
_ORIENTATION = 0x0112


@dataclass
class Intake:
    """Images written for SfM: names (files in the destination folder), the camera group of each, skips."""

    names: list[str]
    groups: dict[str, str]  # image name -> camera group key (one shared camera per key)
    skipped: list[dict] = field(default_factory=list)  # {"file": ..., "reason": ...}
    source: str = ""
    info: dict = field(default_factory=dict)


def _camera_key(im: Image.Image, size: tuple[int, int]) -> str:
    """The camera an image came from: EXIF make/model/focal length (when present) and the image size."""
    exif = im.getexif()
    try:
        sub = exif.get_ifd(0x8769)  # Exif IFD holds FocalLength
    except Exception:  # noqa: BLE001 - broken EXIF blocks only lose the grouping hint
        sub = {}
    make, model = str(exif.get(0x010F, "")).strip(), str(exif.get(0x0110, "")).strip()
    focal = sub.get(0x920A, "")
    try:
        focal = f"{float(focal):.2f}" if focal != "" else ""
    except (TypeError, ValueError, ZeroDivisionError):
        focal = ""
    return f"{make}|{model}|{focal}|{size[0]}x{size[1]}"


def _even_subset(items: list, n: int | None) -> list:
    """``n`` items evenly spread over ``items`` (all of them when n is None or not smaller)."""
    if n is None or n >= len(items):
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, n)).astype(int))
    return [items[i] for i in idx]


def intake_images(folder: Path, dest: Path, max_images: int | None = None, progress=None) -> Intake:
    """Copy the readable images of ``folder`` (sorted by name) into ``dest``.

    Files whose pixels cannot be decoded are skipped and reported. Images with an EXIF orientation other
    than "upright" are rotated and re-saved (keeping the rest of their EXIF, orientation reset to 1); the
    others are copied byte for byte so the camera metadata SfM reads stays intact.
    """
    folder = Path(folder)
    if not folder.exists():
        raise DatasetError(f"{folder}: no such folder; pass --images DIR with your photos")
    if not folder.is_dir():
        raise DatasetError(f"{folder}: not a folder; pass --images DIR (or --video FILE for a video)")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_EXTENSIONS
                   and not p.name.startswith("."))
    files = _even_subset(files, max_images)
    dest.mkdir(parents=True, exist_ok=True)
    names, groups, skipped = [], {}, []
    for path in files:
        try:
            with Image.open(path) as im:
                im.load()
                orientation = im.getexif().get(_ORIENTATION, 1)
                upright = ImageOps.exif_transpose(im) if orientation not in (1, None) else im
                key = _camera_key(im, upright.size)
                if orientation in (1, None):
                    shutil.copyfile(path, dest / path.name)
                else:
                    exif = im.getexif()
                    exif[_ORIENTATION] = 1
                    kwargs = {"exif": exif.tobytes()}
                    if path.suffix.lower() in (".jpg", ".jpeg"):
                        kwargs["quality"] = 95
                    upright.save(dest / path.name, **kwargs)
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            skipped.append({"file": str(path), "reason": reason})
        else:
            names.append(path.name)
            groups[path.name] = key
        if progress is not None:
            progress()
    return Intake(names, groups, skipped, source=str(folder), info={"kind": "images", "files_seen": len(files)})


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image: large for sharp frames, small for blurred ones."""
    from scipy.ndimage import laplace

    grey = rgb[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    return float(laplace(grey).var())


def video_info(path: Path) -> tuple[int, float]:
    """(frame count, frames per second) of the first video stream; counts by decoding when the header lacks it."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise DatasetError(f"{path}: has no video stream; pass a video file (mp4, mov, mkv, ...)")
            stream = container.streams.video[0]
            fps = float(stream.average_rate or stream.guessed_rate or 30.0)
            count = int(stream.frames or 0)
            if count <= 0:
                count = sum(1 for _ in container.decode(stream))
    except DatasetError:
        raise
    except Exception as exc:  # noqa: BLE001 - PyAV raises many error types for unreadable files
        raise DatasetError(f"{path}: cannot read the video ({str(exc).splitlines()[0] if str(exc) else exc}); "
                           "re-encode it (e.g. to H.264 mp4) or extract the frames yourself and use --images") from None
    return count, fps


def upright(frame) -> np.ndarray:
    """The frame as a player shows it: phones store portrait clips as landscape frames plus a display-matrix
    rotation (``frame.rotation``: degrees counterclockwise, as FFmpeg's ``av_display_rotation_get``), which
    ``ffmpeg`` applies on decode and PyAV does not."""
    arr = frame.to_ndarray(format="rgb24")
    quarter_turns = round((frame.rotation or 0) / 90) % 4
    return np.ascontiguousarray(np.rot90(arr, quarter_turns)) if quarter_turns else arr


def intake_video(path: Path, dest: Path, fps: float | None = None, max_images: int = 100, progress=None,
                 known: tuple[int, float] | None = None) -> Intake:
    """Keep the sharpest frame of each of up to ``max_images`` evenly spaced windows of the video.

    The window length is ``video fps / fps`` frames when ``fps`` is given (never fewer windows than that
    allows), otherwise the video is cut into ``max_images`` equal windows. Frames are written as JPEG (q95).
    ``progress()`` is called per decoded frame; ``known`` = (frame count, fps) saves reading them again.
    """
    import av

    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such video file; check the path given to --video")
    if not path.is_file():
        raise DatasetError(f"{path}: not a file; pass --video FILE (or --images DIR for a folder of photos)")
    count, video_fps = known or video_info(path)
    if count <= 0:
        raise DatasetError(f"{path}: the video has no frames")
    windows = max_images
    if fps is not None:
        windows = min(windows, max(1, int(math.floor(count / video_fps * fps))))
    windows = max(1, min(windows, count))
    edges = np.linspace(0, count, windows + 1)
    window_of = np.minimum(np.searchsorted(edges, np.arange(count) + 0.5, side="right") - 1, windows - 1)
    dest.mkdir(parents=True, exist_ok=True)
    names, scores = [], []
    best: tuple[float, np.ndarray | None, int] = (-1.0, None, -1)
    current = 0

    def flush():
        score, arr, index = best
        if arr is not None:
            name = f"frame_{len(names) + 1:05d}.jpg"
            Image.fromarray(arr).save(dest / name, quality=95)
            names.append(name)
            scores.append({"name": name, "frame": index, "sharpness": round(score, 3)})

    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            for i, frame in enumerate(container.decode(stream)):
                w = int(window_of[min(i, count - 1)])
                if w != current:
                    flush()
                    best, current = (-1.0, None, -1), w
                arr = upright(frame)
                s = sharpness(arr)
                if s > best[0]:
                    best = (s, arr, i)
                if progress is not None:
                    progress()
            flush()
    except Exception as exc:  # noqa: BLE001
        raise DatasetError(f"{path}: cannot decode the video ({str(exc).splitlines()[0] if str(exc) else exc}); "
                           "re-encode it (e.g. to H.264 mp4) or extract the frames yourself and use --images") from None
    info = {"kind": "video", "frames_in_video": count, "video_fps": video_fps, "windows": windows, "kept": scores}
    return Intake(names, {n: "video" for n in names}, [], source=str(path), info=info)
