"""The SMERF student's feature lookup, exactly as the baked viewer will see it (Warp, CPU and CUDA).

A submodel stores 8 pre-activation channels on a sparse 3-D grid of side S (voxel centres at
``-2 + (i + 0.5) * 4 / S`` in contracted space) and on three planes of side T (plane k drops axis k; texel centres
likewise). At a contracted point the kernel returns the trilinear sparse value and the *sum* of the three bilinear
plane values, both interpolated from vertex values that went through the baker's 8-bit round trip (density
channel in the density range, the other 7 in the feature range), with clamp-to-edge addressing as the viewer's
textures. Gradients pass straight through the rounding (as the authors' ``simulate_quantization``).

Rows: sparse ``sm * S^3 + (u * S + v) * S + w``; planes ``(sm * 3 + k) * T^2 + a * T + b`` with (a, b) the two
kept axes in order (plane 0: (v, w), plane 1: (u, w), plane 2: (u, v)). Axes are the viewer's (u, v, w).
"""
from __future__ import annotations

import torch

from nerfbake.kernels import cpu_threads, device_of, ensure_loaded, launch_chunks, parallel_map, warp
from nerfbake.render.quantize import RANGE_DENSITY, RANGE_FEATURES, simulate

wp = warp()
wp.set_module_options({"enable_backward": False})

CHANNELS = 8
DENSITY_LO, DENSITY_HI = wp.constant(RANGE_DENSITY[0]), wp.constant(RANGE_DENSITY[1])
FEATURE_LO, FEATURE_HI = wp.constant(RANGE_FEATURES[0]), wp.constant(RANGE_FEATURES[1])


@wp.func
def quantized(x: float, channel: int, enabled: int) -> float:
    """``x`` rounded as the 8-bit bake stores channel ``channel`` (0: density, else a feature) when ``enabled``,
    unchanged otherwise."""
    if enabled == 0:
        return x
    lo = FEATURE_LO
    hi = FEATURE_HI
    if channel == 0:
        lo = DENSITY_LO
        hi = DENSITY_HI
    u = (wp.clamp(x, lo, hi) - lo) / (hi - lo)
    return wp.round(u * 255.0) / 255.0 * (hi - lo) + lo


@wp.func
def axis_cell(x: float, res: int) -> wp.vec2:
    """(lower texel index, fraction) along one axis at contracted coordinate x, clamp-to-edge."""
    g = (x + 2.0) / 4.0 * float(res) - 0.5
    g = wp.clamp(g, 0.0, float(res - 1))
    i0 = wp.min(int(wp.floor(g)), res - 2)
    return wp.vec2(float(i0), g - float(i0))


@wp.func
def sparse_corner(z: wp.vec3, s: int, c: int):
    """(row offset within the submodel, weight) of corner c of the trilinear stencil."""
    cu = axis_cell(z[0], s)
    cv = axis_cell(z[1], s)
    cw = axis_cell(z[2], s)
    du = (c >> 2) & 1
    dv = (c >> 1) & 1
    dw = c & 1
    wu = wp.where(du == 1, cu[1], 1.0 - cu[1])
    wv = wp.where(dv == 1, cv[1], 1.0 - cv[1])
    ww = wp.where(dw == 1, cw[1], 1.0 - cw[1])
    row = ((int(cu[0]) + du) * s + int(cv[0]) + dv) * s + int(cw[0]) + dw
    return row, wu * wv * ww


@wp.func
def plane_corner(z: wp.vec3, t: int, k: int, c: int):
    """(row offset within the submodel's planes, weight) of corner c of plane k's bilinear stencil."""
    a = 0
    b = 1
    if k == 0:
        a = 1
        b = 2
    elif k == 1:
        b = 2
    ca = axis_cell(z[a], t)
    cb = axis_cell(z[b], t)
    da = (c >> 1) & 1
    db = c & 1
    w = wp.where(da == 1, ca[1], 1.0 - ca[1]) * wp.where(db == 1, cb[1], 1.0 - cb[1])
    row = k * t * t + (int(ca[0]) + da) * t + int(cb[0]) + db
    return row, w


