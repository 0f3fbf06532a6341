"""The tree in memory, in svox's layout so that saving is a dtype cast.

Nodes hold 2x2x2 cells. ``child[n, x, y, z]`` is the *relative* index of the node refining that cell
(0 = the cell is a leaf); node 0 is the root. ``data[n, x, y, z]`` holds a leaf's values
``[R_0..R_{B-1}, G_0..G_{B-1}, B_0..B_{B-1}, sigma]`` (pre-sigmoid SH, density in world units). World point p
maps to tree coordinates ``offset + invradius * p`` in [0, 1)^3; a cell of a node at depth d has side 2^-(d+1).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


N = 2  # branching factor per axis; volrend's shaders hard-code 2


def sh_format(num_basis: int) -> str:
    """svox's ``data_format`` string for a tree with ``num_basis`` SH bases per channel."""
    return f"SH{num_basis}"


def basis_from_format(data_format: str, data_dim: int) -> int:
    """Number of SH basis functions per colour channel, checked against ``data_dim``."""
    if data_format.startswith("SH"):
        b = int(data_format[2:])
        if b not in (1, 4, 9, 16, 25) or 3 * b + 1 != data_dim:
            raise ValueError(f"data_format {data_format} does not match data_dim {data_dim} (SH B needs 3B+1 channels, B a square <= 25)")
        return b
    raise ValueError(f"data_format {data_format!r} is not supported (nerfbake reads SH trees: SH1/SH4/SH9/SH16/SH25)")


