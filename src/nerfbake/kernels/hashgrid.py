"""Multi-resolution hash encoding (instant-ngp) forward and backward as Warp kernels.

Shapes: ``x`` (N, 3) in [0, 1]^3; ``table`` (L, T, F) features; ``resolution`` (L,) int grid size per level;
``dense`` (L,) int, 1 where (res+1)^3 <= T so the level is indexed densely instead of hashed. Output
(N, L*F) with F = 2 (features are ``vec2``, as in instant-ngp's default). One thread per (block of points, level):
a block of one point on a GPU, of ``CPU_BLOCK`` points on the CPU, where Warp calls the kernel once per thread
index and that call's overhead was half the cost of a dense level. The backward scatters into the table with
atomic adds, and CPU launches deal the levels out over threads, so threads never write the same table rows.
Tables of 2^k rows (every ``HashGrid``) reduce the hash with a mask instead of an integer division.
"""
from __future__ import annotations


import torch

from nerfbake.kernels import cpu_threads, device_of, ensure_loaded, parallel_map, warp

wp = warp()
wp.set_module_options({"enable_backward": False})  # analytic backward kernels below; no tape needed

PRIME_Y = 2654435761
PRIME_Z = 805459861


@wp.func
def corner_weight(c: int, frac: wp.vec3) -> float:
    """Trilinear weight of corner c (bits: x, y, z offsets) of the cell, at fractional position ``frac``."""
    wx = wp.where((c & 1) == 1, frac[0], 1.0 - frac[0])
    wy = wp.where(((c >> 1) & 1) == 1, frac[1], 1.0 - frac[1])
    wz = wp.where(((c >> 2) & 1) == 1, frac[2], 1.0 - frac[2])
    return wx * wy * wz


@wp.func
def corner_index(base: wp.vec3i, c: int, res: int, dense: int, size: int) -> int:
    """Table row of corner c of the cell at ``base``: dense indexing where the level fits, else the spatial hash
    (``size`` rows; a negative ``size`` is -(rows - 1) for 2^k rows, reduced with a mask)."""
    cx = base[0] + (c & 1)
    cy = base[1] + ((c >> 1) & 1)
    cz = base[2] + ((c >> 2) & 1)
    if dense == 1:
        return cx + (res + 1) * (cy + (res + 1) * cz)
    h = wp.uint32(cx) ^ (wp.uint32(cy) * wp.uint32(2654435761)) ^ (wp.uint32(cz) * wp.uint32(805459861))
    if size < 0:
        return int(h & wp.uint32(-size))
    return int(h % wp.uint32(size))


@wp.func
def cell_of(x: wp.array2d(dtype=wp.float32), n: int, res: int, fres: float):
    """The cell holding point n at resolution ``res`` and the point's fractional position inside it."""
    p = wp.vec3(wp.clamp(x[n, 0], 0.0, 1.0), wp.clamp(x[n, 1], 0.0, 1.0), wp.clamp(x[n, 2], 0.0, 1.0)) * fres
    base = wp.vec3i(wp.min(int(wp.floor(p[0])), res - 1), wp.min(int(wp.floor(p[1])), res - 1),
                    wp.min(int(wp.floor(p[2])), res - 1))
    return base, p - wp.vec3(float(base[0]), float(base[1]), float(base[2]))


@wp.kernel
def hash_forward(
    x: wp.array2d(dtype=wp.float32),
    table: wp.array2d(dtype=wp.vec2),
    resolution: wp.array(dtype=wp.int32),
    dense: wp.array(dtype=wp.int32),
    level0: int,
    level_stride: int,
    size: int,
    block: int,
    out: wp.array2d(dtype=wp.vec2),
):
    """Thread (level, block of ``block`` points): the trilinear features of points ``x`` (N, 3) in [0, 1]^3 at one
    level of ``table`` (L, T) vec2 (hashed, or indexed directly where ``dense``) into ``out`` (N, L) vec2."""
    j, b = wp.tid()
    level = level0 + j * level_stride
    res = resolution[level]
    is_dense = dense[level]
    fres = float(res)
    for n in range(b * block, wp.min((b + 1) * block, x.shape[0])):
        base, frac = cell_of(x, n, res, fres)
        acc = wp.vec2(0.0, 0.0)
        for c in range(8):
            acc = acc + corner_weight(c, frac) * table[level, corner_index(base, c, res, is_dense, size)]
        out[n, level] = acc


@wp.kernel
def hash_backward(
    x: wp.array2d(dtype=wp.float32),
    grad_out: wp.array2d(dtype=wp.vec2),
    resolution: wp.array(dtype=wp.int32),
    dense: wp.array(dtype=wp.int32),
    level0: int,
    level_stride: int,
    size: int,
    block: int,
    grad_table: wp.array2d(dtype=wp.vec2),
):
    """Thread (level, block of points): scatter ``grad_out`` (N, L) vec2 into ``grad_table`` (L, T) vec2 with
    :func:`hash_forward`'s corner weights."""
    j, b = wp.tid()
    level = level0 + j * level_stride
    res = resolution[level]
    is_dense = dense[level]
    fres = float(res)
    for n in range(b * block, wp.min((b + 1) * block, x.shape[0])):
        g = grad_out[n, level]
        base, frac = cell_of(x, n, res, fres)
        for c in range(8):
            wp.atomic_add(grad_table, level, corner_index(base, c, res, is_dense, size), corner_weight(c, frac) * g)


def _level_chunks(num_levels: int, device: str) -> list[tuple[int, int, int]]:
    """(first level, stride, count) per launch: all levels at once on a GPU; on the CPU one launch per thread
    with the levels dealt out round-robin, so every thread gets its share of cheap dense (coarse) levels and
    expensive hashed (fine) ones, and no two threads write the same table rows."""
    parts = 1 if device != "cpu" else min(cpu_threads(), num_levels)
    return [(t, parts, len(range(t, num_levels, parts))) for t in range(parts)]