@wp.kernel
def lookup_forward(z: wp.array(dtype=wp.vec3), sm: wp.array(dtype=wp.int32), sparse: wp.array2d(dtype=wp.float32),
                   planes: wp.array2d(dtype=wp.float32), s: int, t: int, quantize: int, start: int,
                   out_sparse: wp.array2d(dtype=wp.float32), out_planes: wp.array2d(dtype=wp.float32)):
    """One thread per point (from ``start``): the 8 channels of contracted point ``z[n]`` in submodel ``sm[n]``,
    trilinear from the sparse grid (S^3 per submodel) into ``out_sparse`` (N, 8) and bilinear from the three T^2
    planes into ``out_planes`` (N, 8)."""
    n = wp.tid() + start
    p = z[n]
    sbase = sm[n] * s * s * s
    pbase = sm[n] * 3 * t * t
    for ch in range(8):
        acc = float(0.0)
        for c in range(8):
            row, w = sparse_corner(p, s, c)
            acc += w * quantized(sparse[sbase + row, ch], ch, quantize)
        out_sparse[n, ch] = acc
        acc = float(0.0)
        for k in range(3):
            for c in range(4):
                row, w = plane_corner(p, t, k, c)
                acc += w * quantized(planes[pbase + row, ch], ch, quantize)
        out_planes[n, ch] = acc


@wp.kernel
def lookup_backward(z: wp.array(dtype=wp.vec3), sm: wp.array(dtype=wp.int32), grad_sparse_out: wp.array2d(dtype=wp.float32),
                    grad_planes_out: wp.array2d(dtype=wp.float32), s: int, t: int, ch0: int, ch_stride: int,
                    mark_sparse: int, mark_planes: int, grad_sparse: wp.array2d(dtype=wp.float32), grad_planes: wp.array2d(dtype=wp.float32),
                    touched_sparse: wp.array(dtype=wp.uint8), touched_planes: wp.array(dtype=wp.uint8)):
    """Thread (channel, point): scatter the two outputs' gradients (N, 8) into ``grad_sparse`` and ``grad_planes``
    with :func:`lookup_forward`'s weights; channel 0's threads also set the stencil's rows in ``touched_sparse``
    (when ``mark_sparse``) and ``touched_planes`` (when ``mark_planes``): the rows a lazy optimizer must visit."""
    j, n = wp.tid()
    ch = ch0 + j * ch_stride
    p = z[n]
    sbase = sm[n] * s * s * s
    pbase = sm[n] * 3 * t * t
    gs = grad_sparse_out[n, ch]
    gp = grad_planes_out[n, ch]
    flag_s = mark_sparse != 0 and ch == 0
    flag_p = mark_planes != 0 and ch == 0
    for c in range(8):
        row, w = sparse_corner(p, s, c)
        wp.atomic_add(grad_sparse, sbase + row, ch, w * gs)
        if flag_s:
            touched_sparse[sbase + row] = wp.uint8(1)
    for k in range(3):
        for c in range(4):
            row, w = plane_corner(p, t, k, c)
            wp.atomic_add(grad_planes, pbase + row, ch, w * gp)
            if flag_p:
                touched_planes[pbase + row] = wp.uint8(1)


