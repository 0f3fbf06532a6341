"""The deferred appearance MLP of SMERF (paper eq. 7): 3 dense layers (ELU, sigmoid output) whose kernels and
biases live on a P^3 lattice per submodel and are trilinearly interpolated at the camera position, so view-dependent
colour can vary across a large scene. Arrays are ``[submodel, z, y, x, ...]`` over the training frame, exactly what
``deferred_mlp.json`` stores and the viewer (and :func:`nerfbake.smerf.baked_render.deferred_mlp_weights`) reads."""
from __future__ import annotations

import json
import math

import numpy as np
import torch
from torch import nn


def pos_enc(v: torch.Tensor, degrees: int = 4) -> torch.Tensor:
    """[v, sin(2^k v), cos(2^k v)] with k outer, axis inner (the deferred MLP's view-direction encoding)."""
    scaled = torch.cat([v * (2.0 ** k) for k in range(degrees)], -1)
    return torch.cat([v, torch.sin(scaled), torch.cos(scaled)], -1)


def deferred_inputs(acc: dict, view_dirs: torch.Tensor, background, combine_op: str = "coarse_sum",
                    exposure: float | None = None) -> torch.Tensor:
    """The MLP input per pixel, laid out as the viewer's shader writes it: the accumulated diffuse colour composited
    over the background (SNeRG mode), the accumulated features, with ``coarse_sum`` the sparse-grid-only colour and
    features, then the unit view direction (training frame) and its sin/cos encoding. ``acc`` holds ``color``
    (R, 3), ``visibility`` (R,), ``feat`` (R, 4), ``coarse_color``, ``coarse_feat``."""
    bg = torch.as_tensor(background, dtype=acc["color"].dtype, device=acc["color"].device)
    c_in = acc["color"] + acc["visibility"][:, None] * bg

    def e(x):
        if exposure is None:
            return x
        x = x.clamp(1e-7, 1 - 1e-7)
        return torch.log(x / (1 - x)) + math.log(exposure)

    parts = [e(c_in), e(acc["feat"])]
    if combine_op == "coarse_sum":
        parts += [e(acc["coarse_color"]), e(acc["coarse_feat"])]
    v = view_dirs / view_dirs.norm(dim=-1, keepdim=True)
    return torch.cat(parts + [pos_enc(v)], -1)


