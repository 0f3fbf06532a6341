"""Input encodings: NeRF's positional encoding and instant-ngp's multiresolution hash grid."""
from __future__ import annotations

import math

import torch
from torch import nn


class PositionalEncoding(nn.Module):
    """[x, sin(2^k x), cos(2^k x)] for k < num_freqs (NeRF eq. 4)."""

    def __init__(self, num_freqs: int, include_input: bool = True):
        super().__init__()
        self.num_freqs, self.include_input = num_freqs, include_input
        self.register_buffer("freqs", 2.0 ** torch.arange(num_freqs), persistent=False)

    @property
    def out_dim(self) -> int:
        return 3 * (2 * self.num_freqs + int(self.include_input))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xb = (x[..., None, :] * self.freqs[:, None]).flatten(-2)
        parts = [torch.sin(xb), torch.cos(xb)]
        if self.include_input:
            parts.insert(0, x)
        return torch.cat(parts, dim=-1)


class HashGrid(nn.Module):
    """Multiresolution hash encoding of points in [0, 1]^3 -> (N, levels*2) (Warp kernel, CPU and CUDA)."""

    def __init__(self, levels: int = 16, log2_table: int = 19, base_res: int = 16, max_res: int = 2048):
        super().__init__()
        self.levels, self.log2_table, self.base_res, self.max_res = levels, log2_table, base_res, max_res
        size = 2**log2_table
        growth = math.exp((math.log(max_res) - math.log(base_res)) / max(levels - 1, 1))
        res = torch.tensor([int(math.floor(base_res * growth**i)) for i in range(levels)], dtype=torch.int32)
        self.register_buffer("resolution", res, persistent=False)
        self.register_buffer("dense", ((res.long() + 1) ** 3 <= size).int(), persistent=False)
        # Dense levels use only (res+1)^3 rows; store every level at full size for a simple layout.
        self.table = nn.Parameter(torch.empty(levels, size, 2).uniform_(-1e-4, 1e-4))

    @property
    def out_dim(self) -> int:
        return self.levels * 2

    def forward(self, x01: torch.Tensor) -> torch.Tensor:
        from nerfbake.kernels.hashgrid import hash_encode

        return hash_encode(x01, self.table, self.resolution, self.dense)


def mlp(in_dim: int, hidden: int, layers: int, out_dim: int, act=nn.ReLU) -> nn.Sequential:
    """``layers`` hidden layers of width ``hidden``; the output layer has no activation."""
    mods: list[nn.Module] = []
    d = in_dim
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), act()]
        d = hidden
    mods.append(nn.Linear(d, out_dim))
    return nn.Sequential(*mods)


class TruncExp(torch.autograd.Function):
    """exp with its gradient clamped (instant-ngp's density activation): stable with large raw values."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return TruncExp.apply(x)
