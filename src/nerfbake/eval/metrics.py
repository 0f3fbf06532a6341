"""Image quality metrics as the papers compute them.

Images are float tensors in [0, 1] shaped (H, W, 3) or (N, H, W, 3) (channels last, like every image in
nerfbake). PSNR is per image; SSIM is mip-NeRF's: 11x11 Gaussian window with sigma 1.5, valid
convolution, k1 = 0.01, k2 = 0.03, averaged over pixels and channels. DSSIM = (1 - SSIM) / 2 for losses.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from nerfbake.data.images import load_image_uint8, to_float
from nerfbake.eval.lpips import lpips


def _as_batch(img) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(img) if not isinstance(img, torch.Tensor) else img, dtype=torch.float32)
    if t.ndim == 3:
        t = t[None]
    if t.ndim != 4 or t.shape[-1] not in (1, 3):
        raise ValueError(f"expected an image shaped (H, W, 3) or (N, H, W, 3), got {tuple(t.shape)}")
    return t


def mse(a, b) -> torch.Tensor:
    a, b = _as_batch(a), _as_batch(b)
    return ((a - b) ** 2).mean(dim=(1, 2, 3))


def psnr(a, b) -> torch.Tensor:
    """Per-image PSNR in dB for [0, 1] images (inputs are clipped to [0, 1] first)."""
    a, b = _as_batch(a).clamp(0, 1), _as_batch(b).clamp(0, 1)
    return -10.0 * torch.log10(mse(a, b).clamp_min(1e-10))


def _gaussian_kernel(size: int, sigma: float, device, dtype) -> torch.Tensor:
    x = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _filter_valid(x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Separable valid convolution of (N, C, H, W) with the 1-D kernel k along H then W."""
    c = x.shape[1]
    x = F.conv2d(x, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return F.conv2d(x, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)


def ssim_map(a, b, window: int = 11, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03,
             filter_fn=None, clip: bool = True) -> torch.Tensor:
    """Per-pixel SSIM, (N, C, H', W'). ``filter_fn`` replaces the Gaussian (e.g. a box filter on 3x3 patches).
    ``clip`` bounds the statistics as mip-NeRF's metric does; losses turn it off, because the square root's
    gradient is infinite on flat patches (variance 0) and would make the loss NaN."""
    a, b = _as_batch(a), _as_batch(b)
    x, y = a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2)
    if filter_fn is None:
        kern = _gaussian_kernel(window, sigma, x.device, x.dtype)
        filter_fn = lambda z: _filter_valid(z, kern)  # noqa: E731
    mu_x, mu_y = filter_fn(x), filter_fn(y)
    sxx = filter_fn(x * x) - mu_x**2
    syy = filter_fn(y * y) - mu_y**2
    sxy = filter_fn(x * y) - mu_x * mu_y
    # Clip the variances as mip-NeRF does; float error can make them slightly negative.
    if clip:
        sxx, syy = sxx.clamp_min(0), syy.clamp_min(0)
        sxy = torch.sign(sxy) * torch.minimum(torch.sqrt(sxx * syy), sxy.abs())
    c1, c2 = k1**2, k2**2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2)
    return num / den


def ssim(a, b) -> torch.Tensor:
    """Per-image SSIM (mip-NeRF form), shape (N,)."""
    return ssim_map(a, b).mean(dim=(1, 2, 3))


def dssim(a, b, filter_fn=None) -> torch.Tensor:
    """Structural dissimilarity (1 - SSIM) / 2, averaged over everything: a differentiable loss."""
    return (1.0 - ssim_map(a, b, filter_fn=filter_fn, clip=False).mean()) / 2.0


def patch_dssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """DSSIM on a batch of 3x3 patches (P, 3, 3, 3) with a box filter over each patch (SMERF's distillation loss)."""
    box = lambda z: z.mean(dim=(2, 3), keepdim=True)  # noqa: E731
    return dssim(a, b, filter_fn=box)


def image_metrics(pred, gt, lpips_nets: tuple[str, ...] = ("alex", "vgg")) -> dict[str, float]:
    """PSNR, SSIM and the requested LPIPS variants for one image pair, as plain floats."""
    out = {"psnr": float(psnr(pred, gt)[0]), "ssim": float(ssim(pred, gt)[0])}
    for net in lpips_nets:
        out[f"lpips_{net}"] = float(lpips(pred, gt, net)[0])
    return out


def compare_image_files(reference, scored) -> dict[str, float]:
    """``nerfbake metrics A B``: :func:`image_metrics` of image ``scored`` against ``reference`` (RGBA on white)."""
    a, b = (to_float(load_image_uint8(Path(p), disk_cache=False), background=(1.0, 1.0, 1.0)) for p in (reference, scored))
    if a.shape != b.shape:
        raise ValueError(f"{scored}: size {b.shape[1]}x{b.shape[0]} differs from {reference}'s {a.shape[1]}x{a.shape[0]}; "
                         "compare images of the same size")
    return image_metrics(b, a)
