"""SMERF's camera-based partition (paper section 3, eq. 6): the training cameras are normalised into [-1, 1]^3,
which is cut into K^3 cells; a submodel exists only where training cameras are, and every camera (training or
test) is rendered by the submodel whose cell holds it (the inf-norm nearest centre). Inside a submodel, points are
expressed as ``submodel_scale * (p - centre)`` before the contraction, with ``submodel_scale = K * factor``
(2.5 for K = 1, 0.8 for K > 1, as the authors' configs). The linear index is (i * K + j) * K + k, x slowest,
in the training frame, matching the viewer's ``sm_to_params`` lookup.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nerfbake.errors import NerfbakeError


class PartitionError(NerfbakeError):
    """A partition that cannot be made or read (no cameras, a bad record); names the cause and the fix."""


def layer_offsets(span: np.ndarray, k: int) -> np.ndarray:
    """Where, in cube units, the middle of the cameras' box goes along each axis (3,), given its ``span`` in cube
    units (3,): on an axis where the cameras span fewer than K cells (a walk at eye height, a row of rooms), the
    middle of the fewest whole cell layers that hold them, so no cell boundary runs through the cameras for
    nothing; 0 (the cube's middle) on the others.
    Centred on the cube, the two rooms' cameras at K = 2 straddled the mid-height and mid-depth boundaries too and
    came alive in 8 cells of 3 to 18 cameras each (of 80) instead of 2 of 40: each submodel learnt from an eighth
    of the rays where a half would do, and the rooms' floors and ceilings lay in the contracted shell of the cells
    above and below."""
    width = 2.0 / k
    out = np.zeros(3)
    for axis, extent in enumerate(np.asarray(span, np.float64)):
        layers = int(extent // width) + 1  # the fewest whole layers that hold the span with room to spare
        if layers < k:
            first = (k - layers) // 2
            out[axis] = -1.0 + (first + layers / 2) * width
    return out


MAX_FILL = 4.0  # fill_quantile grows the K = 1 submodel scale factor by at most this much


@dataclass
class Partition:
    """SMERF's K^3 camera-based partition: the scene normalised so the cameras fill [-1, 1]^3, cut into K^3 cells, a
    submodel for each cell that holds a training camera (``sm_to_params``: -1 for the others)."""
    k: int
    centre: np.ndarray  # normalisation: p_cube = (p - centre) * scale, cameras inside [-1, 1]^3
    scale: float
    sm_to_params: list[int]  # length K^3, -1 where no training camera is
    scale_factor: float

    @property
    def submodel_scale(self) -> float:
        return self.k * self.scale_factor

    @property
    def params_to_sm(self) -> list[int]:
        return [i for i, p in enumerate(self.sm_to_params) if p >= 0]

    @property
    def num_alive(self) -> int:
        return len(self.params_to_sm)

    @classmethod
    def from_cameras(cls, origins: np.ndarray, k: int, margin: float = 0.05, scale_factor: float | None = None,
                     surface_distances: np.ndarray | None = None, core_quantile: float = 0.1,
                     fill_quantile: float = 0.0) -> "Partition":
        """Normalise camera origins (N, 3) into [-1 + margin, 1 - margin]^3 (uniform scale) and mark alive cells.

        With K = 1 the cube is centred on the world origin, which the dataset loaders put at the scene's centre
        of interest, so the object lands in the middle of the submodel's uncontracted core; with K > 1 it is
        centred on the cameras' bounding box along their longest axis and placed along the others so that they
        occupy the fewest whole cell layers (:func:`layer_offsets`): no cells are wasted.

        ``surface_distances`` (M,): how far (inf-norm) from the world origin the training views' surfaces lie (at
        the teacher's median depths; K = 1 only). When even their ``core_quantile`` lies beyond the cameras' span
        (a scene seen from a small baseline), the cube grows until that share of them falls in the submodel's
        uncontracted core (``core_quantile`` 0: the cameras alone size it). Sized by its cameras alone, a
        forward-facing capture (fern: cameras within 0.4 of the origin, the scene 1.3 to 6 in front) put every
        surface in the outer 7 % of the contracted shell. Cameras around an object or among the surfaces of a room
        keep the cameras' cube, the authors' rule.

        ``fill_quantile`` (K = 1, 0: off): when that share of the surfaces lies well inside the core at the authors'
        factor (an object ringed by cameras), the factor grows, up to :data:`MAX_FILL` times, until they reach the
        core's face, so the grids spend their texels on the object rather than on the empty core around it."""
        if k < 1:
            raise PartitionError(f"K must be >= 1, got {k}")
        origins = np.asarray(origins, np.float64)
        if origins.ndim != 2 or origins.shape[0] == 0:
            raise PartitionError("no training cameras to partition")
        factor = scale_factor if scale_factor is not None else (2.5 if k == 1 else 0.8)
        lo, hi = origins.min(0), origins.max(0)
        centre = (lo + hi) / 2 if k > 1 else np.zeros(3)
        half = float(np.abs(origins - centre).max())
        surfaces = surface_distances if k == 1 and surface_distances is not None and len(surface_distances) else None
        if surfaces is not None and core_quantile > 0:
            reach = float(np.quantile(surfaces, core_quantile))
            if reach > half:  # the scene lies beyond the cameras' span: size the cube so ``reach`` meets the core's face
                half = factor * (1.0 - margin) * reach
        scale = (1.0 - margin) / half if half > 0 else 1.0
        if surfaces is not None and fill_quantile > 0 and scale_factor is None:
            extent = float(np.quantile(surfaces, fill_quantile)) * scale  # cube units
            if extent > 0:
                factor = float(np.clip((1.0 - margin) / extent, factor, MAX_FILL * factor))
        if k > 1 and half > 0:
            centre = centre - layer_offsets((hi - lo) * scale, k) / scale
        part = cls(k, centre, scale, [-1] * k ** 3, factor)
        alive = sorted(set(part.cell_index(part.normalize(origins)).tolist()))
        part.sm_to_params = [alive.index(i) if i in alive else -1 for i in range(k ** 3)]
        return part

    def normalize(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, np.float64) - self.centre) * self.scale

    def cell_index(self, cube_points: np.ndarray, strict: bool = False) -> np.ndarray:
        """Linear cell index of points in the [-1, 1]^3 frame (clamped to the cube unless ``strict``)."""
        p = np.asarray(cube_points, np.float64)
        if strict and (np.abs(p) > 1.0 + 1e-9).any():
            bad = int(np.argmax(np.abs(p).max(-1)))
            raise PartitionError(f"camera {bad} at {p[bad].round(3).tolist()} lies outside the partition cube [-1, 1]^3; "
                                 "the partition is built from the training cameras, so keep evaluation cameras inside "
                                 "their range")
        ijk = np.clip(np.floor((p + 1) / 2 * self.k), 0, self.k - 1).astype(int)
        return (ijk[..., 0] * self.k + ijk[..., 1]) * self.k + ijk[..., 2]

    def assign(self, world_origins: np.ndarray, strict: bool = False) -> np.ndarray:
        """Params index of the submodel that renders each camera: its own cell if alive, else the alive cell
        whose centre is nearest in the inf-norm (eq. 6)."""
        p = self.normalize(world_origins)
        cell = self.cell_index(p, strict)
        out = np.array([self.sm_to_params[c] for c in np.atleast_1d(cell)])
        dead = out < 0
        if dead.any():
            centres = np.stack([self.cell_centre(i) for i in self.params_to_sm])
            d = np.abs(np.atleast_2d(p)[dead][:, None, :] - centres[None]).max(-1)
            out[dead] = d.argmin(1)
        return out

    def cell_centre(self, sm: int) -> np.ndarray:
        k = self.k
        ijk = np.array([sm // (k * k), (sm // k) % k, sm % k], np.float64)
        return (ijk + 0.5) * (2.0 / k) - 1.0

    def to_submodel(self, world_points: torch.Tensor, params_idx: int) -> torch.Tensor:
        """World points -> the submodel's frame (before the contraction)."""
        c = self.cell_centre(self.params_to_sm[params_idx])
        centre = torch.as_tensor(self.centre, dtype=world_points.dtype, device=world_points.device)
        cc = torch.as_tensor(c, dtype=world_points.dtype, device=world_points.device)
        return ((world_points - centre) * self.scale - cc) * self.submodel_scale

    def neighbours(self, params_idx: int) -> list[int]:
        """Alive submodels whose cells touch this one's (26-neighbourhood), for ray reassignment and consistency."""
        k, sm = self.k, self.params_to_sm[params_idx]
        i, j, l = sm // (k * k), (sm // k) % k, sm % k
        out = []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                for dl in (-1, 0, 1):
                    a, b, c = i + di, j + dj, l + dl
                    if (di, dj, dl) != (0, 0, 0) and 0 <= a < k and 0 <= b < k and 0 <= c < k:
                        p = self.sm_to_params[(a * k + b) * k + c]
                        if p >= 0:
                            out.append(p)
        return out

    def baking_cameras(self, world_origins: np.ndarray, params_idx: int, radius: float = 1.5) -> np.ndarray:
        """(N,) bool: the cameras whose origins lie within ``radius`` cell widths of the submodel's cell centre, and
        those it renders (SMERF appendix C.2: a submodel's occupancy grid comes from the cameras within 1.5 units of
        its centre, cells being 1 unit wide). A submodel's own cameras alone leave holes where its test views look
        at what none of them saw, which the baked scene draws as background."""
        p = np.atleast_2d(self.normalize(world_origins))
        centre = self.cell_centre(self.params_to_sm[params_idx])
        near = np.linalg.norm(p - centre, axis=-1) * self.k / 2.0 <= radius
        return near | (self.assign(world_origins) == params_idx)

    def mlp_position(self, world_points: np.ndarray, params_idx: int) -> np.ndarray:
        """Where the deferred-MLP lattice of a submodel is sampled: the camera relative to the cell centre, in
        cell half-widths ([-1, 1]^3 over the cell; the viewer's ``(cam - centre) * K``)."""
        c = self.cell_centre(self.params_to_sm[params_idx])
        return (self.normalize(world_points) - c) * self.k

    def to_json(self) -> dict:
        return {"k": self.k, "centre": self.centre.tolist(), "scale": self.scale, "sm_to_params": self.sm_to_params,
                "scale_factor": self.scale_factor}

    @classmethod
    def from_json(cls, d: dict) -> "Partition":
        return cls(d["k"], np.asarray(d["centre"]), d["scale"], list(d["sm_to_params"]), d["scale_factor"])