class MerfLookup(torch.autograd.Function):
    """(z (N,3), sm (N,) int32, sparse (rows, 8), planes (rows, 8)) -> sparse values (N, 8), plane sums (N, 8).

    Leaf parameters get their gradient added in place (no grid-sized temporaries per step); CPU backward
    launches deal the 8 channels out over threads so no two threads write the same element. ``touched``, when
    given, is a pair (sparse rows, plane rows) of uint8 row masks or None: the backward sets every row it writes."""

    @staticmethod
    def forward(ctx, z, sm, sparse, planes, s: int, t: int, quantize: bool, touched=None):
        z = z.detach().contiguous().float()
        sm = sm.to(torch.int32).contiguous()
        n = z.shape[0]
        out_s = torch.empty(n, CHANNELS, device=z.device)
        out_p = torch.empty(n, CHANNELS, device=z.device)
        if n:
            dev = device_of(z)
            ensure_loaded(lookup_forward, dev)
            args = [wp.from_torch(z, dtype=wp.vec3), wp.from_torch(sm), wp.from_torch(sparse.detach().contiguous()),
                    wp.from_torch(planes.detach().contiguous()), int(s), int(t), int(quantize)]
            outs = [wp.from_torch(out_s), wp.from_torch(out_p)]
            parallel_map(lambda ab: wp.launch(lookup_forward, dim=ab[1] - ab[0], inputs=args + [ab[0]] + outs, device=dev),
                         launch_chunks(n, dev))
        ctx.save_for_backward(z, sm)
        ctx.params = (sparse, planes)
        ctx.sizes = (int(s), int(t))
        ctx.touched = touched
        return out_s, out_p

    @staticmethod
    def backward(ctx, g_s, g_p):
        z, sm = ctx.saved_tensors
        s, t = ctx.sizes
        grads = []
        for p in ctx.params:
            if p.is_leaf and p.requires_grad:
                if p.grad is None:
                    p.grad = torch.zeros_like(p)
                grads.append(p.grad)
            else:
                grads.append(torch.zeros_like(p))
        n = z.shape[0]
        if n:
            dev = device_of(z)
            ensure_loaded(lookup_backward, dev)
            parts = 1 if dev != "cpu" else min(cpu_threads(), CHANNELS)
            args = [wp.from_torch(z, dtype=wp.vec3), wp.from_torch(sm), wp.from_torch(g_s.contiguous().float()),
                    wp.from_torch(g_p.contiguous().float()), s, t]
            touched = ctx.touched if ctx.touched is not None else (None, None)
            marks = [int(m is not None) for m in touched]
            unused = torch.zeros(1, dtype=torch.uint8, device=z.device)
            outs = [wp.from_torch(grads[0]), wp.from_torch(grads[1])]
            outs += [wp.from_torch(m if m is not None else unused) for m in touched]
            parallel_map(lambda c0: wp.launch(lookup_backward, dim=(len(range(c0, CHANNELS, parts)), n),
                                              inputs=args + [c0, parts] + marks + outs, device=dev), range(parts))
        ret = [None if (p.is_leaf and p.requires_grad) else g for p, g in zip(ctx.params, grads)]
        return None, None, ret[0], ret[1], None, None, None, None


def merf_lookup(z, sm, sparse, planes, s: int, t: int, quantize: bool = True, touched=None):
    """MERF's grid read on the Warp kernels: contracted points ``z`` (N, 3) in [-2, 2]^3 of submodels ``sm`` (N,)
    int32 -> (sparse (N, 8), planes (N, 8)): the trilinear read of submodel ``sm``'s S^3 grid (``sparse``
    rows sm * S^3 + (u * S + v) * S + w) and the sum of its three bilinear T^2 plane reads (``planes`` rows
    (sm * 3 + k) * T^2 + a * T + b), each texel first sent through the viewer's 8-bit round trip when
    ``quantize`` (straight-through). Gradients reach ``sparse`` and ``planes``; ``touched`` (a pair of uint8 masks
    over their rows, or None for either, e.g. for a :class:`~nerfbake.train.row_adam.RowAdam`) records which rows
    the backward wrote.
    :func:`merf_lookup_reference` is the torch twin."""
    return MerfLookup.apply(z, sm, sparse, planes, s, t, quantize, touched)


def merf_lookup_reference(z, sm, sparse, planes, s: int, t: int, quantize: bool = True):
    """Plain torch version of the same lookup (for tests): differentiable through autograd."""
    def q(v):
        if not quantize:
            return v
        return torch.cat([simulate(v[..., :1], RANGE_DENSITY), simulate(v[..., 1:], RANGE_FEATURES)], -1)

    def cell(x, res):
        g = ((x + 2) / 4 * res - 0.5).clamp(0, res - 1)
        i0 = g.floor().long().clamp(max=res - 2)
        return i0, g - i0

    sm = sm.long()
    (iu, fu), (iv, fv), (iw, fw) = (cell(z[:, a], s) for a in range(3))
    out_s = 0
    for c in range(8):
        du, dv, dw = (c >> 2) & 1, (c >> 1) & 1, c & 1
        w = (fu if du else 1 - fu) * (fv if dv else 1 - fv) * (fw if dw else 1 - fw)
        row = sm * s ** 3 + ((iu + du) * s + iv + dv) * s + iw + dw
        out_s = out_s + w[:, None] * q(sparse[row])
    out_p = 0
    for k, (a, b) in enumerate(((1, 2), (0, 2), (0, 1))):
        (ia, fa), (ib, fb) = cell(z[:, a], t), cell(z[:, b], t)
        for c in range(4):
            da, db = (c >> 1) & 1, c & 1
            w = (fa if da else 1 - fa) * (fb if db else 1 - fb)
            row = (sm * 3 + k) * t * t + (ia + da) * t + ib + db
            out_p = out_p + w[:, None] * q(planes[row])
    return out_s, out_p