def unique_rows(key: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct rows of ``key`` (U, C) and each row's index among them (R,). On the CPU, rows are compared as
    raw bytes with numpy: ``torch.unique(dim=0)`` there compares rows one tensor op at a time, 18 ms for a 4608-ray
    batch against 2 ms, a tenth of a distillation step of the demo."""
    if key.device.type != "cpu":
        return torch.unique(key, dim=0, return_inverse=True)
    k = np.ascontiguousarray(key.detach().numpy())
    rows = k.view(np.dtype((np.void, k.dtype.itemsize * k.shape[1]))).reshape(-1)
    _, first, inv = np.unique(rows, return_index=True, return_inverse=True)
    return key[torch.from_numpy(first)], torch.from_numpy(inv.reshape(-1))


class GridMLP(nn.Module):
    """SMERF's grid of deferred MLPs: one small MLP (in_dim -> width -> width -> 3) per vertex of a P^3 lattice per
    submodel, whose weights are trilinearly interpolated at the camera position."""
    def __init__(self, num_submodels: int, in_dim: int = 41, width: int = 16, grid: int = 5, activation: str = "elu",
                 generator: torch.Generator | None = None):
        super().__init__()
        self.grid, self.activation = grid, activation
        dims = [in_dim, width, width, 3]
        self.kernels = nn.ParameterList()
        self.biases = nn.ParameterList()
        for a, b in zip(dims[:-1], dims[1:]):
            w = torch.randn(a, b, generator=generator) / math.sqrt(a)  # LeCun normal, as flax's Dense
            self.kernels.append(nn.Parameter(w.expand(num_submodels, grid, grid, grid, a, b).clone()))
            self.biases.append(nn.Parameter(torch.zeros(num_submodels, grid, grid, grid, b)))

    def corners(self, pos: torch.Tensor):
        """Lattice corner indices (R, 8, 3) as (x, y, z) and trilinear weights (R, 8) at positions in [-1, 1]^3."""
        g = (pos + 1) / 2 * self.grid - 0.5
        lo = torch.floor(g)
        f = g - lo
        off = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=pos.dtype, device=pos.device)
        idx = (lo[:, None, :] + off[None]).clamp(0, self.grid - 1).long()
        w = torch.where(off[None] == 1, f[:, None, :], 1 - f[:, None, :]).prod(-1)
        return idx, w

    def weights_at(self, params_idx: torch.Tensor, pos: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per row: the interpolated (kernel (R, in, out), bias (R, out)) of every layer, as the trilinear weights
        spread over all lattice cells (R, N P^3) times the stacked parameters (a matmul, so the backward pass is
        deterministic, unlike scattering gathered kernels back)."""
        idx, w = self.corners(pos)
        g3 = self.grid ** 3
        cell = params_idx[:, None] * g3 + (idx[..., 2] * self.grid + idx[..., 1]) * self.grid + idx[..., 0]
        n = self.kernels[0].shape[0]
        spread = torch.zeros(pos.shape[0], n * g3, dtype=pos.dtype, device=pos.device).scatter_add_(1, cell, w)
        out = []
        for kern, bias in zip(self.kernels, self.biases):
            k = spread @ kern.reshape(n * g3, -1)
            out.append((k.view(-1, *kern.shape[-2:]), spread @ bias.reshape(n * g3, -1)))
        return out

    def forward(self, x: torch.Tensor, params_idx: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """Interpolate the layers once per distinct (submodel, position) - in the viewer one per frame, in training
        one per camera - then apply them per ray. Feeding every ray its own position works but costs a gather of
        8 kernels per ray in the forward and a scatter of as many in the backward."""
        uniq, inv = unique_rows(torch.cat([params_idx[:, None].to(pos.dtype), pos], 1))
        layers = self.weights_at(uniq[:, 0].long(), uniq[:, 1:])
        # Rows picked with a one-hot matmul rather than k[inv]: the backward of CPU advanced indexing adds in a
        # thread-dependent order, which made training runs differ from rerun to rerun.
        pick = torch.nn.functional.one_hot(inv, len(uniq)).to(x.dtype)
        h = x
        for i, (k, b) in enumerate(layers):
            h = torch.bmm(h[:, None, :], (pick @ k.reshape(len(uniq), -1)).view(-1, *k.shape[1:]))[:, 0] + pick @ b
            if i < len(layers) - 1:
                h = nn.functional.elu(h) if self.activation == "elu" else torch.relu(h)
        return torch.sigmoid(h)

    def tv_loss(self) -> torch.Tensor:
        """Mean squared difference between lattice neighbours along each axis (the authors' L2 TV, weight 0.1); zero
        for a single MLP (P = 1), which has no neighbours (the mean of no differences would be NaN)."""
        total = torch.zeros((), device=self.kernels[0].device)
        if self.grid < 2:
            return total
        for p in list(self.kernels) + list(self.biases):
            for axis in (1, 2, 3):
                total = total + (p.diff(dim=axis) ** 2).mean()
        return total

    def export(self) -> dict:
        """``deferred_mlp.json`` content: {"ResampleDense_i/kernel": {"shape", "data"}, ...}."""
        out = {}
        for i, (k, b) in enumerate(zip(self.kernels, self.biases)):
            for name, t in (("kernel", k), ("bias", b)):
                t = t.detach().cpu()
                out[f"ResampleDense_{i}/{name}"] = {"shape": list(t.shape), "data": t.reshape(-1).tolist()}
        return out


def deferred_mlp_text(export: dict, precision=np.float16) -> str:
    """``export`` as JSON text, every weight rounded to ``precision`` (float16: 11 significant bits) and written as
    the shortest decimal that reads back as that value. The viewer reads float32; ``json.dumps`` writes a float32
    widened to double with up to 17 digits (lego K = 1: 1.1 MB), float32's shortest digits half that. This file is
    repeated in every submodel folder and holds the MLPs of all of them, so it dominates small scenes and
    partitioned ones; float16 digits halve it again (`make demo`'s: 586 → 304 KB of 0.90 → 0.62 MB) and move the
    baked renders by at most 1.1e-4, a thirtieth of one 8-bit step (same PSNR to 0.001 dB). An array with a weight
    float16 cannot hold keeps float32."""
    def array(values) -> str:
        data = np.asarray(values, dtype=np.float32).reshape(-1)
        if not np.isfinite(data).all():
            raise ValueError("the deferred MLP has non-finite weights; the distillation diverged")
        fits = not data.size or float(np.abs(data).max()) <= float(np.finfo(precision).max)
        rounded = data.astype(precision) if fits else data
        return "[" + ",".join(str(v) for v in rounded) + "]"

    items = [f'{json.dumps(name)}: {{"shape": {json.dumps(list(entry["shape"]))}, "data": {array(entry["data"])}}}'
             for name, entry in export.items()]
    return "{" + ", ".join(items) + "}"
