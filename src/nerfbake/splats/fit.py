"""Fit Gaussians to images: Adam on every parameter against target views (a teacher's renders of the training
cameras, or the training photos), through the reference rasteriser's autograd, one random crop of one view a step.

The learning rates are the 3DGS reference's (means 1.6e-4 of the scene's extent, log scales 5e-3, rotations 1e-3,
opacities 5e-2, colour 2.5e-3 and a twentieth of it for the higher SH bands) with its L1 + 0.2 D-SSIM loss. There is
no densification: the Gaussians start from a tree's leaves, which already cover the scene. The fit draws under the
compositing rules of the viewer the splats are meant for (``FitConfig.rules``): splats fitted under one renderer's
rules lose about 2 dB in a renderer with others.
"""
from __future__ import annotations

import math
import random
from dataclasses import dataclass, replace

import numpy as np
import torch

from nerfbake.data.cameras import Camera
from nerfbake.eval.metrics import patch_dssim
from nerfbake.kernels.splat_raster import REFERENCE, SplatRules
from nerfbake.progress import progress_bar
from nerfbake.splats.gaussians import FIELDS, Gaussians
from nerfbake.splats.rasterize import rasterize


@dataclass
class FitConfig:
    steps: int = 300
    crop: int = 128  # a crop of this many pixels a side per step (the whole view when it is smaller)
    lr_means: float = 1.6e-4  # times the extent of the Gaussians' centres
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_sh: float = 2.5e-3
    dssim_mult: float = 0.2
    seed: int = 0
    rules: SplatRules = REFERENCE  # the compositing of the viewer the splats are fitted for


def crop_camera(camera: Camera, x0: int, y0: int, w: int, h: int) -> Camera:
    """The part of ``camera``'s image from pixel (x0, y0), ``w`` x ``h`` pixels, as a camera of its own."""
    return replace(camera, width=w, height=h, cx=camera.cx - x0, cy=camera.cy - y0, c2w=camera.c2w.copy())


def fit_gaussians(g: Gaussians, views: list[tuple[Camera, np.ndarray]], cfg: FitConfig,
                  background=(1.0, 1.0, 1.0)) -> tuple[Gaussians, list[float]]:
    """``g`` fitted to ``views`` ((camera, (H, W, 3) image in [0, 1]) pairs); returns the fitted Gaussians and the
    PSNR of each step's crop before its update."""
    if not views:
        raise ValueError("fitting splats needs at least one target view")
    rng = random.Random(cfg.seed)
    params = {k: torch.nn.Parameter(torch.as_tensor(getattr(g, k), dtype=torch.float32).clone()) for k in FIELDS}
    extent = float(np.ptp(g.means, axis=0).max()) if len(g) > 1 else 1.0
    opt = torch.optim.Adam([
        {"params": [params["means"]], "lr": cfg.lr_means * extent},
        {"params": [params["log_scales"]], "lr": cfg.lr_scales},
        {"params": [params["quats"]], "lr": cfg.lr_quats},
        {"params": [params["opacity_logits"]], "lr": cfg.lr_opacity},
        {"params": [params["sh"]], "lr": cfg.lr_sh},
    ], eps=1e-15)
    rest_scale = torch.ones_like(params["sh"])
    rest_scale[:, :, 1:] = 1.0 / 20.0  # the higher bands learn at a twentieth of the rate (Adam: scale the step)
    history = []
    with progress_bar("fit splats", cfg.steps, unit="step") as advance:
        for _ in range(cfg.steps):
            camera, image = views[rng.randrange(len(views))]
            w, h = min(cfg.crop, camera.width), min(cfg.crop, camera.height)
            x0, y0 = rng.randrange(camera.width - w + 1), rng.randrange(camera.height - h + 1)
            target = torch.as_tensor(image[y0:y0 + h, x0:x0 + w], dtype=torch.float32)
            pred = rasterize(*(params[k] for k in FIELDS), crop_camera(camera, x0, y0, w, h), background,
                             cfg.rules)
            l1 = (pred - target).abs().mean()
            loss = (1 - cfg.dssim_mult) * l1
            if cfg.dssim_mult > 0 and h >= 3 and w >= 3:
                patches = pred[: h // 3 * 3, : w // 3 * 3].reshape(h // 3, 3, w // 3, 3, 3).permute(0, 2, 4, 1, 3)
                goal = target[: h // 3 * 3, : w // 3 * 3].reshape(h // 3, 3, w // 3, 3, 3).permute(0, 2, 4, 1, 3)
                loss = loss + cfg.dssim_mult * patch_dssim(patches.reshape(-1, 3, 3, 3), goal.reshape(-1, 3, 3, 3))
            opt.zero_grad()
            loss.backward()
            params["sh"].grad *= rest_scale
            opt.step()
            mse = float(((pred.detach().clamp(0, 1) - target) ** 2).mean())
            history.append(-10 * math.log10(max(mse, 1e-10)))
            advance(psnr=history[-1])
    out = {k: params[k].detach().double().numpy() for k in FIELDS}
    return Gaussians(**out), history
