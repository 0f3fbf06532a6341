"""Adam on chosen rows of a (rows, C) float32 grid, in place (Warp, CPU and CUDA): the kernel behind
:class:`nerfbake.train.row_adam.RowAdam`.

One thread per listed row updates its C values and both moments where they lie and zeroes its gradient and mask
entry, so a step moves 7 row-sized reads and writes per touched row and nothing else (torch's gather, update and
scatter of the same rows took twice the time of the whole dense fused Adam on bonsai's grids).
"""
from __future__ import annotations

import torch

from nerfbake.kernels import device_of, ensure_loaded, launch_chunks, parallel_map, warp

wp = warp()
wp.set_module_options({"enable_backward": False})


@wp.kernel
def adam_rows(rows: wp.array(dtype=wp.int64), value: wp.array2d(dtype=wp.float32), grad: wp.array2d(dtype=wp.float32),
              exp_avg: wp.array2d(dtype=wp.float32), exp_avg_sq: wp.array2d(dtype=wp.float32),
              mask: wp.array(dtype=wp.uint8), beta1: float, beta2: float, step_size: float, root_bc2: float,
              eps: float, start: int):
    """Thread i (from ``start``): torch.optim.Adam's update of row ``rows[i]``, then its gradient and mask cleared."""
    r = rows[wp.tid() + start]
    for c in range(value.shape[1]):
        g = grad[r, c]
        m = exp_avg[r, c] + (1.0 - beta1) * (g - exp_avg[r, c])
        v = beta2 * exp_avg_sq[r, c] + (1.0 - beta2) * g * g
        exp_avg[r, c] = m
        exp_avg_sq[r, c] = v
        value[r, c] = value[r, c] - step_size * m / (wp.sqrt(v) / root_bc2 + eps)
        grad[r, c] = 0.0
    mask[r] = wp.uint8(0)


def adam_on_rows(rows: torch.Tensor, value: torch.Tensor, grad: torch.Tensor, exp_avg: torch.Tensor,
                 exp_avg_sq: torch.Tensor, mask: torch.Tensor, beta1: float, beta2: float, step_size: float,
                 root_bc2: float, eps: float) -> None:
    """Adam step on rows ``rows`` (int64) of ``value`` (contiguous float32 (R, C), moments alike), in place; the
    rows' ``grad`` and ``mask`` (uint8 (R,)) entries are cleared. ``step_size`` is lr / (1 - beta1^t) and
    ``root_bc2`` sqrt(1 - beta2^t)."""
    n = rows.shape[0]
    if n == 0:
        return
    for t in (value, grad, exp_avg, exp_avg_sq):
        if t.dtype != torch.float32 or not t.is_contiguous() or t.shape != value.shape:
            raise ValueError(f"adam_on_rows: every grid must be contiguous float32 {tuple(value.shape)}")
    dev = device_of(value)
    ensure_loaded(adam_rows, dev)
    args = [wp.from_torch(rows.contiguous(), dtype=wp.int64)] + [wp.from_torch(t) for t in (value, grad, exp_avg, exp_avg_sq)]
    args += [wp.from_torch(mask), float(beta1), float(beta2), float(step_size), float(root_bc2), float(eps)]
    parallel_map(lambda ab: wp.launch(adam_rows, dim=ab[1] - ab[0], inputs=args + [ab[0]], device=dev),
                 launch_chunks(n, dev))