CPU_BLOCK = 256  # points per kernel call on the CPU (see the module docstring)


def _size_arg(rows: int) -> int:
    """The kernels' ``size``: -(rows - 1), a mask, for 2^k rows; else the row count (modulo)."""
    return -(rows - 1) if rows > 1 and rows & (rows - 1) == 0 else rows


def _launch(kernel, n: int, rows: int, chunks, inputs_fn, output, device: str) -> None:
    ensure_loaded(kernel, device)
    block = CPU_BLOCK if device == "cpu" else 1

    def run(chunk):
        level0, stride, count = chunk
        # Level-major order: a thread sweeps all points of one level before the next, so it works in one
        # table (a few MB) at a time instead of jumping between all of them for every point.
        wp.launch(kernel, dim=(count, -(-n // block)), inputs=[*inputs_fn(level0, stride), _size_arg(rows), block, output],
                  device=device)

    parallel_map(run, chunks)


class HashEncodeFunction(torch.autograd.Function):
    """Differentiable w.r.t. the table only (positions get no gradient: the fields never need it).

    For a leaf table (a Parameter) the backward kernel adds straight into ``table.grad`` instead of returning a
    fresh table-sized tensor: allocating and zero-filling tens of MB every step (page faults) cost more than
    the kernel itself. Trainers should zero gradients with ``set_to_none=False`` to keep that buffer."""

    @staticmethod
    def forward(ctx, x, table, resolution, dense):
        x = x.contiguous().float()
        n, (num_levels, _, nf) = x.shape[0], table.shape
        if nf != 2:
            raise ValueError("the Warp hash encoding stores 2 features per level")
        out = torch.empty(n, num_levels, 2, device=x.device, dtype=torch.float32)
        if n > 0:
            dev = device_of(x)
            wx, wo = wp.from_torch(x), wp.from_torch(out, dtype=wp.vec2)
            wt = wp.from_torch(table.detach().contiguous(), dtype=wp.vec2)
            wr, wd = wp.from_torch(resolution), wp.from_torch(dense)
            _launch(hash_forward, n, table.shape[1], _level_chunks(num_levels, dev), lambda lo, st: [wx, wt, wr, wd, lo, st],
                    wo, dev)
        ctx.save_for_backward(x, resolution, dense)
        ctx.table_shape = table.shape
        ctx.leaf_table = table if table.is_leaf and table.requires_grad else None
        return out.view(n, num_levels * 2)

    @staticmethod
    def backward(ctx, grad_out):
        x, resolution, dense = ctx.saved_tensors
        leaf = ctx.leaf_table
        if leaf is not None:
            if leaf.grad is None:
                leaf.grad = torch.zeros_like(leaf)
            grad_table = leaf.grad
        else:
            grad_table = torch.zeros(ctx.table_shape, device=x.device, dtype=torch.float32)
        if x.shape[0] > 0:
            dev = device_of(x)
            n, num_levels = x.shape[0], ctx.table_shape[0]
            wx = wp.from_torch(x)
            wg = wp.from_torch(grad_out.contiguous().float().view(n, num_levels, 2), dtype=wp.vec2)
            wr, wd = wp.from_torch(resolution), wp.from_torch(dense)
            wgt = wp.from_torch(grad_table, dtype=wp.vec2)
            _launch(hash_backward, x.shape[0], ctx.table_shape[1], _level_chunks(ctx.table_shape[0], dev),
                    lambda lo, st: [wx, wg, wr, wd, lo, st], wgt, dev)
        return None, (None if leaf is not None else grad_table), None, None


def hash_encode(x: torch.Tensor, table: torch.Tensor, resolution: torch.Tensor, dense: torch.Tensor) -> torch.Tensor:
    """instant-ngp's multiresolution hash encoding on the Warp kernels: points ``x`` (N, 3) in [0, 1]^3, ``table``
    (L, T, F) features per level, ``resolution`` (L,) cells per axis, ``dense`` (L,) 1 where a level's
    (res + 1)^3 corners fit the table and are indexed directly -> (N, L * F), each level's 8 corners trilinearly
    blended. Gradients reach ``table`` only (:class:`HashEncodeFunction`); :func:`hash_encode_reference` is
    the torch twin the tests compare with."""
    return HashEncodeFunction.apply(x, table, resolution, dense)


def hash_encode_reference(x, table, resolution, dense) -> torch.Tensor:
    """Slow, obviously-correct torch version of the same encoding (for tests)."""
    num_levels, size, nf = table.shape
    outs = []
    x = x.clamp(0, 1)
    for level in range(num_levels):
        res = int(resolution[level])
        p = x * res
        i = p.floor().long().clamp(max=res - 1)
        frac = p - i
        acc = torch.zeros(x.shape[0], nf, dtype=table.dtype, device=x.device)
        for c in range(8):
            d = torch.tensor([c & 1, (c >> 1) & 1, (c >> 2) & 1], device=x.device)
            corner = i + d
            w = torch.where(d == 1, frac, 1 - frac).prod(-1)
            if int(dense[level]):
                idx = corner[:, 0] + (res + 1) * (corner[:, 1] + (res + 1) * corner[:, 2])
            else:
                h = corner[:, 0] ^ (corner[:, 1] * PRIME_Y) ^ (corner[:, 2] * PRIME_Z)
                idx = (h & 0xFFFFFFFF) % size
            acc = acc + w[:, None] * table[level, idx]
        outs.append(acc)
    return torch.cat(outs, dim=-1)
