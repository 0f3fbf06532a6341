"""The 8-bit quantisation SMERF bakes with, and its straight-through simulation during training.

Baking stores ``round(255 * sigmoid(x))`` as uint8; the viewer reads ``min + byte / 255 * (max - min)`` with the
ranges of ``scene_params.json`` (features and the gate [-7, 7], density [-14, 14]). Training applies the same
round trip in the forward pass and passes gradients straight through (the authors' ``simulate_quantization``), so
the student is trained on exactly the values the viewer will see.
"""
from __future__ import annotations

import numpy as np
import torch

RANGE_FEATURES = (-7.0, 7.0)
RANGE_DENSITY = (-14.0, 14.0)


def to_bytes(x: np.ndarray | torch.Tensor, value_range: tuple[float, float]) -> np.ndarray:
    """Pre-activation values -> uint8 as the baker writes them (values are clipped to the range first)."""
    x = torch.as_tensor(x, dtype=torch.float64)
    lo, hi = value_range
    unit = (x.clamp(lo, hi) - lo) / (hi - lo)
    return torch.round(255.0 * unit).to(torch.uint8).numpy()


def from_bytes(b: np.ndarray, value_range: tuple[float, float]) -> np.ndarray:
    """uint8 -> the value the viewer's shader reconstructs."""
    lo, hi = value_range
    return lo + b.astype(np.float64) / 255.0 * (hi - lo)


def simulate(x: torch.Tensor, value_range: tuple[float, float]) -> torch.Tensor:
    """Forward: the byte round trip (clip, 256 levels); backward: identity (straight-through)."""
    lo, hi = value_range
    q = torch.round((x.clamp(lo, hi) - lo) / (hi - lo) * 255.0) / 255.0 * (hi - lo) + lo
    return x + (q - x).detach()
