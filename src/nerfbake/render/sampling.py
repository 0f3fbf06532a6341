"""Placing intervals along rays: uniform, stratified and inverse-CDF (hierarchical) sampling.

``t`` are interval endpoints (..., S+1) in world distance; ``w`` (..., S) weights on those intervals.
"""
from __future__ import annotations

import torch


def uniform_t(near: torch.Tensor, far: torch.Tensor, num_intervals: int) -> torch.Tensor:
    """Evenly spaced endpoints (..., S+1) between ``near`` and ``far`` (broadcastable (...,) tensors)."""
    u = torch.linspace(0.0, 1.0, num_intervals + 1, device=near.device, dtype=near.dtype)
    return near[..., None] + (far - near)[..., None] * u


def stratified_t(
    near: torch.Tensor, far: torch.Tensor, num_intervals: int, generator: torch.Generator | None = None,
    u: torch.Tensor | None = None,
) -> torch.Tensor:
    """Uniform endpoints with each interior endpoint jittered within its stratum (still sorted).

    The jitter comes from ``u`` (..., S+1) uniforms when given (so callers can draw a whole batch's randomness
    up front), else from ``generator``."""
    t = uniform_t(near, far, num_intervals)
    mid = 0.5 * (t[..., 1:] + t[..., :-1])
    lo = torch.cat([t[..., :1], mid], dim=-1)
    hi = torch.cat([mid, t[..., -1:]], dim=-1)
    if u is None:
        u = torch.rand(t.shape, generator=generator, device=t.device, dtype=t.dtype)
    jittered = lo + (hi - lo) * u
    # Keep the ray's extent exactly [near, far].
    return torch.cat([t[..., :1], jittered[..., 1:-1], t[..., -1:]], dim=-1)


def midpoints(t: torch.Tensor) -> torch.Tensor:
    """Interval centres (..., S)."""
    return 0.5 * (t[..., 1:] + t[..., :-1])


def sample_pdf(
    t: torch.Tensor,
    w: torch.Tensor,
    num_samples: int,
    deterministic: bool = False,
    generator: torch.Generator | None = None,
    eps: float = 1e-5,
    u: torch.Tensor | None = None,
    stratified: bool = False,
) -> torch.Tensor:
    """Draw ``num_samples`` sorted positions (..., num_samples) from the piecewise-constant pdf ``w`` on ``t``.

    Inverse transform sampling of the histogram (NeRF's hierarchical sampling). ``deterministic`` uses
    evenly spaced quantiles instead of random ones (for evaluation); ``u`` (..., num_samples) supplies the
    random quantiles instead of ``generator``. ``stratified`` puts random quantile i of n in [i/n, (i+1)/n)
    (mip-NeRF 360's draw) instead of sorting independent ones, whose gaps vary widely.
    """
    w = w + eps
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, dim=-1)], dim=-1).clamp(max=1.0)
    shape = (*cdf.shape[:-1], num_samples)
    if deterministic:
        u = torch.linspace(0.0, 1.0, num_samples, device=t.device, dtype=t.dtype).expand(shape)
    else:
        if u is None:
            u = torch.rand(shape, generator=generator, device=t.device, dtype=t.dtype)
        if stratified:
            u = (torch.arange(num_samples, device=u.device, dtype=u.dtype) + u) / num_samples
        else:
            u, _ = torch.sort(u, dim=-1)
    u = u.contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True).clamp(1, cdf.shape[-1] - 1)
    below, above = idx - 1, idx
    cdf_lo, cdf_hi = cdf.gather(-1, below), cdf.gather(-1, above)
    t_lo, t_hi = t.gather(-1, below), t.gather(-1, above)
    denom = torch.where(cdf_hi - cdf_lo < 1e-12, torch.ones_like(cdf_hi), cdf_hi - cdf_lo)
    frac = ((u - cdf_lo) / denom).clamp(0.0, 1.0)
    return t_lo + frac * (t_hi - t_lo)
