"""Ray marching through an occupancy grid (empty-space skipping) as Warp kernels.

Each ray steps from ``t_near`` (plus a per-ray offset in [0, dt) for training) to ``t_far`` in steps of
``dt`` and keeps the steps whose midpoint falls in an occupied cell of a G^3 grid over an axis-aligned box.
Two passes: count per ray, then write packed samples at offsets from the prefix sum. Output is "packed":
``ray_idx`` (S,), interval ends ``t0``, ``t1`` (S,), sorted by ray then t.

Unbounded scenes (``contract_centre``/``contract_half`` given): the grid covers MERF-contracted space [-2, 2]^3 of
``q = (x - centre) / half``, and a step taken where ``r = ||q||_inf > 1`` is ``dt * r^2`` long: about the same
length in contracted space everywhere (d(2 - 1/r)/dr = 1/r^2), so the far field costs a fixed number of steps
(instant-ngp's cascaded grids with cone-angle steps, in one grid).
"""
from __future__ import annotations

import torch

from nerfbake.kernels import device_of, ensure_loaded, launch_chunks, parallel_map, warp

wp = warp()
wp.set_module_options({"enable_backward": False})


@wp.func
def occupied(p: wp.vec3, box_min: wp.vec3, inv_cell: wp.vec3, grid: wp.array3d(dtype=wp.uint8)) -> int:
    """1 if point ``p`` lies in an occupied cell of ``grid`` (G, G, G) over the box from ``box_min`` (cell size 1 /
    ``inv_cell``), else 0."""
    g = grid.shape[0]
    q = wp.cw_mul(p - box_min, inv_cell)
    i = int(wp.floor(q[0]))
    j = int(wp.floor(q[1]))
    k = int(wp.floor(q[2]))
    if i < 0 or j < 0 or k < 0 or i >= g or j >= g or k >= g:
        return 0
    return int(grid[i, j, k])


@wp.func
def grid_position(p: wp.vec3, box_min: wp.vec3, inv_cell: wp.vec3, centre: wp.vec3, inv_half: wp.vec3, contracted: int) -> wp.vec3:
    """The point the grid is looked up at: p itself, or its MERF contraction (then box_min is -2, inv_cell G/4)."""
    if contracted == 0:
        return p
    q = wp.cw_mul(p - centre, inv_half)
    r = wp.max(wp.abs(q[0]), wp.max(wp.abs(q[1]), wp.abs(q[2])))
    if r <= 1.0:
        return q
    c = q / r
    for a in range(3):
        if wp.abs(q[a]) >= r:
            c[a] = wp.sign(q[a]) * (2.0 - 1.0 / r)
    return c


@wp.func
def step_length(p: wp.vec3, dt: float, centre: wp.vec3, inv_half: wp.vec3, contracted: int) -> float:
    """dt, or dt * r^2 beyond the unit cube of contracted marching (a near-constant step in contracted space)."""
    if contracted == 0:
        return dt
    q = wp.cw_mul(p - centre, inv_half)
    r = wp.max(wp.abs(q[0]), wp.max(wp.abs(q[1]), wp.abs(q[2])))
    return dt * wp.max(1.0, r * r)


@wp.kernel
def march_count(
    origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), t_near: wp.array(dtype=float),
    t_far: wp.array(dtype=float), offset: wp.array(dtype=float), grid: wp.array3d(dtype=wp.uint8),
    box_min: wp.vec3, inv_cell: wp.vec3, dt: float, max_steps: int, centre: wp.vec3, inv_half: wp.vec3,
    contracted: int, ray0: int, counts: wp.array(dtype=wp.int32),
):
    """One thread per ray (from ``ray0``): how many intervals of length ``dt`` (stretched by the contraction where
    ``contracted``) between ``t_near`` and ``t_far`` fall in occupied cells, into ``counts`` (R,)."""
    r = ray0 + wp.tid()
    o = origins[r]
    d = dirs[r]
    t = t_near[r] + offset[r] * step_length(o + t_near[r] * d, dt, centre, inv_half, contracted)
    n = int(0)
    steps = int(0)
    while t < t_far[r] and steps < max_steps:
        h = step_length(o + t * d, dt, centre, inv_half, contracted)
        if occupied(grid_position(o + (t + 0.5 * h) * d, box_min, inv_cell, centre, inv_half, contracted),
                    box_min, inv_cell, grid) == 1:
            n += 1
        t += h
        steps += 1
    counts[r] = n


