"""PlenOctree volume rendering as Warp kernels (one source for CPU and CUDA): forward and analytic backward.

Per ray, as svox/volrend do: map the ray into tree space, clip it to the slicing box, then repeatedly descend
from the root to the leaf containing the current point, take one sample spanning the leaf up to its exit,
and step past the exit by ``step_size``. Samples with sigma <= ``sigma_thresh`` are skipped; the march stops
once transmittance falls below ``stop_thresh`` (the colour is then renormalised by 1/(1-T), as volrend does),
otherwise the background is blended with the remaining transmittance.

The backward (PlenOctrees appendix B.3) re-marches each ray twice: the forward pass gives the final colour,
then for sample i with weight w_i = T_i a_i, colour c_i = sigmoid(sum_k Y_k s_ik):
  dC/ds_ik = w_i c_i (1 - c_i) Y_k
  dC/dsigma_i = delta_i (T_{i+1} c_i - (C - sum_{j<=i} w_j c_j))     (delta_i in world units)
It assumes no early stop (``stop_thresh`` 0), as svox's training renderer does.
"""
from __future__ import annotations

from dataclasses import replace

import torch

from nerfbake.kernels import cpu_threads, device_of, ensure_loaded, launch_chunks, parallel_map, warp
from nerfbake.render.envmap import sample_equirect

wp = warp()
wp.set_module_options({"enable_backward": False})

vec25 = wp.types.vector(length=25, dtype=wp.float32)
MAX_DEPTH = 24


@wp.func
def sh_basis(d: wp.vec3) -> vec25:
    """Real SH to degree 4 in the svox sign convention (must agree with nerfbake.render.sh)."""
    x = d[0]
    y = d[1]
    z = d[2]
    xx = x * x
    yy = y * y
    zz = z * z
    xy = x * y
    yz = y * z
    xz = x * z
    b = vec25()
    b[0] = 0.28209479177387814
    b[1] = -0.4886025119029199 * y
    b[2] = 0.4886025119029199 * z
    b[3] = -0.4886025119029199 * x
    b[4] = 1.0925484305920792 * xy
    b[5] = -1.0925484305920792 * yz
    b[6] = 0.31539156525252005 * (2.0 * zz - xx - yy)
    b[7] = -1.0925484305920792 * xz
    b[8] = 0.5462742152960396 * (xx - yy)
    b[9] = -0.5900435899266435 * y * (3.0 * xx - yy)
    b[10] = 2.890611442640554 * xy * z
    b[11] = -0.4570457994644658 * y * (4.0 * zz - xx - yy)
    b[12] = 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
    b[13] = -0.4570457994644658 * x * (4.0 * zz - xx - yy)
    b[14] = 1.445305721320277 * z * (xx - yy)
    b[15] = -0.5900435899266435 * x * (xx - 3.0 * yy)
    b[16] = 2.5033429417967046 * xy * (xx - yy)
    b[17] = -1.7701307697799304 * yz * (3.0 * xx - yy)
    b[18] = 0.9461746957575601 * xy * (7.0 * zz - 1.0)
    b[19] = -0.6690465435572892 * yz * (7.0 * zz - 3.0)
    b[20] = 0.10578554691520431 * (zz * (35.0 * zz - 30.0) + 3.0)
    b[21] = -0.6690465435572892 * xz * (7.0 * zz - 3.0)
    b[22] = 0.47308734787878004 * (xx - yy) * (7.0 * zz - 1.0)
    b[23] = -1.7701307697799304 * xz * (xx - 3.0 * yy)
    b[24] = 0.6258357354491761 * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy))
    return b


@wp.func
def leaf_at(child: wp.array(dtype=wp.int32), p: wp.vec3):
    """(flat cell index, cells per axis at the leaf's depth, point in leaf-local [0,1)^3)."""
    q = wp.vec3(wp.clamp(p[0], 0.0, 0.9999999), wp.clamp(p[1], 0.0, 0.9999999), wp.clamp(p[2], 0.0, 0.9999999))
    node = int(0)
    cube = float(1.0)
    slot = int(0)
    for _ in range(MAX_DEPTH):
        q = q * 2.0
        cube = cube * 2.0
        ix = wp.clamp(int(wp.floor(q[0])), 0, 1)
        iy = wp.clamp(int(wp.floor(q[1])), 0, 1)
        iz = wp.clamp(int(wp.floor(q[2])), 0, 1)
        q = q - wp.vec3(float(ix), float(iy), float(iz))
        slot = node * 8 + ix * 4 + iy * 2 + iz
        skip = child[slot]
        if skip == 0:
            break
        node = node + skip
    return slot, cube, q


@wp.func
def leaf_exit(q: wp.vec3, d: wp.vec3, cube: float) -> float:
    """Tree-space distance from leaf-local point q along d to the leaf's boundary."""
    t = float(1.0e9)
    for a in range(3):
        if d[a] > 0.0:
            t = wp.min(t, (1.0 - q[a]) / d[a])
        elif d[a] < 0.0:
            t = wp.min(t, -q[a] / d[a])
    return t / cube


