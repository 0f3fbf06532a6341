"""Rays from cameras: per image, random batches, and random 3x3 patches (SMERF's SSIM loss needs patches).

A ray batch is a dict of tensors with leading shape (...): ``origins`` (...,3), ``directions`` (...,3) unit
length in world space, ``cam_idx`` (...) long, and ``pixels`` (...,2) long (column, row) when drawn from images.
Depth along a ray is therefore world distance; ``z_scale`` (...) = cos angle to the optical axis converts it to
the camera's z-depth.
"""
from __future__ import annotations

import numpy as np
import torch

from nerfbake.data.cameras import Camera, undistort


def camera_rays(camera: Camera, pixels_xy: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Rays through pixel centres. ``pixels_xy`` (N,2) float pixel coordinates (col, row) of the pixel's corner;
    None means every pixel, returned with shape (H, W, ...)."""
    grid_shape = None
    if pixels_xy is None:
        rows, cols = torch.meshgrid(
            torch.arange(camera.height, dtype=torch.float64), torch.arange(camera.width, dtype=torch.float64), indexing="ij"
        )
        pixels_xy = torch.stack([cols, rows], dim=-1).reshape(-1, 2)
        grid_shape = (camera.height, camera.width)
    pixels_xy = pixels_xy.to(torch.float64)
    xd = (pixels_xy[:, 0] + 0.5 - camera.cx) / camera.fx
    yd = (pixels_xy[:, 1] + 0.5 - camera.cy) / camera.fy
    x, y = undistort(xd, yd, camera.distortion)
    dirs_cam = torch.stack([x, -y, -torch.ones_like(x)], dim=-1)  # OpenCV normalised -> OpenGL camera axes
    norm = dirs_cam.norm(dim=-1, keepdim=True)
    c2w = torch.from_numpy(camera.c2w)
    dirs = (dirs_cam / norm) @ c2w[:3, :3].T
    origins = c2w[:3, 3].expand_as(dirs)
    out = {
        "origins": origins.to(torch.float32),
        "directions": dirs.to(torch.float32),
        "z_scale": (1.0 / norm[:, 0]).to(torch.float32),
    }
    if grid_shape is not None:
        out = {k: v.reshape(*grid_shape, *v.shape[1:]) for k, v in out.items()}
    return out


def random_pixels(
    num_rays: int, sizes: np.ndarray, cam_indices: np.ndarray, generator: torch.Generator, patch: int = 1
) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw ``num_rays`` pixels uniformly over a set of images, as ``patch`` x ``patch`` squares.

    ``sizes`` (C,2) width, height of each camera in ``cam_indices``. Returns (cam_idx (P, patch, patch), pixels
    (P, patch, patch, 2) (col, row)) with P = num_rays // patch^2; patches lie wholly inside their image.
    """
    num_patches = max(1, num_rays // (patch * patch))
    choice = torch.randint(0, len(cam_indices), (num_patches,), generator=generator)
    cam = torch.as_tensor(cam_indices)[choice]
    wh = torch.as_tensor(sizes)[choice]
    u = torch.rand((num_patches, 2), generator=generator, dtype=torch.float64)
    corner = (u * (wh - patch + 1).to(torch.float64)).floor().long()
    offs = torch.stack(torch.meshgrid(torch.arange(patch), torch.arange(patch), indexing="ij"), dim=-1).flip(-1)
    pixels = corner[:, None, None, :] + offs[None]
    return cam[:, None, None].expand(-1, patch, patch), pixels


def ndc_rays(origins: torch.Tensor, directions: torch.Tensor, fx: float, fy: float, width: int, height: int, near: float = 1.0):
    """Map forward-facing rays into NeRF's normalised device coordinates (LLFF scenes).

    Origins are first moved to the plane z = -near; the returned directions are not unit length.
    """
    t = -(near + origins[..., 2]) / directions[..., 2]
    o = origins + t[..., None] * directions
    ox, oy, oz = o.unbind(-1)
    dx, dy, dz = directions.unbind(-1)
    o_ndc = torch.stack([-fx / (width / 2) * ox / oz, -fy / (height / 2) * oy / oz, 1 + 2 * near / oz], dim=-1)
    d_ndc = torch.stack(
        [-fx / (width / 2) * (dx / dz - ox / oz), -fy / (height / 2) * (dy / dz - oy / oz), -2 * near / oz], dim=-1
    )
    return o_ndc, d_ndc