@wp.kernel
def march_write(
    origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), t_near: wp.array(dtype=float),
    t_far: wp.array(dtype=float), offset: wp.array(dtype=float), grid: wp.array3d(dtype=wp.uint8),
    box_min: wp.vec3, inv_cell: wp.vec3, dt: float, max_steps: int, centre: wp.vec3, inv_half: wp.vec3,
    contracted: int, ray0: int, starts: wp.array(dtype=wp.int32),
    ray_idx: wp.array(dtype=wp.int32), t0: wp.array(dtype=float), t1: wp.array(dtype=float),
):
    """One thread per ray: the intervals :func:`march_count` counted, written from ``starts[r]`` into ``ray_idx``,
    ``t0``, ``t1`` (S,)."""
    r = ray0 + wp.tid()
    o = origins[r]
    d = dirs[r]
    t = t_near[r] + offset[r] * step_length(o + t_near[r] * d, dt, centre, inv_half, contracted)
    s = starts[r]
    steps = int(0)
    while t < t_far[r] and steps < max_steps:
        h = step_length(o + t * d, dt, centre, inv_half, contracted)
        if occupied(grid_position(o + (t + 0.5 * h) * d, box_min, inv_cell, centre, inv_half, contracted),
                    box_min, inv_cell, grid) == 1:
            ray_idx[s] = r
            t0[s] = t
            t1[s] = wp.min(t + h, t_far[r])
            s += 1
        t += h
        steps += 1


def march_rays(
    origins: torch.Tensor, dirs: torch.Tensor, t_near: torch.Tensor, t_far: torch.Tensor, grid: torch.Tensor,
    box_min: torch.Tensor, box_max: torch.Tensor, dt: float, offset: torch.Tensor | None = None, max_steps: int = 4096,
    contract_centre: torch.Tensor | None = None, contract_half: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Packed samples (ray_idx long (S,), t0 (S,), t1 (S,)) in occupied cells of ``grid`` (G,G,G) bool/uint8.

    With ``contract_centre``/``contract_half`` (3,) the grid spans contracted space and ``box_min``/``box_max``
    must be -2 and 2 (see the module docstring); ``dt`` is then the step inside the unit cube."""
    n = origins.shape[0]
    dev = device_of(origins)
    if offset is None:
        offset = torch.zeros(n, device=origins.device)
    g = grid.shape[0]
    inv_cell = (g / (box_max - box_min)).tolist()
    contracted = contract_centre is not None
    centre = contract_centre.tolist() if contracted else [0.0] * 3
    inv_half = (1.0 / contract_half).tolist() if contracted else [1.0] * 3
    common = [
        wp.from_torch(origins.contiguous().float(), dtype=wp.vec3), wp.from_torch(dirs.contiguous().float(), dtype=wp.vec3),
        wp.from_torch(t_near.contiguous().float()), wp.from_torch(t_far.contiguous().float()),
        wp.from_torch(offset.contiguous().float()), wp.from_torch(grid.to(torch.uint8).contiguous()),
        wp.vec3(*box_min.tolist()), wp.vec3(*inv_cell), float(dt), int(max_steps),
        wp.vec3(*centre), wp.vec3(*inv_half), int(contracted),
    ]
    counts = torch.zeros(n, dtype=torch.int32, device=origins.device)
    wc = wp.from_torch(counts)
    chunks = launch_chunks(n, dev)
    ensure_loaded(march_count, dev)
    parallel_map(lambda c: wp.launch(march_count, dim=c[1] - c[0], inputs=[*common, c[0], wc], device=dev), chunks)
    csum = torch.cumsum(counts, 0, dtype=torch.int64)
    total = int(csum[-1]) if n else 0
    starts = (csum - counts).to(torch.int32)
    ray_idx = torch.empty(total, dtype=torch.int32, device=origins.device)
    t0 = torch.empty(total, device=origins.device)
    t1 = torch.empty(total, device=origins.device)
    if total:
        outs = [wp.from_torch(starts), wp.from_torch(ray_idx), wp.from_torch(t0), wp.from_torch(t1)]
        parallel_map(lambda c: wp.launch(march_write, dim=c[1] - c[0], inputs=[*common, c[0], *outs], device=dev), chunks)
    return ray_idx.long(), t0, t1
