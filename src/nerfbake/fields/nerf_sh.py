"""NeRF-SH (PlenOctrees §4.1): NeRF's MLP predicting density and SH coefficients instead of RGB."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from nerfbake.fields.encoding import PositionalEncoding
from nerfbake.render.sh import sh_num_coeffs


@dataclass
class NeRFSHConfig:
    num_freqs: int = 10
    depth: int = 8
    width: int = 256
    skip: int = 4
    sh_degree: int = 3
    # "relu" (PlenOctrees) or "softplus" (softplus(x - 1), mip-NeRF's: never without a gradient; the paper preset's
    # choice, see teacher/presets.py). The tree stores activated densities, so either converts to the same format.
    density_activation: str = "relu"


class NeRFSHField(nn.Module):
    """Positional encoding -> ``depth`` ReLU layers (input re-injected after layer ``skip``) -> sigma, SH."""

    def __init__(self, cfg: NeRFSHConfig):
        super().__init__()
        if cfg.density_activation not in ("relu", "softplus"):
            raise ValueError(f"unknown density activation {cfg.density_activation!r}; choose relu or softplus")
        self.cfg = cfg
        self.encoding = PositionalEncoding(cfg.num_freqs)
        d_in = self.encoding.out_dim
        layers = []
        d = d_in
        for i in range(cfg.depth):
            layers.append(nn.Linear(d, cfg.width))
            d = cfg.width + (d_in if i + 1 == cfg.skip else 0)
        self.layers = nn.ModuleList(layers)
        self.num_basis = sh_num_coeffs(cfg.sh_degree)
        self.sigma_head = nn.Linear(d, 1)
        self.sh_head = nn.Linear(d, 3 * self.num_basis)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """He-uniform hidden layers and Glorot-uniform heads, zero biases (jaxnerf uses Glorot and zero biases).
        PyTorch's default init shrinks the signal about sixfold per ReLU layer, so at depth 8 the density head
        sees only its bias: sigma is the same tiny constant everywhere, or ReLU-dead everywhere (half the seeds),
        and the paper preset never leaves the background-only solution."""
        for layer in self.layers:
            nn.init.kaiming_uniform_(layer.weight, nonlinearity="relu")
            nn.init.zeros_(layer.bias)
        for head in (self.sigma_head, self.sh_head):
            nn.init.xavier_uniform_(head.weight)
            nn.init.zeros_(head.bias)

    @property
    def sh_degree(self) -> int:
        return self.cfg.sh_degree

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        e = self.encoding(x)
        h = e
        for i, layer in enumerate(self.layers):
            h = torch.relu(layer(h))
            if i + 1 == self.cfg.skip:
                h = torch.cat([h, e], dim=-1)
        raw = self.sigma_head(h)[:, 0]
        if self.cfg.density_activation == "softplus":
            return nn.functional.softplus(raw - 1.0), self.sh_head(h)
        return torch.relu(raw), self.sh_head(h)

    def density(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward(x)[0]
