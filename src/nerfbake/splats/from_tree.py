"""Gaussians from a PlenOctree: one per leaf that is not empty.

A leaf is a cube of constant density and SH colour. Its Gaussian sits at the cube's centre with standard deviation
``SPREAD`` times the cube's side per axis (0.4: a lattice of such Gaussians at the leaves' spacing sums to about
one, so a surface of leaves is covered without holes or doubled opacity), opacity ``1 - exp(-sigma * side)``
(what a ray crossing the cube collects), and colour refitted: PlenOctrees' colour is ``sigmoid(SH . k)``, 3DGS's
``max(SH . k' + 0.5, 0)``, so ``k'`` is the least-squares fit of ``sigmoid(SH . k) - 0.5`` over ``DIRECTIONS``
directions spread over the sphere, not a copy of ``k``.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from nerfbake.octree.tree import Octree
from nerfbake.render.sh import sh_basis
from nerfbake.splats.gaussians import Gaussians

SPREAD = 0.4
DIRECTIONS = 128
MIN_OPACITY = 1.0 / 255.0  # a splat fainter than one 8-bit level is dropped


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
