"""Ray marching a baked SMERF submodel as the official web viewer's fragment shader does (a Warp kernel for CPU
and CUDA). The spec this follows, in our own words, is ``docs/smerf_viewer.md``; in short:

* rays start on the near plane (t = 1 of the unnormalised camera ray, submodel frame) and are split into the
  regions of the MERF contraction they cross (core cube and six pyramids), where the contracted ray is straight;
  each region's exit is found in closed form (the regions are convex in world space), not by the official
  viewer's search over candidate crossings;
* the box around the occupied factor-8 cells bounds the march: a region is left where its ray leaves the box,
  and where the box lies in the core a ray that misses it is not marched, a camera outside the core starts at
  the core, and the march ends past the box (none of these skips a step that could meet an occupied cell);
* marching takes constant steps in contracted space (triplane voxel / stepMult), enlarged up to 10x as an
  exponential average of visibility drops ("larger steps when occluded");
* the factor-8 distance grid jumps over empty space, then the bit-packed factor-8 occupancy grid skips empty
  half-cells, then the 8^3 block index says whether the sparse grid has data;
* density = exp(sparse + gate * sum(triplanes) - 1) with the 7th feature as the gate; alpha from the world-space
  length of the step; colour and features accumulated only where alpha > 0.25/255; stop at visibility 1/255.

The per-pixel deferred MLP runs afterwards in torch (:mod:`nerfbake.smerf.baked_render`).
"""
from __future__ import annotations

import numpy as np
import torch

from nerfbake.kernels import device_of, ensure_loaded, launch_chunks, parallel_map, warp

wp = warp()
wp.set_module_options({"enable_backward": False})

INF = wp.constant(1.0e25)
vec8 = wp.types.vector(length=8, dtype=wp.float32)


@wp.func
def major_axis(v: wp.vec3) -> int:
    """Index (0, 1, 2) of the component of ``v`` with the largest magnitude."""
    ax = wp.abs(v[0])
    ay = wp.abs(v[1])
    az = wp.abs(v[2])
    if ax >= ay and ax >= az:
        return 0
    if ay >= ax and ay >= az:
        return 1
    return 2


@wp.func
def max_abs(v: wp.vec3) -> float:
    """The inf-norm of ``v``."""
    return wp.max(wp.abs(v[0]), wp.max(wp.abs(v[1]), wp.abs(v[2])))


@wp.func
def contract(x: wp.vec3) -> wp.vec3:
    """MERF's piecewise-projective contraction of world point ``x`` into [-2, 2]^3 (identity inside the unit cube)."""
    m = max_abs(x)
    if m <= 1.0:
        return x
    s = 1.0 / m
    z = s * x
    a = major_axis(x)
    z[a] = z[a] * (2.0 - s)
    return z


@wp.func
def uncontract(z: wp.vec3) -> wp.vec3:
    """The inverse of :func:`contract` for ``z`` in (-2, 2)^3."""
    m = max_abs(z)
    if m <= 1.0:
        return z
    inv = wp.max(1.0e-6, 2.0 - m)
    s = 1.0 / inv
    x = s * z
    a = major_axis(z)
    x[a] = wp.sign(x[a]) * s
    return x


@wp.func
def slab(lo: wp.vec3, hi: wp.vec3, o: wp.vec3, inv_d: wp.vec3) -> wp.vec2:
    """(t_enter, t_exit) of the ray ``o + t d`` through the box [lo, hi] (``inv_d`` = 1 / d)."""
    ta = wp.cw_mul(lo - o, inv_d)
    tb = wp.cw_mul(hi - o, inv_d)
    tmin = wp.max(wp.max(wp.min(ta[0], tb[0]), wp.min(ta[1], tb[1])), wp.min(ta[2], tb[2]))
    tmax = wp.min(wp.min(wp.max(ta[0], tb[0]), wp.max(ta[1], tb[1])), wp.max(ta[2], tb[2]))
    return wp.vec2(tmin, tmax)


@wp.func
def core_span(o: wp.vec3, inv_d: wp.vec3) -> wp.vec2:
    """[t in, t out] of the ray in the core box |x| <= 1 - 1e-5 (empty when t in > t out)."""
    c1 = 1.0 - 1.0e-5
    return slab(wp.vec3(-c1, -c1, -c1), wp.vec3(c1, c1, c1), o, inv_d)


