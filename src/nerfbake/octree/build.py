"""Build a PlenOctree from a trained teacher (PlenOctrees section 4.2 and appendix B.2; the authors'
``octree/extraction.py``).

1. Bounding box: the teacher's box, optionally (``autoscale``) shrunk to the coarse cells the training views see.
2. Density on a dense G^3 grid over the box (G = 2^(depth+1)), in z-slabs; cells the teacher's own occupancy
   grid marks empty are not queried.
3. Keep voxels whose compositing weight reaches ``weight_thresh`` on some training ray.
4. The smallest tree whose depth-``depth`` leaves are the kept voxels; each kept leaf gets the mean of the
   teacher's sigma and SH coefficients at ``samples_per_leaf`` random points inside it (sigma ReLU'd); pruned
   space is zero.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from nerfbake.data.formats import load_dataset
from nerfbake.data.rays import camera_rays
from nerfbake.kernels.grid_weights import BLOCK, mark_visible_voxels
from nerfbake.octree.environment import bake_environment, needs_environment
from nerfbake.octree.io import save_tree
from nerfbake.octree.tree import Octree, tree_from_cells
from nerfbake.progress import progress_bar
from nerfbake.render.sh import sh_num_coeffs
from nerfbake.teacher.clearance import CameraClearance
from nerfbake.teacher.protocol import Teacher
from nerfbake.teacher.run import load_teacher
from nerfbake.train.loop import DataParallel, step_generator


@dataclass
class BuildConfig:
    """Settings of the tree extraction (PlenOctrees section 4.2): the dense grid, the weight mask over the training
    rays, the box fitted to what the views see, and the samples averaged into each leaf's SH."""
    # dense grid side G = 2^(depth+1); leaves at the finest depth have side box/G
    grid: int = field(default=512, metadata={"help": "dense grid side (power of two; 512 in the paper)"})
    weight_thresh: float = field(default=0.001, metadata={  # the authors' code default (configs keep it)
        "help": "keep voxels with this compositing weight on some training ray"})
    samples_per_leaf: int = field(default=256, metadata={"help": "teacher samples averaged per leaf (256 paper, 8 fast)"})
    autoscale: bool = field(default=True, metadata={"flag": "--no-autoscale",
                                                    "help": "keep the teacher's box instead of fitting one"})
    autoscale_grid: int = 256
    box_scale: float = field(default=1.0, metadata={"help": (
        "unbounded scenes: cover the teacher's core cube times this (the room beyond the cameras, drawn with "
        "parallax at coarser leaves) and draw only what lies beyond it from the environment map")})
    autoscale_weight: float = 0.05  # the box must hold what views clearly see; fainter floaters outside it are cut
    ray_stride: int = field(default=1, metadata={
        "help": "use every n-th pixel row/column of the training views for the weight mask"})
    seed: int = 0
    chunk: int = 1 << 18  # points per teacher query
    # Rows of the environment map (2x as many columns) baked for teachers that see past their box (unbounded
    # scenes, learned backgrounds: octree/environment.py); 0 draws the constant background there instead.
    env_map_height: int = field(default=256, metadata={"help": (
        "rows of the environment map baked for what lies beyond the box of an unbounded scene or a learned "
        "background (columns: twice that; 0: constant background)")})

    @property
    def depth(self) -> int:
        d = int(round(math.log2(self.grid))) - 1
        if self.grid < 8 or 2 ** (d + 1) != self.grid:
            raise ValueError(f"--grid must be a power of two >= 8, got {self.grid}")
        return d


def build_preset(name: str) -> BuildConfig:
    """The paper's build settings, or ``cpu-small``'s (same 512^3 grid, fewer samples per leaf)."""
    if name == "paper":
        return BuildConfig()
    if name == "cpu-small":
        # 512^3 as the paper: on lego_400 it is 0.28 dB under the teacher (256^3: 1.4 dB) and builds in ~4 min,
        # ~5.5 GB peak, on 2 cores; fewer samples per leaf and a higher weight threshold keep it fast
        return BuildConfig(grid=512, samples_per_leaf=8, autoscale_grid=128, weight_thresh=0.01)
    raise ValueError(f"unknown preset {name!r}; choose paper or cpu-small")


