"""The SMERF student: per submodel, MERF's 8 channels (density, diffuse RGB, 3 view features, gate) on a sparse
S^3 grid plus three T^2 planes in the submodel's contracted space, feature gating (SMERF eq. 8-9) and the
deferred MLP on the P^3 camera lattice (eq. 7).

The grids are the trainable parameters themselves, stored in the viewer's axis order and read through the same
8-bit round trip and interpolation the viewer applies (:mod:`nerfbake.kernels.merf_grid`), so baking is a copy:
what the student renders on a ray is what the baked assets give at the same samples. (The authors train a hash
encoding + MLP evaluated at grid vertices; on a CPU that costs ~20 field evaluations per sample, so nerfbake
optimises the vertex values directly, the "explicit grid" form MERF compares against.)

Frames: world -> partition cube ``(p - centre) * scale`` -> viewer axes (x, y, z) -> (-x, z, y) -> submodel frame
``submodel_scale * (p' - cell centre')`` -> MERF contraction into [-2, 2]^3. Densities are per cube unit, as the
viewer's step lengths are.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from nerfbake.kernels.merf_grid import CHANNELS, merf_lookup
from nerfbake.render.contraction import contract, uncontract
from nerfbake.render.packed import packed_sum, packed_weights
from nerfbake.smerf.assets import VIEWER_FROM_TRAIN
from nerfbake.smerf.deferred_mlp import GridMLP, deferred_inputs
from nerfbake.smerf.partition import Partition


def _axes_like(x: torch.Tensor) -> torch.Tensor:
    """:data:`VIEWER_FROM_TRAIN` as a tensor of ``x``'s dtype and device."""
    return torch.from_numpy(VIEWER_FROM_TRAIN).to(x)


BACKGROUND = (0.5, 0.5, 0.5)  # the viewer's default background, entering only through the MLP input (SNeRG mode)


@dataclass
class StudentConfig:
    """A submodel's sizes: S^3 sparse grid, T^2 planes, the P^3 grid of deferred MLPs, and the grids' starting
    values."""
    sparse_resolution: int = 128  # S (paper 512)
    triplane_resolution: int = 1024  # T (paper 2048)
    mlp_grid: int | None = 1  # P (mlp_lattice_size); None is how students before one MLP at every K recorded it
    mlp_width: int = 16
    init_density: float = 1.0  # sparse density pre-activation at start: exp(1 - 1) = 1 per cube unit
    init_gate: float = 1.0  # so the planes contribute from the first step


def mlp_lattice_size(cfg: StudentConfig, k: int) -> int:
    """P of the deferred-MLP lattice: ``cfg.mlp_grid`` (one MLP per submodel, MERF's deferred MLP, unless set; the
    paper preset sets the authors' 5^3). SMERF's lattice buys 0.58 dB on its large scenes, trained 50k+ steps with
    thousands of cameras; a CPU run gives each of a submodel's 125 MLPs a few cameras' rays, and held-out views fall
    between them. `make demo`'s scene (K = 1), baked: 30.91 -> 32.11 dB with one MLP (figures in
    :func:`nerfbake.pipeline.demo_config`); the 280-view house at K = 2 (S = 32, T = 128, 1000 steps): student
    24.15 -> 24.26, baked 24.42 -> 24.47, and the largest submodel folder 1.40 -> 0.20 MB, since every folder
    repeats the MLPs of all submodels. ``None``, recorded by students from before that default: one at K = 1, 5^3
    above."""
    if cfg.mlp_grid is not None:
        return cfg.mlp_grid
    return 1 if k == 1 else 5