@dataclass
class Octree:
    """A PlenOctree in svox's layout (see the module docstring); tensors on one device."""
    child: torch.Tensor  # int32 (n, 2, 2, 2)
    data: torch.Tensor  # float32 (n, 2, 2, 2, 3B+1)
    offset: torch.Tensor  # float32 (3,)
    invradius: torch.Tensor  # float32 (3,)
    depth_limit: int
    # Colour beyond the tree's box by direction, (H, W, 3) in [0, 1] (render/envmap.py's convention), or None: the
    # renderer's constant background. Baked from the teacher for scenes whose photos show more than the box.
    env_map: torch.Tensor | None = None

    @property
    def num_nodes(self) -> int:
        return self.child.shape[0]

    @property
    def data_dim(self) -> int:
        return self.data.shape[-1]

    @property
    def num_basis(self) -> int:
        return (self.data_dim - 1) // 3

    @property
    def sh_degree(self) -> int:
        return int(round(self.num_basis ** 0.5)) - 1

    @property
    def data_format(self) -> str:
        return sh_format(self.num_basis)

    @property
    def num_leaves(self) -> int:
        return int((self.child == 0).sum())

    @property
    def device(self) -> torch.device:
        return self.data.device

    def to(self, device) -> "Octree":
        env = None if self.env_map is None else self.env_map.to(device)
        return Octree(self.child.to(device), self.data.to(device), self.offset.to(device), self.invradius.to(device),
                      self.depth_limit, env)

    def world_to_tree(self, p: torch.Tensor) -> torch.Tensor:
        return self.offset.to(p) + self.invradius.to(p) * p

    def tree_to_world(self, q: torch.Tensor) -> torch.Tensor:
        return (q - self.offset.to(q)) / self.invradius.to(q)

    @property
    def world_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = (-self.offset / self.invradius).cpu().numpy()
        return lo, lo + 1.0 / self.invradius.cpu().numpy()

    def parent_depth(self) -> np.ndarray:
        """svox's ``parent_depth`` (n, 2): [parent node * 8 + cell slot, node depth]; the root stores [0, 0]."""
        child = self.child.cpu().numpy().reshape(-1)
        out = np.zeros((self.num_nodes, 2), np.int32)
        nodes, depth = np.zeros(1, np.int64), 0
        while nodes.size:
            out[nodes, 1] = depth
            slots = (nodes[:, None] * 8 + np.arange(8)).reshape(-1)
            slots = slots[child[slots] != 0]
            nodes = slots // 8 + child[slots]
            out[nodes, 0] = slots
            depth += 1
        return out

    def leaves(self) -> dict[str, torch.Tensor]:
        """Every leaf: flat cell index into ``data.view(-1, D)``, lower corner in tree coordinates, side, depth."""
        child = self.child.reshape(-1).cpu()
        nodes = torch.zeros(1, dtype=torch.long)
        corner = torch.zeros(1, 3, dtype=torch.float64)
        cell_off = torch.tensor([[x, y, z] for x in range(N) for y in range(N) for z in range(N)], dtype=torch.float64)
        out = {"index": [], "corner": [], "size": [], "depth": []}
        depth = 0
        while nodes.numel():
            size = 0.5 ** (depth + 1)
            slots = (nodes[:, None] * 8 + torch.arange(8)).reshape(-1)
            corners = (corner[:, None, :] + cell_off[None] * size).reshape(-1, 3)
            ptr = child[slots].long()
            leaf = ptr == 0
            out["index"].append(slots[leaf])
            out["corner"].append(corners[leaf])
            out["size"].append(torch.full((int(leaf.sum()),), size, dtype=torch.float64))
            out["depth"].append(torch.full((int(leaf.sum()),), depth, dtype=torch.long))
            nodes = slots[~leaf] // 8 + ptr[~leaf]
            corner = corners[~leaf]
            depth += 1
        return {k: torch.cat(v) for k, v in out.items()}

    def descend(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """For tree-space points q (M, 3): flat leaf index (into ``data.view(-1, D)``), cells per axis at the leaf's
        depth, and the point in leaf-local [0, 1)^3, computed step by step as the render kernel does."""
        child = self.child.reshape(-1)
        q = q.clamp(0.0, 0.9999999)
        node = torch.zeros(q.shape[0], dtype=torch.long, device=q.device)
        slot = node.clone()
        cube = torch.ones(q.shape[0], dtype=q.dtype, device=q.device)
        local = q.clone()
        active = torch.ones_like(node, dtype=torch.bool)
        for _ in range(self.depth_limit + 2):
            q = q * N
            idx = q.floor().clamp(0, N - 1)
            q = q - idx
            idx = idx.long()
            s = node * 8 + idx[:, 0] * 4 + idx[:, 1] * 2 + idx[:, 2]
            slot = torch.where(active, s, slot)
            cube = torch.where(active, cube * N, cube)
            local = torch.where(active[:, None], q, local)
            ptr = child[slot].long()
            active = active & (ptr != 0)
            if not bool(active.any()):
                break
            node = torch.where(active, node + ptr, node)
        return slot, cube, local

    def lookup(self, q: torch.Tensor) -> torch.Tensor:
        """Flat leaf index (into ``data.view(-1, D)``) of tree-space points q (M, 3) in [0, 1)^3."""
        return self.descend(q)[0]

    def query(self, points: torch.Tensor) -> torch.Tensor:
        """Leaf values at world points (M, 3), as svox's ``N3Tree.__call__``."""
        return self.data.reshape(-1, self.data_dim)[self.lookup(self.world_to_tree(points.to(self.data)))]


def tree_from_cells(cells: np.ndarray, depth: int, box_min, box_max, data_dim: int) -> Octree:
    """Smallest tree whose leaves at ``depth`` (a 2^(depth+1) grid over the cube) are exactly ``cells``
    (M, 3) integer coordinates; every other region is a coarser leaf. Nodes are in breadth-first order."""
    res = N ** (depth + 1)
    cells = np.unique(np.asarray(cells, np.int64), axis=0)
    if cells.size and (cells.min() < 0 or cells.max() >= res):
        raise ValueError(f"cell coordinates must lie in [0, {res})")
    levels = []  # node coordinates per depth, sorted by linear key
    for d in range(depth + 1):
        c = np.unique(cells >> (depth - d + 1), axis=0) if cells.size else np.zeros((0, 3), np.int64)
        if d == 0:
            c = np.zeros((1, 3), np.int64)
        levels.append(c)
    starts = np.cumsum([0] + [len(c) for c in levels])
    child = np.zeros((starts[-1], N, N, N), np.int32)
    for d in range(depth):
        side = N ** (d + 1)  # node grid side at depth d+1
        kids = levels[d + 1]
        key_k = (kids[:, 0] * side + kids[:, 1]) * side + kids[:, 2]
        parent = kids >> 1
        pside = N ** d
        key_p = (parent[:, 0] * pside + parent[:, 1]) * pside + parent[:, 2]
        lvl = levels[d]
        key_lvl = (lvl[:, 0] * pside + lvl[:, 1]) * pside + lvl[:, 2]
        pidx = starts[d] + np.searchsorted(key_lvl, key_p)
        kidx = starts[d + 1] + np.searchsorted(np.sort(key_k), key_k)
        b = kids & 1
        child[pidx, b[:, 0], b[:, 1], b[:, 2]] = (kidx - pidx).astype(np.int32)
    box_min, box_max = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
    inv = 1.0 / (box_max - box_min)
    return Octree(
        child=torch.from_numpy(child),
        data=torch.zeros(starts[-1], N, N, N, data_dim),
        offset=torch.tensor(-box_min * inv, dtype=torch.float32),
        invradius=torch.tensor(inv, dtype=torch.float32),
        depth_limit=depth,
    )
