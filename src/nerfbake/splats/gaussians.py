"""Gaussians as the 3DGS reference code stores them: means, log scales, w-first unit quaternions, pre-sigmoid
opacities and SH coefficients whose colour is ``max(SH(d) . k + 0.5, 0)`` (not PlenOctrees' sigmoid)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SH_C0 = 0.28209479177387814  # the degree-0 basis value: colour = SH_C0 * f_dc + 0.5 seen from any direction
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")  # in the rasteriser's argument order


@dataclass
class Gaussians:
    """N Gaussians: ``means`` (N, 3) world, ``log_scales`` (N, 3), ``quats`` (N, 4) w-first, ``opacity_logits`` (N,),
    ``sh`` (N, 3, B) per colour channel, B = (degree + 1)^2 (``sh[:, :, 0]`` is 3DGS's ``f_dc``)."""
    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __post_init__(self):
        n = self.means.shape[0]
        shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"Gaussians.{name} has shape {getattr(self, name).shape}, expected {shape}")
        if self.sh.ndim != 3 or self.sh.shape[:2] != (n, 3) or self.sh.shape[2] not in (1, 4, 9, 16):
            raise ValueError(f"Gaussians.sh has shape {self.sh.shape}, expected ({n}, 3, B) with B in 1, 4, 9, 16")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round(self.sh.shape[2] ** 0.5)) - 1

    @property
    def opacities(self) -> np.ndarray:
        """(N,) in [0, 1]."""
        return 1.0 / (1.0 + np.exp(-self.opacity_logits))

    @property
    def base_colors(self) -> np.ndarray:
        """(N, 3) the view-independent colour (degree 0 only), as compact formats store it."""
        return np.clip(SH_C0 * self.sh[:, :, 0] + 0.5, 0.0, 1.0)


def concatenate(parts: list[Gaussians]) -> Gaussians:
    """One set of Gaussians from several with the same SH degree."""
    return Gaussians(**{k: np.concatenate([getattr(g, k) for g in parts]) for k in FIELDS})