@wp.func
def half_space(iv: wp.vec2, no: float, nd: float, c: float) -> wp.vec2:
    """The interval iv of t cut to where n.(o + t d) >= c, given no = n.o and nd = n.d."""
    if nd > 0.0:
        return wp.vec2(wp.max(iv[0], (c - no) / nd), iv[1])
    if nd < 0.0:
        return wp.vec2(iv[0], wp.min(iv[1], (c - no) / nd))
    if no >= c:
        return iv
    return wp.vec2(INF, -INF)


@wp.func
def region_exit(o: wp.vec3, d: wp.vec3, inv_d: wp.vec3, k: int) -> float:
    """The t where the ray leaves region k (0 core, 1..6 = +x,+y,+z,-x,-y,-z), or -INF where it never is in it.

    Each region is convex in world space, so the ray's stretch in it is one interval cut out by half-spaces: the
    core is the box |x| <= 1 - 1e-5; outer region (axis a, sign s) is s x_a >= 1, s x_a <= 1e4 (contracted
    2 - 1e-4) and s x_a >= |x_b| for both other axes. The shader computes the same closed form."""
    if k == 0:
        t = core_span(o, inv_d)
        if t[0] <= t[1]:
            return t[1]
        return -INF
    a = (k - 1) % 3
    b = (a + 1) % 3
    c = (a + 2) % 3
    sg = wp.where(k <= 3, 1.0, -1.0)
    oa = sg * o[a]
    da = sg * d[a]
    iv = wp.vec2(-INF, INF)
    iv = half_space(iv, oa, da, 1.0)
    iv = half_space(iv, -oa, -da, -1.0e4)
    iv = half_space(iv, oa - o[b], da - d[b], 0.0)
    iv = half_space(iv, oa + o[b], da + d[b], 0.0)
    iv = half_space(iv, oa - o[c], da - d[c], 0.0)
    iv = half_space(iv, oa + o[c], da + d[c], 0.0)
    if iv[0] <= iv[1]:
        return iv[1]
    return -INF


@wp.struct
class Quadrant:
    """One region's straight contracted ray ``oc + t dc`` on [tmin, tmax]; ``t_end``: where it leaves the occupied
    box for good (-INF if it never meets it): no later step can land in an occupied cell; ``core``: the region is
    the unit box."""
    oc: wp.vec3
    dc: wp.vec3
    tmin: float
    tmax: float
    t_end: float
    core: int


@wp.func
def quadrant_setup(o: wp.vec3, d: wp.vec3, tp: float, tq: float, occ_lo: wp.vec3, occ_hi: wp.vec3) -> Quadrant:
    """The contraction region the ray enters at ``tp`` (the core or one of six shells) and where it leaves it (at
    most ``tq``), with the occupied box's span inside it."""
    xp = o + tp * d
    lo = wp.vec3(-1.0, -1.0, -1.0)
    hi = wp.vec3(1.0, 1.0, 1.0)
    q = Quadrant()
    q.core = wp.where(max_abs(xp) <= 1.0, 1, 0)
    if q.core == 0:
        a = major_axis(xp)
        if xp[a] > 0.0:
            lo[a] = 1.0
            hi[a] = 2.0
        else:
            lo[a] = -2.0
            hi[a] = -1.0
    q.oc = contract(xp)
    q.dc = wp.normalize(contract(o + tq * d) - q.oc)
    inv = wp.vec3(1.0 / q.dc[0], 1.0 / q.dc[1], 1.0 / q.dc[2])
    t = slab(lo, hi, q.oc, inv)
    q.tmin = t[0]
    q.tmax = t[1]
    occ = slab(occ_lo, occ_hi, q.oc, inv)
    q.t_end = -INF
    if occ[0] <= occ[1]:
        q.t_end = wp.min(q.tmax, occ[1])
    return q


