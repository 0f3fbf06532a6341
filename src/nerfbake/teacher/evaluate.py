"""Render cameras with a teacher, and ``nerfbake teacher eval``: metrics on a held-out split."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from nerfbake.atomic import check_output_folder
from nerfbake.data.cameras import Camera
from nerfbake.data.formats import load_dataset
from nerfbake.data.rays import CameraBatch, pixel_grid
from nerfbake.data.formats.pose_file import read_pose_file
from nerfbake.eval.views import evaluate_views, render_views_to_folder
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


def render_poses(run: Path, pose_file: Path, out: Path, overwrite: bool = False) -> list[Path]:
    """One PNG per pose in ``out`` (which appears only once every view is rendered)."""
    check_output_folder(out, overwrite, "render")
    model, cfg, meta, _ = load_teacher(run)
    cams = read_pose_file(pose_file)
    bg = tuple(meta["dataset"]["background"] or (1.0, 1.0, 1.0))
    return render_views_to_folder(lambda cam: render_camera(model, cam, bg)["rgb"], cams, out, overwrite,
                                  extra_files={"poses.json": json.dumps({"source": str(pose_file), "count": len(cams)})})
