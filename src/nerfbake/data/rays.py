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


class CameraBatch:
    """Every camera of a set as tensors, so rays for any (camera, pixel) batch come from one vectorised formula."""

    def __init__(self, cameras: list[Camera], device: torch.device | str = "cpu"):
        self.c2w = torch.tensor(np.stack([c.c2w for c in cameras]), dtype=torch.float64, device=device)
        self.intrinsics = torch.tensor([[c.fx, c.fy, c.cx, c.cy] for c in cameras], dtype=torch.float64, device=device)
        self.sizes = np.array([[c.width, c.height] for c in cameras])
        keys = ("k1", "k2", "k3", "k4", "p1", "p2")
        dist = np.array([[c.distortion.get(k, 0.0) for k in keys] for c in cameras], dtype=np.float64)
        self.distortion = torch.tensor(dist, device=device) if np.any(dist) else None

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def rays(self, cam_idx: torch.Tensor, pixels_xy: torch.Tensor) -> dict[str, torch.Tensor]:
        """Rays through the centres of pixels (col, row) (..., 2) of cameras ``cam_idx`` (...)."""
        shape = cam_idx.shape
        cam_idx = cam_idx.reshape(-1)
        pix = pixels_xy.reshape(-1, 2).to(torch.float64)
        fx, fy, cx, cy = self.intrinsics[cam_idx].unbind(-1)
        xd = (pix[:, 0] + 0.5 - cx) / fx
        yd = (pix[:, 1] + 0.5 - cy) / fy
        if self.distortion is not None:
            d = self.distortion[cam_idx]
            x, y = undistort(xd, yd, {k: d[:, i] for i, k in enumerate(("k1", "k2", "k3", "k4", "p1", "p2"))})
        else:
            x, y = xd, yd
        dirs_cam = torch.stack([x, -y, -torch.ones_like(x)], dim=-1)  # OpenCV normalised -> OpenGL camera axes
        norm = dirs_cam.norm(dim=-1, keepdim=True)
        c2w = self.c2w[cam_idx]
        dirs = torch.einsum("nij,nj->ni", c2w[:, :3, :3], dirs_cam / norm)
        out = {
            "origins": c2w[:, :3, 3].to(torch.float32),
            "directions": dirs.to(torch.float32),
            "z_scale": (1.0 / norm[:, 0]).to(torch.float32),
            "cam_idx": cam_idx,
        }
        return {k: v.reshape(*shape, *v.shape[1:]) for k, v in out.items()}


def pixel_grid(width: int, height: int) -> torch.Tensor:
    """(H, W, 2) integer (col, row) coordinates of every pixel."""
    rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    return torch.stack([cols, rows], dim=-1)


def camera_rays(camera: Camera, pixels_xy: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Rays of one camera: through ``pixels_xy`` (N, 2) (col, row), or every pixel as (H, W, ...) arrays."""
    if pixels_xy is None:
        pixels_xy = pixel_grid(camera.width, camera.height)
    cam_idx = torch.zeros(pixels_xy.shape[:-1], dtype=torch.long)
    return CameraBatch([camera]).rays(cam_idx, pixels_xy)


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
