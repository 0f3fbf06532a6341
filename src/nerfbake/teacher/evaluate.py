"""Render cameras with a teacher, and ``nerfbake teacher eval``: metrics on a held-out split."""
from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from nerfbake.atomic import atomic_folder, check_output_folder
from nerfbake.data.cameras import Camera
from nerfbake.data.formats import load_dataset
from nerfbake.data.rays import CameraBatch, pixel_grid
from nerfbake.eval.views import evaluate_views, to_png
from nerfbake.progress import progress_bar
from nerfbake.teacher.run import load_teacher
from nerfbake.train.loop import git_revision, write_json_atomic


@torch.no_grad()
def render_camera(model, camera: Camera, background=(1.0, 1.0, 1.0), chunk: int = 1 << 14) -> dict[str, np.ndarray]:
    """Full image (H, W, 3) colour, depth (H, W) and accumulated alpha for one camera."""
    cams = CameraBatch([camera])
    pix = pixel_grid(camera.width, camera.height).reshape(-1, 2)
    idx = torch.zeros(pix.shape[0], dtype=torch.long)
    dev = next(model.parameters()).device
    bg = None if background is None else torch.tensor(background, dtype=torch.float32, device=dev)
    parts = {"rgb": [], "depth": [], "acc": []}
    for s in range(0, pix.shape[0], chunk):
        rays = cams.rays(idx[s: s + chunk], pix[s: s + chunk])
        out = model.render_rays(rays["origins"].to(dev), rays["directions"].to(dev), bg)
        for k in parts:
            parts[k].append(out[k].cpu())
    h, w = camera.height, camera.width
    return {k: torch.cat(v).reshape(h, w, -1).squeeze(-1).clamp_min(0).numpy() for k, v in parts.items()}


def evaluate_teacher(run: Path, split: str = "test", max_views: int | None = None, write_images: bool = True,
                     appearance_fit: str = "none") -> dict:
    """Held-out metrics into ``RUN/eval/results_SPLIT.json`` (``results_SPLIT_half.json`` with ``appearance_fit``
    half: see :data:`nerfbake.eval.views.APPEARANCE_FITS`)."""
    model, cfg, meta, _ = load_teacher(run)
    ds = load_dataset(meta["data"], downscale=cfg.downscale, normalize=cfg.normalize)
    tag = split if appearance_fit == "none" else f"{split}_{appearance_fit}"
    result = evaluate_views(lambda cam, bg: render_camera(model, cam, bg)["rgb"], ds, split, max_views,
                            Path(run) / "eval" / tag if write_images else None, desc="eval", appearance_fit=appearance_fit)
    result.update({"teacher": cfg.field, "preset": cfg.preset, "data": meta["data"], "config": meta["train"],
                   "git": git_revision()})
    write_json_atomic(Path(run) / "eval" / f"results_{tag}.json", result)
    return result


def read_pose_file(path: Path) -> list[Camera]:
    """Cameras from a transforms-style JSON: ``camera_angle_x`` or ``fl_x``/``fl_y``, ``w``/``h`` (or
    ``width``/``height``), optional ``cx``/``cy``, and ``frames`` with OpenGL ``transform_matrix`` (or ``poses``)."""
    from nerfbake.data.errors import DatasetError
    from nerfbake.data.formats.jsonio import read_json

    path = Path(path)
    meta = read_json(path)
    w = meta.get("w", meta.get("width"))
    h = meta.get("h", meta.get("height"))
    if w is None or h is None:
        raise DatasetError(f"{path}: give the image size as w and h")
    w, h = int(w), int(h)
    if "fl_x" in meta:
        fx = float(meta["fl_x"])
        fy = float(meta.get("fl_y", fx))
    elif "camera_angle_x" in meta:
        fx = fy = 0.5 * w / np.tan(0.5 * float(meta["camera_angle_x"]))
    else:
        raise DatasetError(f"{path}: give a focal length as fl_x or camera_angle_x")
    poses = meta.get("poses") or [f.get("transform_matrix") for f in meta.get("frames", [])]
    if not poses:
        raise DatasetError(f"{path}: no poses (a 'frames' list with transform_matrix, or 'poses')")
    cams = []
    for i, p in enumerate(poses):
        m = np.asarray(p, dtype=np.float64)
        if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
            raise DatasetError(f"{path}: pose {i} must be a finite 4x4 camera-to-world matrix")
        cams.append(Camera(m, w, h, fx, fy, float(meta.get("cx", w / 2)), float(meta.get("cy", h / 2))))
    return cams


def render_poses(run: Path, pose_file: Path, out: Path, overwrite: bool = False) -> list[Path]:
    """One PNG per pose in ``out`` (which appears only once every view is rendered)."""
    out = Path(out)
    check_output_folder(out, overwrite, "render")
    model, cfg, meta, _ = load_teacher(run)
    cams = read_pose_file(pose_file)
    bg = tuple(meta["dataset"]["background"] or (1.0, 1.0, 1.0))
    names = [f"{i:04d}.png" for i in range(len(cams))]
    with atomic_folder(out, overwrite, "render") as tmp, progress_bar("render", len(cams), unit="view") as advance:
        for name, cam in zip(names, cams):
            iio.imwrite(tmp / name, to_png(render_camera(model, cam, bg)["rgb"]))
            advance()
        (tmp / "poses.json").write_text(json.dumps({"source": str(pose_file), "count": len(cams)}))
    return [out / n for n in names]
