"""Lazy image loading with area downscaling and a bounded cache, so large scenes never sit in memory whole.

Images come back as float32 arrays in [0, 1]: (H, W, 3) RGB, or (H, W, 4) when an alpha channel is kept.
Downscaled copies are cached on disk (``$NERFBAKE_CACHE`` or ``~/.cache/nerfbake``) keyed by path, size, mtime
and factor, and decoded images are kept in a small in-memory LRU.
"""
from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from nerfbake.data.errors import DatasetError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".exr")


def cache_dir() -> Path:
    return Path(os.environ.get("NERFBAKE_CACHE", Path.home() / ".cache" / "nerfbake"))


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) read from the file header only, EXIF orientation honoured."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: image file is missing; check the path in the dataset's pose file or restore the image")
    try:
        with Image.open(path) as im:
            w, h = im.size
            orientation = im.getexif().get(0x0112, 1)
    except (UnidentifiedImageError, OSError) as exc:
        raise DatasetError(f"{path}: not a readable image ({exc}); re-export it or remove it from the dataset") from None
    return (h, w) if orientation in (5, 6, 7, 8) else (w, h)


def _decode(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            im = ImageOps.exif_transpose(im)
            if im.mode not in ("RGB", "RGBA"):
                im = im.convert("RGBA" if "A" in im.mode or "transparency" in im.info else "RGB")
            arr = np.asarray(im)
    except FileNotFoundError:
        raise DatasetError(f"{path}: image file is missing; check the path in the dataset's pose file or restore the image") from None
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot decode image ({exc}); re-export it or remove it from the dataset") from None
    return arr


def area_downscale(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Box-filter an (H, W, C) uint8 image to ``size`` = (width, height)."""
    if (arr.shape[1], arr.shape[0]) == size:
        return arr
    return np.asarray(Image.fromarray(arr).resize(size, Image.Resampling.BOX))


class ImageCache:
    """Thread-safe LRU of decoded uint8 images, bounded in bytes."""

    def __init__(self, max_bytes: int = 1 << 30):
        self.max_bytes = max_bytes
        self._items: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key):
        with self._lock:
            arr = self._items.get(key)
            if arr is not None:
                self._items.move_to_end(key)
            return arr

    def put(self, key, arr: np.ndarray) -> None:
        with self._lock:
            if key in self._items:
                return
            self._items[key] = arr
            self._bytes += arr.nbytes
            while self._bytes > self.max_bytes and len(self._items) > 1:
                _, old = self._items.popitem(last=False)
                self._bytes -= old.nbytes


_MEMORY_CACHE = ImageCache()


def load_image_uint8(path: Path, size: tuple[int, int] | None = None, disk_cache: bool = True) -> np.ndarray:
    """Decode ``path`` to uint8 (H, W, 3|4), area-downscaled to ``size`` = (width, height) if given."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise DatasetError(f"{path}: image file is missing; check the path in the dataset's pose file or restore the image") from None
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns, size)
    arr = _MEMORY_CACHE.get(key)
    if arr is not None:
        return arr
    cached = None
    if size is not None and disk_cache:
        digest = hashlib.sha1(repr(key).encode()).hexdigest()[:24]
        cached = cache_dir() / "images" / f"{digest}.npy"
        if cached.is_file():
            try:
                arr = np.load(cached)
            except (OSError, ValueError):
                arr = None
    if arr is None:
        arr = _decode(path)
        if size is not None and (arr.shape[1], arr.shape[0]) != size:
            arr = area_downscale(arr, size)
            if cached is not None:
                try:
                    cached.parent.mkdir(parents=True, exist_ok=True)
                    tmp = cached.with_suffix(f".tmp{os.getpid()}.npy")
                    np.save(tmp, arr)
                    os.replace(tmp, cached)
                except OSError:
                    pass  # a read-only home is not an error; we just do not cache
    _MEMORY_CACHE.put(key, arr)
    return arr


def to_float(arr: np.ndarray, background: tuple[float, float, float] | None, keep_alpha: bool = False) -> np.ndarray:
    """uint8 image -> float32 in [0, 1]; RGBA is composited over ``background`` (RGB·a + bg·(1-a)) unless None."""
    img = arr.astype(np.float32) / 255.0
    if img.shape[-1] == 4 and background is not None:
        rgb, a = img[..., :3], img[..., 3:]
        comp = rgb * a + np.asarray(background, np.float32) * (1.0 - a)
        return np.concatenate([comp, a], axis=-1) if keep_alpha else comp
    if img.shape[-1] == 4 and not keep_alpha:
        return img[..., :3]
    return img
