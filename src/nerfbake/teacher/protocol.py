"""What a route may ask of a teacher. Both fields' teachers (``HashTeacher``, ``NeRFSHTeacher``) implement it; the
octree route (building, the environment map) and the SMERF route (distillation, baking, seams) type against it
and call nothing else, so a new teacher field is added by implementing these members (and a loader entry in
``teacher/run.py``).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

from nerfbake.teacher.models import SceneBox


@runtime_checkable
class Teacher(Protocol):
    kind: str  # "hash" or "nerf-sh": recorded in run folders and reports
    box: SceneBox  # the scene's bounds, near/far and whether it is contracted
    background: torch.nn.Module | None  # a learned directional background (or None): colour for rays that leave

    @property
    def sh_degree(self) -> int:
        """Degree of the spherical harmonics ``query`` returns (B = (sh_degree + 1)^2 coefficients per channel)."""

    @property
    def noise_dims(self) -> int:
        """Uniform random numbers (in [0, 1)) one training ray of ``render_rays`` consumes."""

    def query(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points (N, 3) -> density ``sigma`` (N,) and SH coefficients (N, 3 * B), channel-major (octree leaves)."""

    def density_at(self, x: torch.Tensor) -> torch.Tensor:
        """Points (N, 3) -> sigma (N,) as the renderer sees the scene: zero where it never samples."""

    def may_be_occupied(self, x: torch.Tensor) -> torch.Tensor:
        """Points (N, 3) -> bool (N,): False only where the teacher is known to be empty (its occupancy grid grown
        by one cell), so a builder can skip querying there."""

    def render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, background: torch.Tensor | None = None,
                    noise: torch.Tensor | None = None) -> dict:
        """Rays (R, 3) + (R, 3) -> ``rgb`` (R, 3), ``acc`` (R,), ``depth`` (R,) and the packed intervals ``ray_idx``,
        ``t0``, ``t1`` (S,) with their compositing weights ``w`` (S,). ``noise`` (R, noise_dims) jitters the samples
        (a training render); None renders deterministically."""

    def to(self, *args, **kwargs) -> "Teacher":
        ...

    def parameters(self, recurse: bool = True):
        ...
