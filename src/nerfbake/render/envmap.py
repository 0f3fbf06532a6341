"""Environment maps: colour at infinity by direction, stored as an equirectangular image.

A PlenOctree covers one box. What a capture shows beyond it (the room around bonsai, the sky) is drawn from an
environment map baked from the teacher. Convention, shared by every renderer (torch here, the Warp front end,
the browser's shader): texel (row i, column j) of an (H, W, 3) map holds the colour seen in direction
``(sin th cos ph, sin th sin ph, cos th)`` with ``ph = 2 pi ((j + 0.5) / W - 0.5)`` and ``th = pi (i + 0.5) / H``
(row 0 looks along +z). Lookups are bilinear between texel centres, wrapping around in ph and clamped at the
poles: exactly a WebGL texture with LINEAR filtering, REPEAT in s and CLAMP_TO_EDGE in t.
"""
from __future__ import annotations

import math

import torch


def equirect_angles(height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Polar angle th and azimuth ph (each (H, W), float64) at the texel centres of an H x W map."""
    th = math.pi * (torch.arange(height, dtype=torch.float64) + 0.5) / height
    ph = 2 * math.pi * ((torch.arange(width, dtype=torch.float64) + 0.5) / width - 0.5)
    return torch.meshgrid(th, ph, indexing="ij")


def equirect_directions(height: int, width: int) -> torch.Tensor:
    """Unit directions (H, W, 3) at the texel centres of an H x W map."""
    th, ph = equirect_angles(height, width)
    return torch.stack([th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()], -1).float()


def equirect_coords(dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Texture coordinates (s, t) in [0, 1] of directions (..., 3) (any length)."""
    unit = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    s = torch.atan2(unit[..., 1], unit[..., 0]) / (2 * math.pi) + 0.5
    t = torch.acos(unit[..., 2].clamp(-1.0, 1.0)) / math.pi
    return s, t


def sample_equirect(env: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of an (H, W, 3) map in directions (R, 3) -> (R, 3)."""
    h, w = env.shape[:2]
    s, t = equirect_coords(dirs.to(env.device, torch.float32))
    x, y = s * w - 0.5, (t * h - 0.5).clamp(0.0, h - 1.0)
    x0, y0 = x.floor(), y.floor()
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    i0 = y0.long().clamp(0, h - 1)
    i1 = (i0 + 1).clamp(max=h - 1)
    j0 = x0.long() % w
    j1 = (j0 + 1) % w
    env = env.float()
    top = env[i0, j0] * (1 - fx) + env[i0, j1] * fx
    bottom = env[i1, j0] * (1 - fx) + env[i1, j1] * fx
    return top * (1 - fy) + bottom * fy
