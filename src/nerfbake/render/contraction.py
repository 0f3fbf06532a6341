"""MERF's piecewise-projective contraction (SMERF paper eq. 5) and its inverse.

Points with inf-norm <= 1 are unchanged; outside, the coordinate that attains the inf-norm maps to
sign(x)(2 - 1/|x|) and the others are divided by the inf-norm, so the whole space lands in [-2, 2]^3
while straight lines stay straight inside each of the six pyramids x_j = ||x||_inf (what makes ray
marching exact). It is continuous across the unit cube's surface and inside each pyramid; across the
pyramids' shared edges (|x_i| = |x_j| > 1) it jumps, as the paper's definition implies.
SMERF applies it per submodel after scaling coordinates by the submodel scale factor.
"""
from __future__ import annotations

import torch

_EPS = 1e-12


def contract(x: torch.Tensor) -> torch.Tensor:
    """Map (..., 3) points into [-2, 2]^3."""
    mag = x.abs()
    inf = mag.amax(dim=-1, keepdim=True)
    outside = inf > 1.0
    inf_safe = inf.clamp_min(1.0)
    is_max = mag >= inf  # the coordinate(s) attaining the inf-norm
    scaled = x / inf_safe
    edge = torch.sign(x) * (2.0 - 1.0 / mag.clamp_min(_EPS))
    return torch.where(outside, torch.where(is_max, edge, scaled), x)


def uncontract(c: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`contract` for (..., 3) points with inf-norm < 2."""
    mag = c.abs()
    inf_c = mag.amax(dim=-1, keepdim=True)
    outside = inf_c > 1.0
    inf_x = 1.0 / (2.0 - inf_c.clamp(1.0, 2.0 - 1e-7))  # inf-norm of the original point
    is_max = mag >= inf_c
    edge = torch.sign(c) * inf_x
    scaled = c * inf_x
    return torch.where(outside, torch.where(is_max, edge, scaled), c)
