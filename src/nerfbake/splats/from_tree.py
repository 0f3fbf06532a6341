"""Gaussians from a PlenOctree: one per leaf that is not empty.

A leaf is a cube of constant density and SH colour. Its Gaussian sits at the cube's centre with standard deviation
``SPREAD`` times the cube's side per axis (0.4: a lattice of such Gaussians at the leaves' spacing sums to about
one, so a surface of leaves is covered without holes or doubled opacity), opacity ``1 - exp(-sigma * side)``
(what a ray crossing the cube collects), and colour refitted: PlenOctrees' colour is ``sigmoid(SH . k)``, 3DGS's
``max(SH . k' + 0.5, 0)``, so ``k'`` is the least-squares fit of ``sigmoid(SH . k) - 0.5`` over ``DIRECTIONS``
directions spread over the sphere, not a copy of ``k``.

A tree of an unbounded scene draws what lies beyond its box from an environment map (colour by direction). No splat
file can hold such a map, so :func:`environment_shell` turns it into splats too: flat Gaussians on a sphere
``SHELL_DISTANCE`` box half-sizes around the box, one per texel, each facing the centre, as opaque as a splat gets.
Seen from inside the box, a direction's colour then comes from the shell within a few degrees of where the map
puts it; every splat viewer draws the room or the sky behind the scene.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from nerfbake.data.images import area_downscale
from nerfbake.octree.tree import Octree
from nerfbake.render.envmap import equirect_angles
from nerfbake.render.rotations import matrix_quaternion
from nerfbake.render.sh import sh_basis
from nerfbake.splats.gaussians import SH_C0, Gaussians

SPREAD = 0.4
DIRECTIONS = 128
MIN_OPACITY = 1.0 / 255.0  # a splat fainter than one 8-bit level is dropped
# The environment shell's radius in box half-sizes: from inside the box a direction is off by at most
# atan(sqrt(3) / 20), under 5 degrees; and within gsplat.js's far plane (100) for boxes of half-size up to 5.
SHELL_DISTANCE = 20.0
SHELL_ROWS = 64  # the map is averaged down to at most this many rows (twice as many columns) of shell splats
SHELL_SPREAD = 0.6  # standard deviation in texel spacings: neighbours overlap into an opaque shell
SHELL_OPACITY = 0.99


def sphere_directions(n: int) -> torch.Tensor:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci lattice), (n, 3) float64."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt(1.0 - z * z)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def refit_sh(coeffs: torch.Tensor, tree_degree: int, degree: int, chunk: int = 1 << 16) -> torch.Tensor:
    """3DGS coefficients (N, 3, (degree+1)^2) whose ``SH . k' + 0.5`` best matches (least squares over the sphere)
    the PlenOctree colours ``sigmoid(SH . k)`` of ``coeffs`` (N, 3, (tree_degree+1)^2)."""
    dirs = sphere_directions(DIRECTIONS)
    source = sh_basis(tree_degree, dirs)  # (M, B)
    target_basis = sh_basis(degree, dirs)  # (M, B')
    fit = torch.linalg.pinv(target_basis)  # (B', M)
    out = []
    for a in range(0, coeffs.shape[0], chunk):
        colour = torch.sigmoid(coeffs[a:a + chunk].double() @ source.T)  # (n, 3, M)
        out.append((colour - 0.5) @ fit.T)
    return torch.cat(out).float() if out else coeffs.new_zeros(0, 3, target_basis.shape[1])


def gaussians_from_tree(tree: Octree, sh_degree: int | None = None, max_splats: int | None = None) -> Gaussians:
    """One Gaussian per leaf whose opacity reaches one 8-bit level (see the module docstring), the ``max_splats``
    most opaque ones when given; SH up to ``sh_degree`` (default: the tree's, at most 3, the 3DGS maximum)."""
    tree_degree = tree.sh_degree
    degree = min(tree_degree, 3) if sh_degree is None else sh_degree
    if not 0 <= degree <= 3:
        raise ValueError(f"--sh-degree must be 0..3 (the 3DGS layouts stop at degree 3), got {degree}")
    leaves = tree.leaves()
    data = tree.data.reshape(-1, tree.data_dim).cpu()[leaves["index"]]
    inv = tree.invradius.cpu().double()
    side = leaves["size"][:, None] / inv[None]  # (N, 3) world units
    sigma = data[:, -1].double().clamp_min(0)
    alpha = 1.0 - torch.exp(-sigma * side.mean(1))
    keep = alpha >= MIN_OPACITY
    if max_splats is not None and int(keep.sum()) > max_splats:
        threshold = torch.topk(torch.where(keep, alpha, -1.0), max_splats).values[-1]
        keep &= alpha >= threshold
        keep &= torch.cumsum(keep.long(), 0) <= max_splats  # ties at the threshold: the first ones
    centre_tree = leaves["corner"][keep] + leaves["size"][keep, None] / 2
    means = tree.tree_to_world(centre_tree.to(tree.offset.dtype)).double()
    nb = tree.num_basis
    coeffs = data[keep, :-1].reshape(-1, 3, nb)
    a = alpha[keep].clamp(max=1.0 - 1e-6)
    return Gaussians(
        means=means.numpy(),
        log_scales=torch.log(SPREAD * side[keep]).numpy(),
        quats=np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (int(keep.sum()), 1)),
        opacity_logits=torch.log(a / (1 - a)).numpy(),
        sh=refit_sh(coeffs, tree_degree, degree).double().numpy(),
    )


def environment_shell(tree: Octree, sh_degree: int, rows: int = SHELL_ROWS) -> Gaussians | None:
    """The tree's environment map as a sphere of flat splats around its box (see the module docstring), colour
    only (higher SH bands zero); None for a tree without a map."""
    if tree.env_map is None:
        return None
    env = np.asarray(tree.env_map.detach().cpu().numpy(), np.float64)
    if env.shape[0] > rows:
        env = area_downscale(np.round(env * 255).astype(np.uint8), (2 * rows, rows)).astype(np.float64) / 255.0
    h, w = env.shape[:2]
    th, ph = (a.numpy().reshape(-1) for a in equirect_angles(h, w))
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)  # the map's direction per texel
    e_th = np.stack([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)], -1)
    e_ph = np.stack([-np.sin(ph), np.cos(ph), np.zeros_like(ph)], -1)
    inv = tree.invradius.detach().cpu().double().numpy()
    centre = tree.tree_to_world(torch.full((1, 3), 0.5, dtype=torch.float64)).numpy()[0]
    radius = SHELL_DISTANCE * float((0.5 / inv).max())
    spacing_th = radius * np.pi / h
    spacing_ph = radius * 2 * np.pi * np.maximum(np.sin(th), 0.5 / h) / w
    scales = np.stack([SHELL_SPREAD * spacing_th * np.ones_like(th), SHELL_SPREAD * spacing_ph,
                       1e-3 * spacing_th * np.ones_like(th)], -1)
    sh = np.zeros((h * w, 3, (sh_degree + 1) ** 2))
    sh[:, :, 0] = (env.reshape(-1, 3) - 0.5) / SH_C0
    return Gaussians(means=centre + radius * d, log_scales=np.log(scales),
                     quats=matrix_quaternion(np.stack([e_th, e_ph, d], -1)),  # columns: the disc's axes, its normal
                     opacity_logits=np.full(h * w, np.log(SHELL_OPACITY / (1 - SHELL_OPACITY))), sh=sh)
