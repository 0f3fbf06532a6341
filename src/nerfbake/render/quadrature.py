"""The volume-rendering quadrature of NeRF (Max 1995): alpha, transmittance, weights, compositing.

Every renderer in nerfbake (teacher, octree reference, student, baked reference) composites through
these functions so that "the same scene" means the same numbers everywhere.
"""
from __future__ import annotations

import torch


def alpha_from_density(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """alpha_i = 1 - exp(-sigma_i * delta_i); sigma (..., S) >= 0, delta (..., S) interval lengths."""
    return -torch.expm1(-sigma * delta)


def transmittance_from_alpha(alpha: torch.Tensor) -> torch.Tensor:
    """T_i = prod_{j<i} (1 - alpha_j), the light reaching interval i. Returns (..., S+1): T_0 = 1, T_S is what is left."""
    ones = torch.ones_like(alpha[..., :1])
    return torch.cumprod(torch.cat([ones, 1.0 - alpha], dim=-1), dim=-1)


def weights_from_alpha(alpha: torch.Tensor) -> torch.Tensor:
    """w_i = T_i * alpha_i, (..., S); sums to 1 - T_S <= 1."""
    return alpha * transmittance_from_alpha(alpha)[..., :-1]


def weights_from_density(sigma: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights and alphas for densities on intervals ``t`` (..., S+1). Returns (w, alpha)."""
    delta = t[..., 1:] - t[..., :-1]
    alpha = alpha_from_density(sigma, delta)
    return weights_from_alpha(alpha), alpha


def composite(
    w: torch.Tensor,
    rgb: torch.Tensor,
    background: torch.Tensor | float | None = None,
    t: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Composite per-interval colours. Returns ``rgb`` (..., 3), ``acc`` (...,) and, with ``t``, expected ``depth``.

    ``background`` (a float, (3,) or (..., 3)) fills the remaining transmittance 1 - acc.
    """
    acc = w.sum(dim=-1)
    color = (w[..., None] * rgb).sum(dim=-2)
    if background is not None:
        color = color + (1.0 - acc)[..., None] * torch.as_tensor(background, dtype=color.dtype, device=color.device)
    out = {"rgb": color, "acc": acc}
    if t is not None:
        mid = 0.5 * (t[..., 1:] + t[..., :-1])
        out["depth"] = (w * mid).sum(dim=-1)
    return out
