"""Input encodings: NeRF's positional encoding and instant-ngp's multiresolution hash grid."""
from __future__ import annotations

import functools
import math

import torch
from torch import nn

from nerfbake.kernels.hashgrid import hash_encode


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
        return hash_encode(x01, self.table, self.resolution, self.dense)


# Rows per chunk of the CPU MLP pass: a (4096, 64) float32 activation is 1 MB and stays in cache; a whole batch's
# (131072, 64) is 32 MB, and every matmul, ReLU and ReLU backward streams it through memory. Measured on 2 cores: a
# 32 -> 64 -> 16 forward over 131k rows, 33.5 ms whole, 7.5 ms chunked; the unbounded teacher's no-gradient renders
# 16.3k -> 28.2k rays/s; its training 9.3k rays/s either way in float32, and in bfloat16 7.3-8.4k whole against
# 9.4-10.7k chunked (benchmarks/unbounded_speed.py).
CPU_CHUNK_ROWS = 4096


def _layers_in(dtype, params):
    """(weights, biases) of the flat [w0, b0, w1, b1, ...] parameter list, cast to the compute dtype."""
    return [w.to(dtype) for w in params[0::2]], [b.to(dtype) for b in params[1::2]]


def _hidden_activations(x, weights, biases) -> list[torch.Tensor]:
    """[x, h1, ..., hk]: the input chunk and each hidden layer's ReLU output (everything but the output layer)."""
    acts = [x]
    for w, b in zip(weights[:-1], biases[:-1]):
        acts.append(torch.addmm(b, acts[-1], w.t()).relu_())
    return acts


class _ChunkedReLUMLP(torch.autograd.Function):
    """Forward and backward of Linear/ReLU/.../Linear one row chunk at a time. Only the input is kept for the
    backward, which recomputes each chunk's hidden activations (a matmul each, cheaper than storing them).
    ``dtype`` bfloat16 runs the matmuls and activations in bfloat16 (inputs, outputs and gradients stay float32;
    weight gradients are summed in float32)."""

    @staticmethod
    def forward(ctx, x, chunk, dtype, *params):
        weights, biases = _layers_in(dtype, params)
        out = x.new_empty(x.shape[0], weights[-1].shape[0])
        for s in range(0, x.shape[0], chunk):
            h = _hidden_activations(x[s: s + chunk].to(dtype), weights, biases)[-1]
            out[s: s + chunk] = torch.addmm(biases[-1], h, weights[-1].t())
        ctx.chunk, ctx.dtype = chunk, dtype
        ctx.save_for_backward(x, *params)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x, *params = ctx.saved_tensors
        dtype = ctx.dtype
        weights, biases = _layers_in(dtype, params)
        grad_w = [torch.zeros_like(w) for w in params[0::2]]
        grad_b = [torch.zeros_like(b) for b in params[1::2]]
        grad_x = torch.empty_like(x) if ctx.needs_input_grad[0] else None
        for s in range(0, x.shape[0], ctx.chunk):
            acts = _hidden_activations(x[s: s + ctx.chunk].to(dtype), weights, biases)
            g = grad_out[s: s + ctx.chunk].to(dtype)
            for i in range(len(weights) - 1, -1, -1):
                grad_w[i] += g.t() @ acts[i]
                grad_b[i] += g.sum(0, dtype=grad_b[i].dtype)
                if i > 0:
                    g = torch.ops.aten.threshold_backward(g @ weights[i], acts[i], 0.0)
                elif grad_x is not None:
                    grad_x[s: s + ctx.chunk] = g @ weights[0]
        grads = [v for pair in zip(grad_w, grad_b) for v in pair]
        return (grad_x, None, None, *grads)


class MLP(nn.Sequential):
    """Linear/ReLU layers (an ``nn.Sequential``, so checkpoints keep their keys). On the CPU the pass runs in
    row chunks that stay in cache (:data:`CPU_CHUNK_ROWS`); on a GPU it is the plain sequence. ``compute_dtype``
    bfloat16 computes the CPU pass in bfloat16 where the CPU has native bfloat16 matmuls (AVX512-BF16/AMX)."""

    compute_dtype: torch.dtype = torch.float32

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        linears = [m for m in self if isinstance(m, nn.Linear)]
        if x.is_cuda or x.dim() != 2 or len(linears) != (len(self) + 1) // 2 \
                or not all(isinstance(m, nn.ReLU) for m in self[1::2]):
            return super().forward(x)
        params = [p for m in linears for p in (m.weight, m.bias)]
        bf16 = self.compute_dtype == torch.bfloat16 and x.dtype == torch.float32 and cpu_has_bf16()
        return _ChunkedReLUMLP.apply(x.contiguous(), CPU_CHUNK_ROWS, torch.bfloat16 if bf16 else x.dtype, *params)


@functools.cache
def cpu_has_bf16() -> bool:
    """Whether this CPU multiplies bfloat16 matrices natively (elsewhere bfloat16 would be emulated, slowly)."""
    return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def mlp(in_dim: int, hidden: int, layers: int, out_dim: int, act=nn.ReLU) -> nn.Sequential:
    """``layers`` hidden layers of width ``hidden``; the output layer has no activation."""
    mods: list[nn.Module] = []
    d = in_dim
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), act()]
        d = hidden
    mods.append(nn.Linear(d, out_dim))
    return MLP(*mods)


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