@wp.func
def texel3(grid: wp.array3d(dtype=wp.uint8), c: wp.vec3) -> float:
    """The value of the 3-D byte texture ``grid`` at the texel holding ``c`` (texel units, clamped), as the viewer's
    texelFetch."""
    n0 = grid.shape[0]
    n1 = grid.shape[1]
    n2 = grid.shape[2]
    i = wp.clamp(int(wp.floor(c[0])), 0, n0 - 1)
    j = wp.clamp(int(wp.floor(c[1])), 0, n1 - 1)
    k = wp.clamp(int(wp.floor(c[2])), 0, n2 - 1)
    return float(grid[i, j, k])


@wp.func
def trilerp(tex: wp.array4d(dtype=wp.uint8), s: wp.vec3, ch: int) -> float:
    """Hardware-style LINEAR filtering at texel-space coordinate s (texel i's centre at i), clamp to edge; [0, 1]."""
    i0 = int(wp.floor(s[0]))
    j0 = int(wp.floor(s[1]))
    k0 = int(wp.floor(s[2]))
    fx = s[0] - float(i0)
    fy = s[1] - float(j0)
    fz = s[2] - float(k0)
    acc = float(0.0)
    for c in range(8):
        dx = c // 4
        dy = (c // 2) % 2
        dz = c % 2
        i = wp.clamp(i0 + dx, 0, tex.shape[0] - 1)
        j = wp.clamp(j0 + dy, 0, tex.shape[1] - 1)
        k = wp.clamp(k0 + dz, 0, tex.shape[2] - 1)
        w = wp.where(dx == 1, fx, 1.0 - fx) * wp.where(dy == 1, fy, 1.0 - fy) * wp.where(dz == 1, fz, 1.0 - fz)
        acc += w * float(tex[i, j, k, ch])
    return acc / 255.0


@wp.func
def bilerp(tex: wp.array4d(dtype=wp.uint8), layer: int, u: float, v: float, ch: int) -> float:
    """Bilinear read of channel ``ch`` of plane ``layer`` of ``tex`` (3, T, T, C) at (u, v) in [0, 1]^2, as WebGL's
    LINEAR filter (texel centres at half-integers)."""
    n = tex.shape[1]
    x = u * float(n) - 0.5
    y = v * float(n) - 0.5
    i0 = int(wp.floor(x))
    j0 = int(wp.floor(y))
    fx = x - float(i0)
    fy = y - float(j0)
    acc = float(0.0)
    for c in range(4):
        dx = c // 2
        dy = c % 2
        i = wp.clamp(i0 + dx, 0, n - 1)
        j = wp.clamp(j0 + dy, 0, n - 1)
        acc += wp.where(dx == 1, fx, 1.0 - fx) * wp.where(dy == 1, fy, 1.0 - fy) * float(tex[layer, i, j, ch])
    return acc / 255.0


@wp.func
def plane_sum(tex: wp.array4d(dtype=wp.uint8), p: wp.vec3, ch: int) -> float:
    """Sum of the three triplanes' channel ``ch`` at point ``p`` in [0, 1]^3 (the yz, xz and xy planes)."""
    return bilerp(tex, 0, p[1], p[2], ch) + bilerp(tex, 1, p[0], p[2], ch) + bilerp(tex, 2, p[0], p[1], ch)


@wp.func
def sigmoid(x: float) -> float:
    """1 / (1 + e^-x)."""
    return 1.0 / (1.0 + wp.exp(-x))


@wp.struct
class BakedScene:
    """One baked submodel's textures as the viewer uploads them (byte arrays), with its grid sizes and the occupied
    box."""
    block_indices: wp.array4d(dtype=wp.uint8)
    atlas_rgb: wp.array4d(dtype=wp.uint8)
    atlas_density: wp.array4d(dtype=wp.uint8)
    atlas_features: wp.array4d(dtype=wp.uint8)
    plane_rgb: wp.array4d(dtype=wp.uint8)
    plane_density: wp.array4d(dtype=wp.uint8)
    plane_features: wp.array4d(dtype=wp.uint8)
    occupancy8: wp.array3d(dtype=wp.uint8)
    distance8: wp.array3d(dtype=wp.uint8)
    triplane_res: int
    triplane_voxel: float
    sparse_voxel: float
    block: int
    rf_min: float
    rf_max: float
    rd_min: float
    rd_max: float
    scale: float
    gating: int
    occ_lo: wp.vec3  # contracted box around every occupied factor-8 cell (occupied_box)
    occ_hi: wp.vec3


@wp.kernel
def baked_march(
    scene: BakedScene, origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), step_mult: float,
    visibility_delay: float, ray0: int,
    out_color: wp.array(dtype=wp.vec3), out_feat: wp.array(dtype=wp.vec4), out_coarse_color: wp.array(dtype=wp.vec3),
    out_coarse_feat: wp.array(dtype=wp.vec4), out_visibility: wp.array(dtype=float),
):
    """One thread per ray (from ``ray0``): the viewer's fragment shader march through one baked submodel ->
    accumulated diffuse colour (R, 3), features (R, 4), their values at the coarse exit and the remaining visibility
    (R,)."""
    r = ray0 + wp.tid()
    o = origins[r]
    d = dirs[r]
    for a in range(3):  # an exactly axis-parallel ray would divide by zero in the region solvers (GPU-defined there)
        if wp.abs(d[a]) < 1.0e-9:
            d[a] = 1.0e-9
    near = 1.0
    # regions crossed, sorted by exit t (world t along the unnormalised ray)
    exits = vec8(INF, INF, INF, INF, INF, INF, INF, INF)
    n = int(0)
    # Where the occupied box lies in the core (contracted = world there), a ray that misses it in world space meets
    # no occupied cell: no regions, no march, only the deferred MLP's background.
    lo = scene.occ_lo
    hi = scene.occ_hi
    in_core = max_abs(lo) <= 1.0 and max_abs(hi) <= 1.0
    inv_d = wp.vec3(1.0 / d[0], 1.0 / d[1], 1.0 / d[2])
    hit = slab(lo, hi, o, inv_d)
    misses = in_core and (hit[0] > hit[1] or hit[1] < near)
    for k in range(wp.where(misses, 0, 7)):
        t = region_exit(o, d, inv_d, k)
        if t >= near:
            j = n
            while j > 0 and exits[j - 1] > t:
                exits[j] = exits[j - 1]
                j -= 1
            exits[j] = t
            n += 1
    q = quadrant_setup(o, d, near, near + 0.5 * (exits[0] - near), lo, hi)
    tc = float(0.0)
    orig_step = scene.triplane_voxel / step_mult
    if in_core and not misses and q.core == 0:
        # a camera outside the core meets the occupied box only in the core: start where the ray enters it, as a
        # quadrant change there would (visibility is still 1, so the step is orig_step)
        core = core_span(o, inv_d)
        q = quadrant_setup(o, d, core[0] + 0.1 * (core[1] - core[0]), core[0] + 0.9 * (core[1] - core[0]), lo, hi)
        tc = q.tmin + 0.5 * orig_step
    qi = int(1)
    t_block = float(-INF)
    vis = float(1.0)
    ema = float(1.0)
    color = wp.vec3()
    feat = wp.vec4()
    coarse_color = wp.vec3()
    coarse_feat = wp.vec4()
    tres = float(scene.triplane_res)
    max_steps = wp.where(misses, 0, int(step_mult) * int(wp.ceil(wp.sqrt(2.0 * tres * tres))))
    min_p = wp.vec3(-2.0, -2.0, -2.0)
    vs_grid = 8.0 * scene.triplane_voxel
    rf = scene.rf_max - scene.rf_min
    rd = scene.rd_max - scene.rd_min
    nb = scene.block_indices.shape[0]
    b = float(scene.block)
    i = int(0)
    while i < max_steps and vis > 1.0 / 255.0:
        i += 1
        ema = visibility_delay * ema + (1.0 - visibility_delay) * vis
        step = orig_step * (10.0 - 9.0 * wp.sqrt(wp.min(1.0, ema / 0.8)))
        if tc > q.t_end:
            # past the occupied box in the core, which holds it all: a line leaves a convex box once
            if in_core and q.core == 1:
                break
            if max_abs(q.oc + q.tmax * q.dc) >= 2.0 - 1.0e-3:
                break
            if qi >= 7:
                break
            if exits[qi - 1] >= exits[qi] - 16.0 * step:
                qi += 1
                if qi >= 7:
                    break
            lo_t = exits[qi - 1]
            hi_t = exits[qi]
            q = quadrant_setup(o, d, lo_t + 0.1 * (hi_t - lo_t), lo_t + 0.9 * (hi_t - lo_t), lo, hi)
            tc = q.tmin + 0.5 * step
            qi += 1
            t_block = -INF
        z = q.oc + tc * q.dc
        # Until tc passes t_block the ray is inside the occupied half-cell found last (its factor-8 cell has
        # distance 0), so both grid queries are skipped there, as the shader does.
        if tc > t_block:
            # 1. distance grid: jump whole empty cells
            dist = texel3(scene.distance8, wp.cw_div(z - min_p, wp.vec3(vs_grid, vs_grid, vs_grid))) * vs_grid
            if dist > 0.0:
                tc += dist
                continue
            # 2. bit-packed occupancy (cached exit of the last queried cell)
            pos = (z - min_p) / vs_grid
            bmin = wp.vec3(wp.floor(pos[0]), wp.floor(pos[1]), wp.floor(pos[2]))
            bmax = bmin + wp.vec3(1.0, 1.0, 1.0)
            occ = int(texel3(scene.occupancy8, bmin))
            empty = occ == 0
            if not empty:
                rel = pos - bmin
                bit = int(1)
                if rel[2] > 0.5:
                    bit *= 2
                    bmin[2] += 0.5
                if rel[1] > 0.5:
                    bit *= 4
                    bmin[1] += 0.5
                if rel[0] > 0.5:
                    bit *= 16
                    bmin[0] += 0.5
                bmax = bmin + wp.vec3(0.5, 0.5, 0.5)
                empty = (occ // bit) % 2 == 0
            inv = wp.vec3(1.0 / q.dc[0], 1.0 / q.dc[1], 1.0 / q.dc[2])
            t_block = slab(bmin * vs_grid + min_p, bmax * vs_grid + min_p, q.oc, inv)[1]
            if empty:
                tc = wp.max(tc, t_block) + 0.5 * step
                continue
        # 3. sparse grid block
        g = (z - min_p) / scene.sparse_voxel - wp.vec3(0.5, 0.5, 0.5)
        block_min = wp.vec3(wp.floor(g[0] / b) * b, wp.floor(g[1] / b) * b, wp.floor(g[2] / b) * b)
        bi = wp.clamp(int(block_min[0] / b), 0, nb - 1)
        bj = wp.clamp(int(block_min[1] / b), 0, nb - 1)
        bk = wp.clamp(int(block_min[2] / b), 0, nb - 1)
        ix = int(scene.block_indices[bi, bj, bk, 0])
        if ix > 254:
            tc += step
            continue
        idx = wp.vec3(float(ix), float(scene.block_indices[bi, bj, bk, 1]), float(scene.block_indices[bi, bj, bk, 2]))
        local = g - block_min
        local = wp.vec3(wp.clamp(local[0], 0.0, b), wp.clamp(local[1], 0.0, b), wp.clamp(local[2], 0.0, b))
        s = local + idx * (b + 1.0)
        sd = scene.rd_min + rd * trilerp(scene.atlas_density, s, 0)
        gate = scene.rf_min + rf * trilerp(scene.atlas_density, s, 1)
        pt = (z - min_p) / (scene.triplane_voxel * tres)
        td = 2.0 * scene.rd_min + scene.rd_min + rd * plane_sum(scene.plane_density, pt, 0)
        w_gate = wp.where(scene.gating == 1, gate, 1.0)
        density = wp.exp(sd + w_gate * td - 1.0)
        t_next = wp.min(tc + step, q.tmax)
        step_world = wp.length(uncontract(q.oc + t_next * q.dc) - uncontract(z)) / scene.scale
        alpha = 1.0 - wp.exp(-density * step_world)
        if alpha > 0.25 / 255.0:
            w = vis * alpha
            for c in range(3):
                srgb = scene.rf_min + rf * trilerp(scene.atlas_rgb, s, c)
                trgb = 3.0 * scene.rf_min + rf * plane_sum(scene.plane_rgb, pt, c)
                color[c] += w * sigmoid(srgb + w_gate * trgb)
                coarse_color[c] += w * sigmoid(srgb)
            for c in range(4):
                sf = gate
                if c < 3:
                    sf = scene.rf_min + rf * trilerp(scene.atlas_features, s, c)
                tf = 3.0 * scene.rf_min + rf * plane_sum(scene.plane_features, pt, c)
                feat[c] += w * sigmoid(sf + w_gate * tf)
                coarse_feat[c] += w * sigmoid(sf)
        vis *= 1.0 - alpha
        tc += step
    out_color[r] = color
    out_feat[r] = feat
    out_coarse_color[r] = coarse_color
    out_coarse_feat[r] = coarse_feat
    out_visibility[r] = vis


def to_warp_scene(sm, device: str):
    """A :class:`BakedScene` struct over a loaded :class:`~nerfbake.smerf.assets.Submodel` (arrays copied to device)."""
    p = sm.params
    s = BakedScene()

    def a(x):
        return wp.array(x, dtype=wp.uint8, device=device)

    s.block_indices, s.atlas_rgb, s.atlas_density, s.atlas_features = (a(sm.block_indices), a(sm.atlas_rgb),
                                                                       a(sm.atlas_density), a(sm.atlas_features))
    s.plane_rgb, s.plane_density, s.plane_features = a(sm.plane_rgb), a(sm.plane_density), a(sm.plane_features)
    s.occupancy8, s.distance8 = a(sm.occupancy[8]), a(sm.distance[8])
    s.triplane_res = int(p["triplane_resolution"])
    s.triplane_voxel = float(p["triplane_voxel_size"])
    s.sparse_voxel = float(p["sparse_grid_voxel_size"])
    s.block = int(p["data_block_size"])
    s.rf_min, s.rf_max = (float(v) for v in p["range_features"])
    s.rd_min, s.rd_max = (float(v) for v in p["range_density"])
    s.scale = float(p["submodel_scale"])
    s.gating = 0 if p.get("feature_gating") is False else 1
    s.occ_lo, s.occ_hi = (wp.vec3(*v) for v in occupied_box(sm.occupancy[8], 8.0 * s.triplane_voxel))
    return s


def occupied_box(occupancy8: np.ndarray, voxel: float) -> tuple[list[float], list[float]]:
    """[lo, hi] in contracted coordinates around every occupied factor-8 cell of the bit-packed ``occupancy8``
    (n, n, n; [x, y, z]; a non-zero byte), each cell ``voxel`` wide from -2; an empty grid gives an empty box
    (lo > hi). Not from the distance grid: its zeros include the occupied cells' neighbours. The viewer computes
    the same box at upload (smerf.js: occupiedBox)."""
    cells = np.argwhere(np.asarray(occupancy8) > 0)
    if len(cells) == 0:
        return [1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]
    return ((-2.0 + cells.min(0) * voxel).tolist(), (-2.0 + (cells.max(0) + 1) * voxel).tolist())


def march_baked(scene, origins: torch.Tensor, dirs: torch.Tensor, step_mult: int = 1,
                visibility_delay: float = 0.99) -> dict[str, torch.Tensor]:
    """Per ray (submodel frame, unnormalised direction to the near plane): accumulated diffuse colour, features,
    coarse (sparse-only) colour and features, and the remaining visibility. ``step_mult`` is the viewer's whole
    stepMult (the kernel takes it as a float)."""
    n = origins.shape[0]
    dev = device_of(origins)
    out = {"color": torch.zeros(n, 3), "feat": torch.zeros(n, 4), "coarse_color": torch.zeros(n, 3),
           "coarse_feat": torch.zeros(n, 4), "visibility": torch.ones(n)}
    out = {k: v.to(origins.device) for k, v in out.items()}
    if n == 0:
        return out
    ins = [scene, wp.from_torch(origins.contiguous().float(), dtype=wp.vec3), wp.from_torch(dirs.contiguous().float(), dtype=wp.vec3),
           float(step_mult), float(visibility_delay)]
    outs = [wp.from_torch(out["color"], dtype=wp.vec3), wp.from_torch(out["feat"], dtype=wp.vec4),
            wp.from_torch(out["coarse_color"], dtype=wp.vec3), wp.from_torch(out["coarse_feat"], dtype=wp.vec4),
            wp.from_torch(out["visibility"])]
    ensure_loaded(baked_march, dev)
    parallel_map(lambda c: wp.launch(baked_march, dim=c[1] - c[0], inputs=[*ins, c[0], *outs], device=dev), launch_chunks(n, dev))
    return out
