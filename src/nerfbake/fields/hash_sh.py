"""The fast teacher's field: hash grid -> small MLP -> density and SH colour coefficients.

Colour comes only from SH coefficients (no view direction input to the MLP), so the same field converts
to a PlenOctree by averaging coefficients and densities inside each leaf.
Bounded scenes map their box to [0, 1]^3; unbounded ones use the MERF contraction of x / scene_scale.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from nerfbake.fields.encoding import HashGrid, mlp, trunc_exp
from nerfbake.render.contraction import contract
from nerfbake.render.sh import sh_num_coeffs


MLP_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}


@dataclass
class HashSHConfig:
    levels: int = 16
    log2_table: int = 19
    base_res: int = 16
    max_res: int = 1024
    hidden: int = 64
    geo_features: int = 15
    sh_degree: int = 3
    color_layers: int = 2


class HashSHField(nn.Module):
    def __init__(self, cfg: HashSHConfig, box_min, box_max, contracted: bool = False):
        super().__init__()
        self.cfg = cfg
        self.contracted = contracted
        self.register_buffer("box_min", torch.as_tensor(box_min, dtype=torch.float32))
        self.register_buffer("box_max", torch.as_tensor(box_max, dtype=torch.float32))
        self.grid = HashGrid(cfg.levels, cfg.log2_table, cfg.base_res, cfg.max_res)
        self.density_net = mlp(self.grid.out_dim, cfg.hidden, 1, 1 + cfg.geo_features)
        self.num_basis = sh_num_coeffs(cfg.sh_degree)
        self.color_net = mlp(cfg.geo_features, cfg.hidden, cfg.color_layers, 3 * self.num_basis)

    def set_mlp_dtype(self, name: str) -> None:
        """"bfloat16": both MLPs' CPU pass computes in bfloat16 where the CPU multiplies it natively
        (fields/encoding.py: MLP); elsewhere, and on GPUs, float32. Inputs and outputs stay float32."""
        if name not in MLP_DTYPES:
            raise ValueError(f"MLP dtype {name!r}: choose one of {', '.join(MLP_DTYPES)}")
        self.density_net.compute_dtype = self.color_net.compute_dtype = MLP_DTYPES[name]

    @property
    def sh_degree(self) -> int:
        return self.cfg.sh_degree

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        if self.contracted:
            # box is the region kept at full resolution ([-1, 1]^3 after scaling); space beyond is contracted.
            centre, half = (self.box_max + self.box_min) / 2, (self.box_max - self.box_min) / 2
            return (contract((x - centre) / half) + 2.0) / 4.0
        return (x - self.box_min) / (self.box_max - self.box_min)

    def density_and_features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.density_net(self.grid(self.normalize(x)))
        return trunc_exp(h[:, 0] - 1.0), h[:, 1:]

    def density(self, x: torch.Tensor) -> torch.Tensor:
        return self.density_and_features(x)[0]

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """sigma (N,), sh coefficients (N, 3*B)."""
        sigma, feat = self.density_and_features(x)
        return sigma, self.sh_coeffs(feat)

    def sh_coeffs(self, feat: torch.Tensor) -> torch.Tensor:
        """SH coefficients (N, 3*B) from the geometry features of :meth:`density_and_features`."""
        return self.color_net(feat)
