"""The space around the training cameras that the teacher never rendered, taken as empty by what is baked from it.

A teacher's rays start at its near bound (0.9 x the sparse points' nearest depth for real captures), so nothing
within that distance of a training camera ever reached a photo: the field there holds whatever the hash grid started
with or collided into, and ``density_at`` reports it. The teacher's own renders never show it, but a student
warm-started from those densities, or fitted to them at random points, and an octree cut from them, do, because
the viewer marches from its own, much smaller near plane (the phone clip's baked scene: coloured blocks over the
floor nearest the camera, 20.3 dB against 24.8 with the viewer's near plane moved to the teacher's). The sparse
points say no surface is that close to any camera, so the bakers read the teacher through
:meth:`CameraClearance.density`, which is zero inside those balls.
"""
from __future__ import annotations

import numpy as np
import torch


class CameraClearance:
    """Balls of radius ``radius`` (the teacher's near bound) around the training camera centres ``origins`` (N, 3),
    in the teacher's world frame."""

    def __init__(self, origins, radius: float, chunk: int = 1 << 16):
        self.origins = torch.as_tensor(np.asarray(origins, np.float32)).reshape(-1, 3)
        self.radius = float(radius)
        self.chunk = chunk

    @classmethod
    def of_teacher(cls, teacher_meta: dict, cameras) -> "CameraClearance":
        """The clearance of a teacher run (its ``config.json`` as loaded) around its training ``cameras``."""
        return cls(np.stack([c.origin for c in cameras]), teacher_meta["box"]["near"])

    def inside(self, x: torch.Tensor) -> torch.Tensor:
        """Points (M, 3) -> bool (M,): within ``radius`` of some training camera."""
        out = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        if self.radius <= 0 or self.origins.shape[0] == 0:
            return out
        o = self.origins.to(x.device)
        near_box = ((x >= o.min(0).values - self.radius) & (x <= o.max(0).values + self.radius)).all(-1)
        idx = torch.nonzero(near_box)[:, 0]
        for a in range(0, idx.numel(), self.chunk):
            part = idx[a:a + self.chunk]
            out[part] = torch.cdist(x[part].float(), o).amin(-1) <= self.radius
        return out

    def density(self, teacher, x: torch.Tensor) -> torch.Tensor:
        """The teacher's ``density_at(x)`` with the clearance emptied."""
        sigma = teacher.density_at(x)
        return torch.where(self.inside(x), torch.zeros_like(sigma), sigma)