@wp.func
def ray_setup(o: wp.vec3, d: wp.vec3, offset: wp.vec3, invradius: wp.vec3, bb_min: wp.vec3, bb_max: wp.vec3):
    """Tree-space origin and unit direction, world units per tree unit, and the [t0, t1] inside the box."""
    ot = offset + wp.cw_mul(invradius, o)
    ds = wp.cw_mul(invradius, d)
    scale = wp.length(ds)
    dt = ds / scale
    t0 = float(0.0)
    t1 = float(1.0e9)
    for a in range(3):
        if dt[a] != 0.0:
            inv = 1.0 / dt[a]
            ta = (bb_min[a] - ot[a]) * inv
            tb = (bb_max[a] - ot[a]) * inv
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
        elif ot[a] < bb_min[a] or ot[a] > bb_max[a]:
            t1 = -1.0
    return ot, dt, 1.0 / scale, t0, t1


@wp.func
def leaf_color(data: wp.array2d(dtype=float), slot: int, basis: vec25, nb: int, lo: int, hi: int) -> wp.vec3:
    """RGB of leaf ``slot``: the SH components [lo, hi) of ``data`` (leaves, 3 * nb + 1) dotted with ``basis``,
    through a sigmoid (svox's convention)."""
    c = wp.vec3()
    for ch in range(3):
        s = float(0.0)
        for k in range(lo, hi):
            s += basis[k] * data[slot, ch * nb + k]
        c[ch] = 1.0 / (1.0 + wp.exp(-s))
    return c


@wp.kernel
def octree_forward(
    origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), child: wp.array(dtype=wp.int32),
    data: wp.array2d(dtype=float), offset: wp.vec3, invradius: wp.vec3, bb_min: wp.vec3, bb_max: wp.vec3,
    nb: int, lo: int, hi: int, step_size: float, sigma_thresh: float, stop_thresh: float, background: wp.vec3,
    ray0: int, rgb: wp.array(dtype=wp.vec3), depth: wp.array(dtype=float), alpha: wp.array(dtype=float),
):
    """One thread per ray (from ``ray0``): volrend's march through the tree (``child`` links, ``data`` leaves) ->
    ``rgb`` (R, 3) on ``background``, expected ``depth`` (R,) and ``alpha`` (R,)."""
    r = ray0 + wp.tid()
    d = dirs[r]
    ot, dt, to_world, t, t_end = ray_setup(origins[r], d, offset, invradius, bb_min, bb_max)
    basis = sh_basis(d)
    sig = data.shape[1] - 1
    acc = wp.vec3()
    dep = float(0.0)
    T = float(1.0)
    stopped = int(0)
    while t < t_end:
        slot, cube, q = leaf_at(child, ot + t * dt)
        delta = leaf_exit(q, dt, cube)
        sigma = data[slot, sig]
        if sigma > sigma_thresh:
            att = wp.exp(-delta * to_world * sigma)
            w = T * (1.0 - att)
            acc += w * leaf_color(data, slot, basis, nb, lo, hi)
            dep += w * (t + 0.5 * delta) * to_world
            T = T * att
            if T < stop_thresh:
                stopped = 1
                break
        t += delta + step_size
    if stopped == 1:
        rgb[r] = acc / (1.0 - T)
        alpha[r] = 1.0
    else:
        rgb[r] = acc + T * background
        alpha[r] = 1.0 - T
    depth[r] = dep


@wp.kernel
def octree_backward(
    origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), child: wp.array(dtype=wp.int32),
    data: wp.array2d(dtype=float), offset: wp.vec3, invradius: wp.vec3, bb_min: wp.vec3, bb_max: wp.vec3,
    nb: int, lo: int, hi: int, step_size: float, sigma_thresh: float, background: wp.vec3,
    ray0: int, rgb_out: wp.array(dtype=wp.vec3), grad_rgb: wp.array(dtype=wp.vec3), grad: wp.array2d(dtype=float),
):
    """One thread per ray: the analytic gradient of :func:`octree_forward`'s colour (given ``rgb_out`` and
    ``grad_rgb``, (R, 3)) with respect to every leaf's values, added into ``grad`` (leaves, data_dim)."""
    r = ray0 + wp.tid()
    d = dirs[r]
    g = grad_rgb[r]
    ot, dt, to_world, t, t_end = ray_setup(origins[r], d, offset, invradius, bb_min, bb_max)
    basis = sh_basis(d)
    sig = data.shape[1] - 1
    rest = rgb_out[r]  # C - sum_{j<=i} w_j c_j, updated as we go
    T = float(1.0)
    while t < t_end:
        slot, cube, q = leaf_at(child, ot + t * dt)
        delta = leaf_exit(q, dt, cube)
        sigma = data[slot, sig]
        if sigma > sigma_thresh:
            dw = delta * to_world
            att = wp.exp(-dw * sigma)
            w = T * (1.0 - att)
            c = leaf_color(data, slot, basis, nb, lo, hi)
            rest = rest - w * c
            for ch in range(3):
                gs = g[ch] * w * c[ch] * (1.0 - c[ch])
                for k in range(lo, hi):
                    wp.atomic_add(grad, slot, ch * nb + k, gs * basis[k])
            T = T * att
            wp.atomic_add(grad, slot, sig, dw * wp.dot(g, T * c - rest))
        t += delta + step_size


