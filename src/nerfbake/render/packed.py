"""Compositing of *packed* samples: a flat list of intervals sorted by ray (what ray marching produces).

``ray_idx`` (S,) long, non-decreasing; ``t0``, ``t1`` (S,) interval ends; ``sigma`` (S,); ``rgb`` (S, 3).
Per-ray results have shape (R, ...). Transmittance is an exclusive, per-ray cumulative sum of
``log(1 - alpha)`` computed in float64 so long batches keep their precision. Same math as
:mod:`nerfbake.render.quadrature`, for ragged rays.
"""
from __future__ import annotations

import torch

from nerfbake.render.quadrature import alpha_from_density


def packed_weights(sigma: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor, ray_idx: torch.Tensor, num_rays: int):
    """Weights w = T·alpha (S,) and alpha (S,) for packed intervals."""
    alpha = alpha_from_density(sigma, t1 - t0)
    log_keep = torch.log1p(-alpha.clamp(max=1 - 1e-7)).double()
    csum = torch.cumsum(log_keep, 0)
    # Exclusive cumsum restarted at each ray: subtract the running total at the ray's first sample.
    excl = csum - log_keep
    first = torch.zeros(num_rays, dtype=torch.long, device=sigma.device)
    if ray_idx.numel():
        is_first = torch.ones_like(ray_idx, dtype=torch.bool)
        is_first[1:] = ray_idx[1:] != ray_idx[:-1]
        starts = torch.nonzero(is_first).squeeze(-1)
        first[ray_idx[starts]] = starts
    trans = (torch.exp(excl - excl[first[ray_idx]]) if ray_idx.numel() else excl).to(alpha.dtype)
    return trans * alpha, alpha


def packed_sum(values: torch.Tensor, ray_idx: torch.Tensor, num_rays: int) -> torch.Tensor:
    """Sum per ray of (S, ...) values -> (R, ...)."""
    out = torch.zeros((num_rays, *values.shape[1:]), dtype=values.dtype, device=values.device)
    return out.index_add(0, ray_idx, values)


def packed_composite(w, rgb, t0, t1, ray_idx, num_rays, background=None) -> dict[str, torch.Tensor]:
    """Colour, accumulated alpha and expected depth per ray from packed weights."""
    acc = packed_sum(w, ray_idx, num_rays)
    color = packed_sum(w[:, None] * rgb, ray_idx, num_rays)
    depth = packed_sum(w * 0.5 * (t0 + t1), ray_idx, num_rays)
    if background is not None:
        bg = torch.as_tensor(background, dtype=color.dtype, device=color.device)
        color = color + (1.0 - acc)[:, None] * bg
    return {"rgb": color, "acc": acc, "depth": depth}
