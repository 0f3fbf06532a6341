"""Gaussian splat compositing as Warp kernels (one source for CPU and CUDA): forward and analytic backward.

The screen-space half of the 3DGS rasteriser. Its inputs are the projected splats, already sorted front to back:
centres (K, 2) in pixels, conics (K, 3) = the inverse 2D covariance's (a, b, c) with
``power = -0.5 (a dx^2 + 2 b dx dy + c dy^2)``, opacities (K,) and colours (K, 3). The projection, the colour from
SH and everything before them stay in torch (``splats/rasterize.py``), whose autograd carries these kernels'
gradients on to the means, scales, rotations, opacities and SH.

Per pixel, over the splats binned to its 16 x 16 tile in depth order (``bin_tiles``): ``alpha = min(max_alpha,
o exp(power))`` (power clamped at 0), splats with alpha < min_alpha or power < -cutoff skipped, and compositing stops
before the splat that would take the transmittance under min_transmittance. :class:`SplatRules` holds those four
numbers (and the projection's low-pass): :data:`REFERENCE` the 3DGS reference's (0.99, 1/255, none, 1e-4),
:data:`WEB` antimatter15-style web viewers' (no cap, no skip, a cut at 2.83 sigma). The background fills what
transmittance is left.

The backward walks the same splats front to back again. With C the pixel's final colour (background included),
S_i the colour composited up to and including splat i, T_i the transmittance in front of it and w_i = T_i alpha_i:
  dC/dc_i = w_i,    dC/dalpha_i = T_i c_i - (C - S_i) / (1 - alpha_i)
and alpha's own derivatives (none where it was clamped at max_alpha): d alpha/d o = exp(power), d alpha/d power = alpha.
Gradients of many pixels meet in one splat: on the CPU each thread sums into its own buffers (Warp's CPU atomics are
plain adds), on a GPU one launch adds atomically.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from nerfbake.kernels import cpu_threads, device_of, ensure_loaded, launch_chunks, parallel_map, warp

wp = warp()

TILE = 16


@dataclass(frozen=True)
class SplatRules:
    """How one renderer draws splats. Renderers differ here, and a fit carries over only to a renderer whose rules it
    was fitted under: gsplat.js draws splats fitted under the reference's rules 2-3 dB away from them."""
    low_pass: float = 0.3  # px^2 added to the projected covariance's diagonal (used by the projection, in torch)
    max_alpha: float = 0.99  # alpha's cap (the backward divides by 1 - alpha)
    min_alpha: float = 1.0 / 255.0  # weaker splats are skipped
    cutoff: float = math.inf  # splats are skipped where 0.5 d^T Sigma^-1 d exceeds this
    min_transmittance: float = 1e-4  # stop before the splat that would take the transmittance under this
    max_color: float = math.inf  # colours are clamped to [0, max_color]


REFERENCE = SplatRules()
"""The 3DGS reference rasteriser's (diff-gaussian-rasterization)."""
WEB = SplatRules(low_pass=0.075, max_alpha=0.999, min_alpha=0.0, cutoff=4.0, max_color=1.0)
"""antimatter15/splat's and its descendants' (gsplat.js among them): they keep 4x the 3D covariance and add the
reference's 0.3 px^2 to 4x the projected one, which draws every splat with a low-pass of 0.075 px^2 (a quarter);
a quad out to sqrt(8) sigma with ``exp(-4)`` at its rim; no cap on alpha (0.999 here, for the backward); no skip;
colours stored in 8 bits (so at most 1). Not modelled: they also skip splats centred beyond 1.2x the clip box (a
difference at the image's border only; a fit on crops must not have it) and blend in 8 bits (per-pixel rounding
noise where many faint splats overlap). Transmittance runs out where their 8-bit alpha reaches 255, about where
1e-4 stops this one. Measured: gsplat.js 1.2.9 and this rasteriser under these rules draw lego's 300k leaf splats
50 dB apart (28 dB under the reference's rules, nearly all of it the low-pass)."""


@wp.func
def splat_alpha(xy: wp.vec2, conic: wp.vec3, opacity: float, px: float, py: float, cutoff: float):
    """(alpha before the cap, 0 beyond the cutoff; power after its clamp at 0, dx, dy) of one splat at pixel centre
    (px, py)."""
    dx = px - xy[0]
    dy = py - xy[1]
    power = -0.5 * (conic[0] * dx * dx + 2.0 * conic[1] * dx * dy + conic[2] * dy * dy)
    power = wp.min(power, 0.0)
    raw = opacity * wp.exp(power)
    if power < -cutoff:
        raw = 0.0
    return raw, power, dx, dy


