"""Step functions along rays (after camp_zipnerf's stepfun): ``t`` (..., S+1) sorted endpoints, ``w`` (..., S)
weights. Used by the proposal sampler's losses."""
from __future__ import annotations

import torch


def inner_outer(t_query: torch.Tensor, t: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For each query interval, the weight of (t, w) wholly inside it (inner) and touching it (outer)."""
    cw = torch.cat([torch.zeros_like(w[..., :1]), torch.cumsum(w, dim=-1)], dim=-1)
    t = t.contiguous()
    lo = torch.searchsorted(t, t_query[..., :-1].contiguous(), right=True) - 1
    hi = torch.searchsorted(t, t_query[..., 1:].contiguous(), right=False)
    n = t.shape[-1] - 1
    lo_c, hi_c = lo.clamp(0, n), hi.clamp(0, n)
    outer = cw.gather(-1, hi_c) - cw.gather(-1, lo_c)
    lo_i, hi_i = (lo + 1).clamp(0, n), (hi - 1).clamp(0, n)
    inner = (cw.gather(-1, hi_i) - cw.gather(-1, lo_i)).clamp_min(0)
    return inner, outer


def interlevel_loss(t_final: torch.Tensor, w_final: torch.Tensor, t_prop: torch.Tensor, w_prop: torch.Tensor,
                    eps: float = 1e-7) -> torch.Tensor:
    """mip-NeRF 360 eq. 13: proposal weights must bound the (stopped-gradient) final weights from above."""
    w_final = w_final.detach()
    _, outer = inner_outer(t_final.detach(), t_prop, w_prop)
    return (torch.clamp(w_final - outer, min=0) ** 2 / (w_final + eps)).sum(-1).mean()


def distortion_loss(s: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360 eq. 15 in its O(S) form, on normalised distances ``s`` (..., S+1)."""
    mid = 0.5 * (s[..., 1:] + s[..., :-1])
    delta = s[..., 1:] - s[..., :-1]
    wm = w * mid
    w_cum = torch.cumsum(w, -1)
    wm_cum = torch.cumsum(wm, -1)
    inter = 2 * (wm[..., 1:] * w_cum[..., :-1] - w[..., 1:] * wm_cum[..., :-1]).sum(-1)
    intra = (w**2 * delta).sum(-1) / 3
    return (inter + intra).mean()
