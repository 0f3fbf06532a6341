"""Adam that visits only the grid rows a step wrote (as instant-ngp skips hash entries with a zero gradient).

A SMERF student's grids hold ~160 M values at the CPU preset, while one step's rays and empty-space points touch a
few per cent of the sparse grid's rows. Dense Adam reads and writes all four grid-sized tensors (value, gradient,
two moments) every step and the gradient is zeroed whole again: a fifth of a distillation step on bonsai. Here a
parameter registered with a uint8 row mask (set by whatever writes its gradient, e.g. the MERF lookup's backward)
is updated on the masked rows only (by a Warp kernel that works on the rows where they lie), its gradient zeroed on
those rows only, and the mask cleared; the moments of
rows a step did not touch stay as they were (``torch.optim.SparseAdam``'s rule) instead of decaying and still
moving the value. Other parameters get torch's fused Adam. Update and state names are ``torch.optim.Adam``'s, so its
checkpoints load here and, with every row touched, the two agree step for step.
"""
from __future__ import annotations

import math

import torch
from torch.optim.adam import adam

from nerfbake.kernels.row_adam import adam_on_rows


class RowAdam(torch.optim.Optimizer):
    """``torch.optim.Adam`` (no weight decay, no amsgrad) over ``params``; each parameter in ``row_masks`` (a dict
    parameter -> uint8 mask over its first axis) is updated lazily on its masked rows. Invariant: the gradient of a
    masked parameter is zero outside its mask, so whatever writes the gradient must set the mask."""

    def __init__(self, params, row_masks: dict | None = None, lr: float = 1e-3, betas=(0.9, 0.999),
                 eps: float = 1e-8):
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps})
        self.row_masks = {}
        for p, mask in (row_masks or {}).items():
            if mask.dtype != torch.uint8 or mask.shape != p.shape[:1] or mask.device != p.device:
                raise ValueError(f"row mask {tuple(mask.shape)} {mask.dtype} on {mask.device} does not fit a "
                                 f"parameter {tuple(p.shape)} on {p.device}: one uint8 per row, same device")
            self.row_masks[p] = mask

    def _touched_rows(self, p) -> torch.Tensor | None:
        """Row indices the mask holds for ``p`` (None for a dense parameter)."""
        mask = self.row_masks.get(p)
        return None if mask is None else mask.nonzero().squeeze(1)

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            lr, (b1, b2), eps = group["lr"], group["betas"], group["eps"]
            dense = []
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)  # fused Adam's place
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                if p not in self.row_masks:
                    dense.append(p)
                    continue
                state["step"] += 1
                n = float(state["step"])
                adam_on_rows(self._touched_rows(p), p.data, p.grad, state["exp_avg"], state["exp_avg_sq"],
                             self.row_masks[p], b1, b2, lr / (1 - b1 ** n), math.sqrt(1 - b2 ** n), eps)
            if dense:  # torch's own fused Adam (it counts the steps itself)
                adam([p.data for p in dense], [p.grad for p in dense], *([self.state[p][k] for p in dense]
                     for k in ("exp_avg", "exp_avg_sq")), [], [self.state[p]["step"] for p in dense], fused=True,
                     amsgrad=False, beta1=b1, beta2=b2, lr=lr, weight_decay=0.0, eps=eps, maximize=False)
        return loss

    @torch.no_grad()
    def zero_grad(self, set_to_none: bool = False):
        """Dense parameters as torch does; a masked parameter's gradient on its masked rows only (after
        :meth:`step` there are none left), so no grid-sized write happens."""
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                rows = self._touched_rows(p)
                if rows is None:
                    if set_to_none:
                        p.grad = None
                    else:
                        p.grad.zero_()
                elif rows.numel():
                    p.grad.index_fill_(0, rows, 0.0)
                    self.row_masks[p].index_fill_(0, rows, 0)