@wp.func
def pixel_tile(pid: int, width: int, tiles_x: int):
    """(its 16 x 16 tile, centre x, centre y) of pixel ``pid`` in row-major order."""
    x = pid % width
    y = pid // width
    return (y // 16) * tiles_x + x // 16, float(x) + 0.5, float(y) + 0.5


@wp.kernel
def composite_forward(xy: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3), opacity: wp.array(dtype=float),
                      color: wp.array(dtype=wp.vec3), tile_start: wp.array(dtype=wp.int32),
                      tile_splats: wp.array(dtype=wp.int32), width: int, tiles_x: int, rules: wp.vec4,
                      background: wp.vec3, first: int, out_rgb: wp.array(dtype=wp.vec3),
                      out_end: wp.array(dtype=wp.int32)):
    """One pixel's colour, and where in its tile's list compositing stopped (for the backward); ``rules`` is
    (max_alpha, min_alpha, cutoff, min_transmittance)."""
    pid = wp.tid() + first
    tile, px, py = pixel_tile(pid, width, tiles_x)
    T = float(1.0)
    c = wp.vec3(0.0, 0.0, 0.0)
    end = tile_start[tile + 1]
    for k in range(tile_start[tile], tile_start[tile + 1]):
        g = tile_splats[k]
        raw, power, dx, dy = splat_alpha(xy[g], conic[g], opacity[g], px, py, rules[2])
        alpha = wp.min(raw, rules[0])
        if alpha <= 0.0 or alpha < rules[1]:
            continue
        t_next = T * (1.0 - alpha)
        if t_next < rules[3]:
            end = k
            break
        c = c + (T * alpha) * color[g]
        T = t_next
    out_rgb[pid] = c + T * background
    out_end[pid] = end


@wp.kernel
def composite_backward(xy: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3), opacity: wp.array(dtype=float),
                       color: wp.array(dtype=wp.vec3), tile_start: wp.array(dtype=wp.int32),
                       tile_splats: wp.array(dtype=wp.int32), width: int, tiles_x: int, rules: wp.vec4,
                       rgb: wp.array(dtype=wp.vec3), end: wp.array(dtype=wp.int32), grad_rgb: wp.array(dtype=wp.vec3),
                       first: int, g_xy: wp.array(dtype=wp.vec2), g_conic: wp.array(dtype=wp.vec3),
                       g_opacity: wp.array(dtype=float), g_color: wp.array(dtype=wp.vec3)):
    """One pixel's share of every splat's gradient, summed into the g_* buffers (see the module docstring)."""
    pid = wp.tid() + first
    tile, px, py = pixel_tile(pid, width, tiles_x)
    dl = grad_rgb[pid]
    final = rgb[pid]
    T = float(1.0)
    s = wp.vec3(0.0, 0.0, 0.0)
    for k in range(tile_start[tile], end[pid]):
        g = tile_splats[k]
        raw, power, dx, dy = splat_alpha(xy[g], conic[g], opacity[g], px, py, rules[2])
        alpha = wp.min(raw, rules[0])
        if alpha <= 0.0 or alpha < rules[1]:
            continue
        w = T * alpha
        cg = color[g]
        s = s + w * cg
        wp.atomic_add(g_color, g, w * dl)
        if raw < rules[0]:
            d_alpha = wp.dot(dl, T * cg - (final - s) / (1.0 - alpha))
            wp.atomic_add(g_opacity, g, d_alpha * wp.exp(power))
            d_power = d_alpha * alpha
            if power < 0.0:  # clamped at 0: no gradient through the quadratic form
                cc = conic[g]
                wp.atomic_add(g_conic, g, wp.vec3(-0.5 * dx * dx, -dx * dy, -0.5 * dy * dy) * d_power)
                wp.atomic_add(g_xy, g, wp.vec2(cc[0] * dx + cc[1] * dy, cc[1] * dx + cc[2] * dy) * d_power)
        T = T * (1.0 - alpha)