@torch.no_grad()
def query_density(teacher: Teacher, points: torch.Tensor, chunk: int) -> torch.Tensor:
    """The teacher's density at ``points`` (N, 3) -> (N,) on the CPU, ``chunk`` points per query."""
    dev = next(teacher.parameters()).device
    out = torch.empty(points.shape[0])
    for s in range(0, points.shape[0], chunk):
        out[s: s + chunk] = teacher.query(points[s: s + chunk].to(dev))[0].float().cpu()
    return out


def _cell_centres(lo: torch.Tensor, hi: torch.Tensor, g: int, z0: int, z1: int) -> torch.Tensor:
    """Centres of cells [:, :, z0:z1] of a g^3 grid over [lo, hi], flattened x-major."""
    ax = [(torch.arange(g if a < 2 else z1 - z0, dtype=torch.float64) + (0 if a < 2 else z0) + 0.5) / g for a in range(3)]
    xyz = torch.stack(torch.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    return (lo + xyz * (hi - lo)).float()


def density_grid(teacher: Teacher, clearance: CameraClearance, lo: torch.Tensor, hi: torch.Tensor, g: int, chunk: int,
                 desc: str, dp: DataParallel | None = None) -> torch.Tensor:
    """sigma at the cell centres of a g^3 grid over [lo, hi] (0 where the teacher's occupancy grid is empty and in
    its ``clearance`` around the training cameras); under torchrun each rank fills its share of the slabs."""
    dp = dp or DataParallel()
    sigma = torch.zeros(g, g, g)
    slab = max(1, (1 << 22) // (g * g))
    starts = list(range(0, g, slab))
    with progress_bar(desc, total=g, unit="slice") as advance:
        for j in dp.mine(len(starts)):
            z0 = starts[j]
            z1 = min(g, z0 + slab)
            pts = _cell_centres(lo, hi, g, z0, z1)
            live = teacher.may_be_occupied(pts) & ~clearance.inside(pts)
            vals = torch.zeros(pts.shape[0])
            if live.any():
                vals[live] = query_density(teacher, pts[live], chunk)
            sigma[:, :, z0:z1] = vals.reshape(g, g, z1 - z0)
            advance(z1 - z0)
    return dp.combine(sigma)


def autoscale_box(teacher: Teacher, clearance: CameraClearance, lo: torch.Tensor, hi: torch.Tensor, cameras,
                  cfg: BuildConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Tight box (one cell of margin) around the coarse cells that some training ray sees with weight >=
    autoscale_weight. The authors threshold alpha alone; counting only what the views see keeps a teacher's
    floaters in unseen corners from inflating the box."""
    g = cfg.autoscale_grid
    sigma = density_grid(teacher, clearance, lo, hi, g, cfg.chunk, "octree bbox")  # every rank ends with the whole grid
    coarse = BuildConfig(**{**asdict(cfg), "ray_stride": max(2, cfg.ray_stride), "weight_thresh": cfg.autoscale_weight})
    alive = weight_mask(sigma, lo, hi, cameras, coarse, "octree bbox rays") > 0
    if not alive.any():
        raise ValueError(f"no coarse cell of the teacher reaches weight {cfg.autoscale_weight} on a training ray; is it "
                         "trained? (or build with --no-autoscale)")
    idx = torch.nonzero(alive)
    cell = (hi - lo) / g
    new_lo = lo + (idx.min(0).values - 1).clamp_min(0) * cell
    new_hi = lo + (idx.max(0).values + 2).clamp_max(g) * cell
    return new_lo, new_hi


def weight_mask(sigma: torch.Tensor, lo, hi, cameras, cfg: BuildConfig, desc: str = "octree weights") -> torch.Tensor:
    """uint8 G^3: voxels with compositing weight >= cfg.weight_thresh on some training ray (under torchrun each
    rank marches its share of the cameras)."""
    dp = DataParallel()
    cameras = [cameras[i] for i in dp.mine(len(cameras))]
    g = sigma.shape[0]
    voxel_len = float(((hi - lo) / g).max()) * math.sqrt(3.0)
    skip_sigma = -math.log(1.0 - 0.1 * cfg.weight_thresh) / voxel_len
    blocks = sigma.reshape(g // BLOCK, BLOCK, g // BLOCK, BLOCK, g // BLOCK, BLOCK).amax(dim=(1, 3, 5))
    block_live = blocks > skip_sigma
    keep = torch.zeros(g, g, g, dtype=torch.uint8)
    total = sum(math.ceil(c.height / cfg.ray_stride) * math.ceil(c.width / cfg.ray_stride) for c in cameras)
    with progress_bar(desc, total=total, unit="ray") as advance:
        for cam in cameras:
            rays = camera_rays(cam)
            o = rays["origins"][:: cfg.ray_stride, :: cfg.ray_stride].reshape(-1, 3)
            d = rays["directions"][:: cfg.ray_stride, :: cfg.ray_stride].reshape(-1, 3)
            mark_visible_voxels(o, d, sigma, block_live, lo.tolist(), hi.tolist(), cfg.weight_thresh, keep)
            advance(o.shape[0])
    return dp.combine(keep, "max")


@torch.no_grad()
def fill_leaves(tree: Octree, teacher: Teacher, cfg: BuildConfig, cells: np.ndarray) -> None:
    """Each kept leaf (``cells``: integer coordinates at the finest depth) gets the mean of the teacher's SH and
    density (ReLU'd) at ``samples_per_leaf`` uniform points inside it; a density-weighted SH mean was tried and was
    no better on lego. Pruned space (every other leaf) stays zero: the teacher's faint density there would
    otherwise add haze across the large coarse leaves."""
    leaves = tree.leaves()
    g = 2 ** (tree.depth_limit + 1)
    coords = (leaves["corner"] * g).round().long().numpy()
    key = (coords[:, 0] * g + coords[:, 1]) * g + coords[:, 2]
    kept_key = (cells[:, 0].astype(np.int64) * g + cells[:, 1]) * g + cells[:, 2]
    kept = torch.from_numpy(np.isin(key, kept_key) & (leaves["depth"] == tree.depth_limit).numpy())
    leaves = {k: v[kept] for k, v in leaves.items()}
    n, m = leaves["index"].numel(), cfg.samples_per_leaf
    dp = DataParallel()
    dev = next(teacher.parameters()).device
    flat = tree.data.view(-1, tree.data_dim)
    per = max(1, cfg.chunk // m)
    nb = tree.num_basis
    if 3 * nb != 3 * sh_num_coeffs(teacher.sh_degree):
        raise ValueError("tree and teacher disagree on the SH degree")
    with progress_bar("octree leaves", total=n, unit="leaf") as advance:
        for j in dp.mine(-(-n // per)):  # chunks dealt out over torchrun ranks; random points seeded per chunk
            s = j * per
            idx = leaves["index"][s: s + per]
            corner = leaves["corner"][s: s + per]
            size = leaves["size"][s: s + per]
            u = torch.rand(idx.numel(), m, 3, generator=step_generator(cfg.seed, j), dtype=torch.float64)
            q = corner[:, None, :] + u * size[:, None, None]
            world = tree.tree_to_world(q.reshape(-1, 3)).float()
            sigma, sh = teacher.query(world.to(dev))
            vals = torch.cat([sh.float(), sigma.float()[:, None]], -1).cpu().reshape(idx.numel(), m, -1).mean(1)
            vals[:, -1].clamp_(min=0.0)
            flat[idx] = vals
            advance(idx.numel())
    dp.combine(flat)  # the other leaves are zero on each rank


def unbuildable_reason(meta: dict, clearance: CameraClearance) -> str | None:
    """Why no PlenOctree can be cut from the teacher run whose ``config.json`` is ``meta`` (``clearance``: its near
    bound around its training cameras): the build refuses with it and the pipeline skips the octree route with it;
    None when a tree can be built.

    A forward-facing capture's content lies in front of the cameras out to infinity, with no box around it that
    its cameras look into from outside. A box that lies wholly within the teacher's near bound of its cameras
    (fern read as a 360 capture: its whole core cube) holds only space the teacher's rays never reached."""
    box = meta["box"]
    if box.get("contracted") and meta.get("dataset", {}).get("scene_kind") == "forward-facing":
        return ("a PlenOctree covers one bounded box, and this forward-facing capture's content lies in front of its "
                "cameras out to infinity; use SMERF for it")
    lo, hi = (torch.tensor(box[k], dtype=torch.float64) for k in ("box_min", "box_max"))
    if clearance.inside(_cell_centres(lo, hi, 16, 0, 16)).all():
        return (f"all of the teacher's box lies within its near bound ({clearance.radius:.3g}) of a training camera, "
                "space its rays never reached (the scene's content lies beyond it); use SMERF for it, or retrain "
                "with the --normalize that matches the capture")
    return None


def build_octree(teacher_run: str | Path, out: str | Path, cfg: BuildConfig) -> dict:
    """Build and save a tree; returns a summary (also written next to it as JSON)."""
    start = time.time()
    teacher, tcfg, meta, _ = load_teacher(Path(teacher_run))
    cameras = load_dataset(meta["data"], downscale=tcfg.downscale, normalize=tcfg.normalize).cameras("train")
    clearance = CameraClearance.of_teacher(meta, cameras)
    reason = unbuildable_reason(meta, clearance)
    if reason:
        raise ValueError(f"{teacher_run}: {reason}")
    region = "the teacher's box"
    if meta["box"].get("contracted"):
        # An unbounded 360 scene: the tree covers the uncontracted core (the cube the cameras stand in, where the
        # teacher spends its resolution); what lies beyond is drawn from an environment map (see below).
        region = "the unbounded scene's uncontracted core (cameras inside it)"
    depth = cfg.depth
    lo = torch.tensor(meta["box"]["box_min"], dtype=torch.float64)
    hi = torch.tensor(meta["box"]["box_max"], dtype=torch.float64)
    if cfg.box_scale != 1.0:
        if not meta["box"].get("contracted") or cfg.box_scale <= 0:
            raise ValueError(f"--box-scale {cfg.box_scale}: only an unbounded (contracted) teacher has a field beyond "
                             "its box, and the scale must be positive; leave it at 1 for this teacher")
        centre = (lo + hi) / 2
        lo, hi = centre + (lo - centre) * cfg.box_scale, centre + (hi - centre) * cfg.box_scale
        region = f"{cfg.box_scale:g} x " + region
    if cfg.autoscale:
        lo, hi = autoscale_box(teacher, clearance, lo, hi, cameras, cfg)
    sigma = density_grid(teacher, clearance, lo, hi, cfg.grid, cfg.chunk, "octree density")
    keep = weight_mask(sigma, lo, hi, cameras, cfg)
    cells = torch.nonzero(keep).numpy()
    if cells.shape[0] == 0:
        raise ValueError(f"no voxel reaches weight {cfg.weight_thresh} on any training ray; lower --weight-thresh")
    del sigma, keep
    tree = tree_from_cells(cells, depth, lo.numpy(), hi.numpy(), 3 * sh_num_coeffs(teacher.sh_degree) + 1)
    fill_leaves(tree, teacher, cfg, cells)
    dp = DataParallel()
    path = Path(out)
    if cfg.env_map_height and needs_environment(teacher) and dp.is_main:
        bg = tuple(meta.get("dataset", {}).get("background") or (1.0, 1.0, 1.0))
        tree.env_map = bake_environment(teacher, lo.float(), hi.float(), cameras, cfg.env_map_height, bg)
        region += f"; beyond it, a {cfg.env_map_height}x{2 * cfg.env_map_height} environment map baked from the teacher"
    elif meta["box"].get("contracted"):
        region += "; beyond it, the background colour"
    if dp.is_main:
        save_tree(tree, path)
    dp.barrier()
    summary = {
        "tree": str(path), "teacher": str(teacher_run), "num_leaves": tree.num_leaves, "num_nodes": tree.num_nodes,
        "kept_voxels": int(cells.shape[0]), "depth_limit": depth, "data_format": tree.data_format,
        "box_min": lo.tolist(), "box_max": hi.tolist(), "region": region,
        "env_map": None if tree.env_map is None else list(tree.env_map.shape[:2]), "file_bytes": path.stat().st_size,
        "seconds": time.time() - start, "config": asdict(cfg), "data": meta["data"], "downscale": tcfg.downscale,
    }
    return summary