def _common(tree, origins, dirs, opts):
    nb = tree.num_basis
    lo, hi = opts.basis_range(nb)
    return [
        wp.from_torch(origins.contiguous().float(), dtype=wp.vec3), wp.from_torch(dirs.contiguous().float(), dtype=wp.vec3),
        wp.from_torch(tree.child.reshape(-1).contiguous()), wp.from_torch(tree.data.detach().reshape(-1, tree.data_dim).contiguous()),
        wp.vec3(*tree.offset.tolist()), wp.vec3(*tree.invradius.tolist()),
        wp.vec3(*opts.bbox_min), wp.vec3(*opts.bbox_max), nb, lo, hi, float(opts.step_size), float(opts.sigma_thresh),
    ]


def render_forward(tree, origins: torch.Tensor, dirs: torch.Tensor, opts) -> dict[str, torch.Tensor]:
    """rgb (R, 3), depth (R,) along the world ray, alpha (R,) for unit ``dirs`` in world space. A tree with an
    environment map shows it where ``opts.background`` would be: the kernel composites on black and the map is
    added with the remaining transmittance 1 - alpha (zero for rays that stopped early). The backward kernel needs
    nothing more: it reads the background through the forward's ``rgb``."""
    out = _render_forward(tree, origins, dirs, opts if tree.env_map is None else replace(opts, background=(0.0, 0.0, 0.0)))
    if tree.env_map is not None and origins.shape[0]:
        out["rgb"] = out["rgb"] + (1.0 - out["alpha"])[:, None] * sample_equirect(tree.env_map, dirs)
    return out


def _render_forward(tree, origins: torch.Tensor, dirs: torch.Tensor, opts) -> dict[str, torch.Tensor]:
    n = origins.shape[0]
    dev = device_of(origins)
    rgb = torch.empty(n, 3, device=origins.device)
    depth = torch.empty(n, device=origins.device)
    alpha = torch.empty(n, device=origins.device)
    if n == 0:
        return {"rgb": rgb, "depth": depth, "alpha": alpha}
    common = _common(tree, origins, dirs, opts) + [float(opts.stop_thresh), wp.vec3(*opts.background)]
    outs = [wp.from_torch(rgb, dtype=wp.vec3), wp.from_torch(depth), wp.from_torch(alpha)]
    ensure_loaded(octree_forward, dev)
    parallel_map(lambda c: wp.launch(octree_forward, dim=c[1] - c[0], inputs=[*common, c[0], *outs], device=dev),
                 launch_chunks(n, dev))
    return {"rgb": rgb, "depth": depth, "alpha": alpha}


def backward_buffers(tree) -> list[torch.Tensor]:
    """Gradient accumulators for :func:`render_backward`: one per CPU thread (Warp's CPU atomics are plain
    adds), one on a GPU. Allocate once and pass to every call: each is the size of the leaf data."""
    parts = 1 if tree.device.type != "cpu" else cpu_threads()
    return [torch.zeros(tree.num_nodes * 8, tree.data_dim, device=tree.device) for _ in range(parts)]


def render_backward(tree, origins, dirs, opts, rgb_out: torch.Tensor, grad_rgb: torch.Tensor,
                    buffers: list[torch.Tensor] | None = None) -> torch.Tensor:
    """d loss / d tree.data (same shape) given d loss / d rgb for rays rendered with ``stop_thresh`` 0.
    The result is a view of ``buffers[0]`` (overwritten by the next call)."""
    n = origins.shape[0]
    dev = device_of(origins)
    bufs = buffers if buffers is not None else backward_buffers(tree)
    for b in bufs:
        b.zero_()
    common = _common(tree, origins, dirs, opts) + [wp.vec3(*opts.background)]
    outs = [wp.from_torch(rgb_out.contiguous().float(), dtype=wp.vec3), wp.from_torch(grad_rgb.contiguous().float(), dtype=wp.vec3)]
    chunks = launch_chunks(n, dev, len(bufs))
    ensure_loaded(octree_backward, dev)
    if n:
        parallel_map(lambda cb: wp.launch(octree_backward, dim=cb[0][1] - cb[0][0],
                                          inputs=[*common, cb[0][0], *outs, wp.from_torch(cb[1])], device=dev),
                     list(zip(chunks, bufs)))
    grad = bufs[0]
    for b in bufs[1:]:
        grad += b
    return grad.view(tree.data.shape)
