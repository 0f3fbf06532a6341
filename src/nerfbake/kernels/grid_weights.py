"""Which voxels of a dense density grid matter to the training views (PlenOctrees' weight masking).

Each ray walks the grid voxel by voxel (exact segment lengths: step to the voxel's exit plus a tiny epsilon,
the same stepping as the octree renderer) and marks voxels where its compositing weight T*alpha reaches
``weight_thresh``. 8^3 blocks whose densest voxel cannot reach an alpha of ``skip_alpha`` are stepped over
whole. Marks are plain stores of 1, so CPU threads sharing the mask cannot lose an update.
"""
from __future__ import annotations

import torch

from nerfbake.kernels import device_of, ensure_loaded, launch_chunks, parallel_map, warp

wp = warp()
wp.set_module_options({"enable_backward": False})

BLOCK = 8


@wp.func
def exit_dist(p: wp.vec3, d: wp.vec3, lo: wp.vec3, size: float) -> float:
    """Distance along d from p (inside the cube [lo, lo + size]^3) to the cube's boundary."""
    t = float(1.0e9)
    for a in range(3):
        if d[a] > 0.0:
            t = wp.min(t, (lo[a] + size - p[a]) / d[a])
        elif d[a] < 0.0:
            t = wp.min(t, (lo[a] - p[a]) / d[a])
    return wp.max(t, 0.0)


@wp.kernel
def mark_weights(
    origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), sigma: wp.array3d(dtype=float),
    block_live: wp.array3d(dtype=wp.uint8), box_min: wp.vec3, voxel: wp.vec3, weight_thresh: float, ray0: int,
    keep: wp.array3d(dtype=wp.uint8),
):
    """One thread per ray (from ``ray0``): march the dense ``sigma`` (G, G, G) grid and set ``keep`` (G, G, G) where
    a voxel's compositing weight reaches ``weight_thresh`` (8^3 blocks ``block_live`` marks empty are skipped)."""
    r = ray0 + wp.tid()
    g = sigma.shape[0]
    # march in voxel units, where the grid is the cube [0, g]^3 and voxels are unit cubes
    o = wp.cw_div(origins[r] - box_min, voxel)
    dw = dirs[r]
    ds = wp.cw_div(dw, voxel)
    scale = wp.length(ds)
    d = ds / scale  # unit direction in voxel space; world length = voxel-space length / scale
    t0 = float(0.0)
    t1 = float(1.0e9)
    for a in range(3):
        if d[a] != 0.0:
            ta = (0.0 - o[a]) / d[a]
            tb = (float(g) - o[a]) / d[a]
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
        elif o[a] < 0.0 or o[a] > float(g):
            t1 = -1.0
    t = t0
    T = float(1.0)
    eps = 1.0e-4
    while t < t1 and T >= weight_thresh:
        p = o + t * d
        i = wp.clamp(int(wp.floor(p[0])), 0, g - 1)
        j = wp.clamp(int(wp.floor(p[1])), 0, g - 1)
        k = wp.clamp(int(wp.floor(p[2])), 0, g - 1)
        bi = i / 8
        bj = j / 8
        bk = k / 8
        if block_live[bi, bj, bk] == wp.uint8(0):
            t += exit_dist(p, d, wp.vec3(float(bi * 8), float(bj * 8), float(bk * 8)), 8.0) + eps
        else:
            seg = exit_dist(p, d, wp.vec3(float(i), float(j), float(k)), 1.0)
            alpha = 1.0 - wp.exp(-sigma[i, j, k] * seg / scale)
            if T * alpha >= weight_thresh:
                keep[i, j, k] = wp.uint8(1)
            T = T * (1.0 - alpha)
            t += seg + eps


def mark_visible_voxels(origins: torch.Tensor, dirs: torch.Tensor, sigma: torch.Tensor, block_live: torch.Tensor,
                        box_min, box_max, weight_thresh: float, keep: torch.Tensor) -> None:
    """Set ``keep`` (G^3 uint8) to 1 where some ray's weight reaches ``weight_thresh``; G a multiple of 8."""
    n = origins.shape[0]
    if n == 0:
        return
    dev = device_of(origins)
    g = sigma.shape[0]
    voxel = ((torch.as_tensor(box_max, dtype=torch.float64) - torch.as_tensor(box_min, dtype=torch.float64)) / g).tolist()
    args = [
        wp.from_torch(origins.contiguous().float(), dtype=wp.vec3), wp.from_torch(dirs.contiguous().float(), dtype=wp.vec3),
        wp.from_torch(sigma.contiguous().float()), wp.from_torch(block_live.to(torch.uint8).contiguous()),
        wp.vec3(*[float(v) for v in box_min]), wp.vec3(*voxel), float(weight_thresh),
    ]
    out = wp.from_torch(keep)
    ensure_loaded(mark_weights, dev)
    parallel_map(lambda c: wp.launch(mark_weights, dim=c[1] - c[0], inputs=[*args, c[0], out], device=dev), launch_chunks(n, dev))
