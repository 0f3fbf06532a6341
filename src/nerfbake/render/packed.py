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
    log_keep = torch.log1p(-alpha.clamp(max=1 - 1e-7))
    trans = torch.exp(packed_exclusive_cumsum(log_keep, ray_idx)).to(alpha.dtype)
    return trans * alpha, alpha


def packed_exclusive_cumsum(values: torch.Tensor, ray_idx: torch.Tensor) -> torch.Tensor:
    """Per-ray exclusive cumulative sum of (S,) values (0 at each ray's first sample), summed in float64."""
    if not ray_idx.numel():
        return values.double()
    v = values.double()
    excl = torch.cumsum(v, 0) - v
    is_first = torch.ones_like(ray_idx, dtype=torch.bool)
    is_first[1:] = ray_idx[1:] != ray_idx[:-1]
    pos = torch.arange(ray_idx.numel(), device=ray_idx.device)
    first = torch.cummax(torch.where(is_first, pos, torch.zeros_like(pos)), 0).values  # each sample's ray start
    return excl - excl[first]


def packed_distortion_loss(s0: torch.Tensor, s1: torch.Tensor, w: torch.Tensor, ray_idx: torch.Tensor,
                           num_rays: int) -> torch.Tensor:
    """mip-NeRF 360 eq. 15 (the O(S) form of :func:`nerfbake.render.stepfun.distortion_loss`) for packed intervals
    in normalised distance ``s0``..``s1`` (S,), mean over ``num_rays`` rays (rays with no samples count as 0)."""
    mid = 0.5 * (s0 + s1)
    w_before = packed_exclusive_cumsum(w, ray_idx).to(w.dtype)
    wm_before = packed_exclusive_cumsum(w * mid, ray_idx).to(w.dtype)
    inter = 2 * (w * (mid * w_before - wm_before)).sum()
    intra = (w.square() * (s1 - s0)).sum() / 3
    return (inter + intra) / max(1, num_rays)


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


def packed_median_depth(w: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor, ray_idx: torch.Tensor,
                        num_rays: int) -> torch.Tensor:
    """(R,) depth where each ray's accumulated weight first reaches half its total (the midpoint of that interval);
    inf for rays with no weight. Unlike the expected depth it is not pulled off a surface by a far background."""
    total = packed_sum(w, ray_idx, num_rays)
    reached = packed_exclusive_cumsum(w, ray_idx) + w.double() >= 0.5 * total.double()[ray_idx]
    return _first_where(reached & (w > 0), 0.5 * (t0 + t1), ray_idx, num_rays)


def packed_free_depth(w: torch.Tensor, t0: torch.Tensor, ray_idx: torch.Tensor, num_rays: int,
                      weight: float) -> torch.Tensor:
    """(R,) distance each ray travels before its accumulated weight first exceeds ``weight`` (the start of the
    interval where it does): the stretch in front of the first surface. inf for rays that never reach it."""
    reached = packed_exclusive_cumsum(w, ray_idx) + w.double() > weight
    return _first_where(reached, t0, ray_idx, num_rays)


def _first_where(cond: torch.Tensor, t: torch.Tensor, ray_idx: torch.Tensor, num_rays: int) -> torch.Tensor:
    """(R,) the smallest ``t`` (S,) of each ray's samples where ``cond`` holds (its first, for ascending t); inf
    where it holds for none."""
    out = torch.full((num_rays,), float("inf"), dtype=t.dtype, device=t.device)
    return out.scatter_reduce(0, ray_idx, torch.where(cond, t, torch.full_like(t, float("inf"))), reduce="amin")