def bin_tiles(xy: torch.Tensor, radius: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Each 16 x 16 tile's splats in order: ``tile_start`` (tiles + 1,) offsets into ``tile_splats`` (pairs,), the
    indices of the splats whose box ``xy +- radius`` meets the tile (the splats come sorted front to back, and a
    stable sort by tile keeps that order within each tile)."""
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    lo = torch.floor((xy - radius[:, None]) / TILE).long()
    hi = torch.floor((xy + radius[:, None]) / TILE).long()
    x0, x1 = lo[:, 0].clamp(0, tiles_x - 1), hi[:, 0].clamp(-1, tiles_x - 1)
    y0, y1 = lo[:, 1].clamp(0, tiles_y - 1), hi[:, 1].clamp(-1, tiles_y - 1)
    nx, ny = (x1 - x0 + 1).clamp_min(0), (y1 - y0 + 1).clamp_min(0)
    counts = nx * ny
    splat = torch.repeat_interleave(torch.arange(xy.shape[0]), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(splat.numel()) - first[splat]  # the pair's rank among its splat's tiles
    row = local // nx[splat].clamp_min(1)
    tile = (y0[splat] + row) * tiles_x + x0[splat] + local - row * nx[splat]
    tile, order = torch.sort(tile, stable=True)
    tile_start = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64)
    tile_start[1:] = torch.cumsum(torch.bincount(tile, minlength=tiles_x * tiles_y), 0)
    return tile_start.to(torch.int32), splat[order].to(torch.int32)


class CompositeSplats(torch.autograd.Function):
    """(H, W, 3) image from sorted screen-space splats; differentiable in xy, conic, opacity and colour."""

    @staticmethod
    def forward(ctx, xy, conic, opacity, color, tile_start, tile_splats, width, height, background, rules):
        dev = device_of(xy)
        xy, conic, opacity, color = (t.detach().float().contiguous() for t in (xy, conic, opacity, color))
        tiles_x = -(-width // TILE)
        n = width * height
        rgb = torch.empty(n, 3, device=xy.device)
        end = torch.empty(n, dtype=torch.int32, device=xy.device)
        ensure_loaded(composite_forward, dev)
        ins = [wp.from_torch(xy, dtype=wp.vec2), wp.from_torch(conic, dtype=wp.vec3), wp.from_torch(opacity),
               wp.from_torch(color, dtype=wp.vec3), wp.from_torch(tile_start.to(xy.device)),
               wp.from_torch(tile_splats.to(xy.device)), width, tiles_x, rule_vector(rules)]
        outs = [wp.from_torch(rgb, dtype=wp.vec3), wp.from_torch(end)]
        bg = wp.vec3(*(float(v) for v in background))
        parallel_map(lambda c: wp.launch(composite_forward, dim=c[1] - c[0], inputs=[*ins, bg, c[0], *outs], device=dev),
                     launch_chunks(n, dev))
        ctx.save_for_backward(xy, conic, opacity, color, tile_start, tile_splats, rgb, end)
        ctx.size, ctx.rules = (width, height), rules
        return rgb.reshape(height, width, 3)

    @staticmethod
    def backward(ctx, grad_img):
        xy, conic, opacity, color, tile_start, tile_splats, rgb, end = ctx.saved_tensors
        width, height = ctx.size
        dev = device_of(xy)
        n, k = width * height, xy.shape[0]
        grad = grad_img.reshape(n, 3).float().contiguous()
        chunks = launch_chunks(n, dev, parts=None if dev != "cpu" or n < 4096 else cpu_threads())
        # one set of gradient buffers per chunk (chunks run on different threads on the CPU)
        bufs = [[torch.zeros(k, d, device=xy.device) for d in (2, 3, 1, 3)] for _ in chunks]
        ensure_loaded(composite_backward, dev)
        ins = [wp.from_torch(xy, dtype=wp.vec2), wp.from_torch(conic, dtype=wp.vec3), wp.from_torch(opacity),
               wp.from_torch(color, dtype=wp.vec3), wp.from_torch(tile_start.to(xy.device)),
               wp.from_torch(tile_splats.to(xy.device)), width, -(-width // TILE), rule_vector(ctx.rules),
               wp.from_torch(rgb, dtype=wp.vec3), wp.from_torch(end), wp.from_torch(grad, dtype=wp.vec3)]

        def run(i):
            a, b = chunks[i]
            g_xy, g_conic, g_op, g_col = bufs[i]
            wp.launch(composite_backward, dim=b - a, device=dev,
                      inputs=[*ins, a, wp.from_torch(g_xy, dtype=wp.vec2), wp.from_torch(g_conic, dtype=wp.vec3),
                              wp.from_torch(g_op.reshape(-1)), wp.from_torch(g_col, dtype=wp.vec3)])

        parallel_map(run, range(len(chunks)))
        g_xy, g_conic, g_op, g_col = (sum(b[j] for b in bufs) for j in range(4))
        return g_xy, g_conic, g_op.reshape(-1), g_col, None, None, None, None, None, None


def rule_vector(rules: SplatRules):
    """The kernels' view of ``rules``: (max_alpha, min_alpha, cutoff, min_transmittance)."""
    return wp.vec4(rules.max_alpha, rules.min_alpha, min(rules.cutoff, 1e30), rules.min_transmittance)


def composite(xy, conic, opacity, color, radius, width: int, height: int, background,
              rules: SplatRules = REFERENCE) -> torch.Tensor:
    """(H, W, 3) image of splats sorted front to back (see the module docstring) under ``rules``; ``radius`` (K,)
    bounds each splat's footprint in pixels for the tile binning."""
    with torch.no_grad():
        tile_start, tile_splats = bin_tiles(xy.detach().float().cpu(), radius.detach().float().cpu(), width, height)
    return CompositeSplats.apply(xy, conic, opacity, color, tile_start, tile_splats, width, height,
                                 tuple(float(v) for v in background), rules)