class Student(nn.Module):
    """The MERF-style student of every alive submodel: sparse grids (alive * S^3, 8) and planes (alive * 3 * T^2, 8)
    read through the viewer's 8-bit round trip, and the grid of deferred MLPs."""
    def __init__(self, cfg: StudentConfig, partition: Partition, seed: int = 0):
        super().__init__()
        self.cfg, self.partition = cfg, partition
        n, s, t = partition.num_alive, cfg.sparse_resolution, cfg.triplane_resolution
        sparse = torch.zeros(n * s ** 3, CHANNELS)
        sparse[:, 0] = cfg.init_density
        sparse[:, 7] = cfg.init_gate
        self.sparse = nn.Parameter(sparse)
        self.planes = nn.Parameter(torch.zeros(n * 3 * t * t, CHANNELS))
        self.touched: tuple[torch.Tensor, None] | None = None  # see row_masks
        self.mlp = GridMLP(n, width=cfg.mlp_width, grid=mlp_lattice_size(cfg, partition.k),
                           generator=torch.Generator().manual_seed(seed))
        cells = torch.tensor(np.stack([partition.cell_centre(i) for i in partition.params_to_sm]), dtype=torch.float32)
        self.register_buffer("cell_centres", cells, persistent=False)

    def row_masks(self) -> dict:
        """The sparse grid -> a uint8 mask over its rows that the lookup's backward sets from now on, for a
        :class:`~nerfbake.train.row_adam.RowAdam` (call it after moving the student to its device). Only the
        sparse grid: a bonsai step writes 3 % of its rows but a quarter of the planes' rows, where dense Adam's
        streaming beats visiting rows one by one."""
        if self.touched is None:
            self.touched = (torch.zeros(self.sparse.shape[0], dtype=torch.uint8, device=self.sparse.device), None)
        return {self.sparse: self.touched[0]}

    # ---- frames -------------------------------------------------------------------------------------------
    def to_cube(self, world: torch.Tensor) -> torch.Tensor:
        centre = torch.as_tensor(self.partition.centre, dtype=world.dtype, device=world.device)
        return (world - centre) * self.partition.scale

    def contracted(self, world: torch.Tensor, params_idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points (N, 3) -> contracted submodel coordinates in viewer axes (N, 3) and the inf-norm of the
        uncontracted submodel point (how much the contraction squeezes there)."""
        local = (self.to_cube(world) - self.cell_centres[params_idx]) * self.partition.submodel_scale
        local = local @ _axes_like(local).T
        return contract(local), local.abs().amax(-1)

    def world_from_contracted(self, z: torch.Tensor, params_idx: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`contracted`: contracted submodel points (viewer axes) -> world points."""
        local = uncontract(z) @ _axes_like(z)  # the axis map is its own inverse (and symmetric)
        cube = local / self.partition.submodel_scale + self.cell_centres[params_idx]
        centre = torch.as_tensor(self.partition.centre, dtype=z.dtype, device=z.device)
        return cube / self.partition.scale + centre

    def mlp_position(self, world_origins: torch.Tensor, params_idx: torch.Tensor) -> torch.Tensor:
        """Where the MLP lattice is read: the camera relative to its cell centre, in cell half-widths."""
        return (self.to_cube(world_origins) - self.cell_centres[params_idx]) * self.partition.k

    def realtime_step(self, stretch: torch.Tensor) -> torch.Tensor:
        """The viewer's step length in cube units at a point (one triplane voxel in contracted space, mapped
        back through the contraction: x (inf-norm)^2 along the radial axis outside the unit cube)."""
        base = 4.0 / self.cfg.triplane_resolution / self.partition.submodel_scale
        return base * stretch.clamp_min(1.0) ** 2

    # ---- fields -------------------------------------------------------------------------------------------
    def features(self, z: torch.Tensor, params_idx: torch.Tensor, quantize: bool = True) -> dict[str, torch.Tensor]:
        """Density and the activated colour/features at contracted points, with feature gating as the viewer."""
        cfg = self.cfg
        sp, pl = merf_lookup(z, params_idx, self.sparse, self.planes, cfg.sparse_resolution, cfg.triplane_resolution,
                             quantize, self.touched)
        gate = sp[:, 7:8]
        density = torch.exp(sp[:, 0] + gate[:, 0] * pl[:, 0] - 1.0)
        sf = sp[:, 4:8]  # three features + the gate as the 4th
        return {"density": density, "color": torch.sigmoid(sp[:, 1:4] + gate * pl[:, 1:4]),
                "feat": torch.sigmoid(sf + gate * pl[:, 4:8]), "coarse_color": torch.sigmoid(sp[:, 1:4]),
                "coarse_feat": torch.sigmoid(sf)}

    def render(self, origins: torch.Tensor, dirs: torch.Tensor, params_idx: torch.Tensor, t0: torch.Tensor,
               t1: torch.Tensor, ray_idx: torch.Tensor, cull_alpha: float = 0.0, quantize: bool = True,
               cameras: torch.Tensor | None = None) -> dict:
        """Render rays on given (packed) intervals, e.g. the teacher's: ``origins``/``dirs`` (R, 3) world, unit
        directions; ``params_idx`` (R,) the submodel of each ray; ``t0``/``t1``/``ray_idx`` (N,) the intervals.
        Samples whose alpha at the viewer's step size is below ``cull_alpha`` are dropped (alpha culling). The
        deferred MLP's lattice is read at ``cameras`` (R, 3), the camera centres (as the viewer does once per frame);
        by default at the ray origins."""
        r = origins.shape[0]
        mid = 0.5 * (t0 + t1)
        pts = origins[ray_idx] + mid[:, None] * dirs[ray_idx]
        sm = params_idx[ray_idx]
        z, stretch = self.contracted(pts, sm)
        f = self.features(z, sm, quantize)
        density = f["density"]
        if cull_alpha > 0:
            alpha_rt = 1.0 - torch.exp(-density.detach() * self.realtime_step(stretch))
            density = torch.where(alpha_rt >= cull_alpha, density, torch.zeros_like(density))
        scale = self.partition.scale
        w, alpha = packed_weights(density, t0 * scale, t1 * scale, ray_idx, r)
        acc = {k: packed_sum(w[:, None] * f[k], ray_idx, r) for k in ("color", "feat", "coarse_color", "coarse_feat")}
        opacity = packed_sum(w, ray_idx, r)
        acc["visibility"] = 1.0 - opacity
        x = deferred_inputs(acc, dirs, BACKGROUND)
        specular = self.mlp(x, params_idx, self.mlp_position(origins if cameras is None else cameras, params_idx))
        return {"rgb": acc["color"] + specular, "acc": opacity, "w": w, "alpha": alpha, "density": density,
                "diffuse": acc["color"], "z": z, "stretch": stretch}

    def config_dict(self) -> dict:
        return {"student": asdict(self.cfg), "partition": self.partition.to_json()}
