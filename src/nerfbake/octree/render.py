"""Rendering a tree: options (the authors' viewer's knobs), the Warp kernel front end, and a vectorised torch
reference that follows the same traversal step by step (used to test the kernel and as autograd's ground truth).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nerfbake.atomic import check_output_folder
from nerfbake.data.cameras import Camera
from nerfbake.data.formats.pose_file import read_pose_file
from nerfbake.data.rays import camera_rays
from nerfbake.eval.views import render_views_to_folder
from nerfbake.kernels.octree import render_forward
from nerfbake.octree.io import load_tree
from nerfbake.octree.tree import Octree
from nerfbake.render.envmap import sample_equirect
from nerfbake.render.packed import packed_composite, packed_weights
from nerfbake.render.sh import sh_basis
from nerfbake.train.loop import default_device


@dataclass
class RenderOptions:
    """Defaults are volrend's high-quality setting; training uses ``training()`` (no skipping, no early stop)."""

    step_size: float = 1e-4  # tree units past each leaf exit
    sigma_thresh: float = 1e-2
    stop_thresh: float = 1e-2
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    bbox_min: tuple[float, float, float] = (0.0, 0.0, 0.0)  # slicing box in tree coordinates
    bbox_max: tuple[float, float, float] = (1.0, 1.0, 1.0)
    basis_min: int = 0  # SH component range [basis_min, basis_max); None = all the tree holds
    basis_max: int | None = None

    @classmethod
    def from_text(cls, step_size: float | None = None, sh_range: str | None = None, slice_box: str | None = None,
                  **kw) -> "RenderOptions":
        """Options as the command line gives them: ``sh_range`` "lo,hi" (half-open), ``slice_box`` six numbers
        "xmin,ymin,zmin,xmax,ymax,zmax" in tree coordinates [0, 1]."""
        opts = cls(**kw)
        if step_size is not None:
            opts.step_size = step_size
        if sh_range:
            opts.basis_min, opts.basis_max = (int(v) for v in sh_range.split(","))
        if slice_box:
            v = [float(x) for x in slice_box.split(",")]
            if len(v) != 6:
                raise ValueError("--slice takes 6 numbers: xmin,ymin,zmin,xmax,ymax,zmax in tree coordinates [0, 1]")
            opts.bbox_min, opts.bbox_max = tuple(v[:3]), tuple(v[3:])
        return opts

    @classmethod
    def training(cls, **kw) -> "RenderOptions":
        return cls(sigma_thresh=0.0, stop_thresh=0.0, **kw)

    def basis_range(self, num_basis: int) -> tuple[int, int]:
        hi = num_basis if self.basis_max is None else self.basis_max
        if not 0 <= self.basis_min < hi <= num_basis:
            raise ValueError(f"SH component range [{self.basis_min}, {hi}) is outside the {num_basis} basis functions this tree holds")
        return self.basis_min, hi


def render_rays(tree: Octree, origins: torch.Tensor, dirs: torch.Tensor, opts: RenderOptions | None = None) -> dict:
    """Kernel renderer: rgb (R, 3), depth (R,), alpha (R,) for world rays with unit directions."""
    opts = opts or RenderOptions()
    opts.basis_range(tree.num_basis)
    return render_forward(tree, origins.to(tree.device), dirs.to(tree.device), opts)


def render_camera(tree: Octree, camera: Camera, opts: RenderOptions | None = None, chunk: int = 1 << 18) -> dict[str, np.ndarray]:
    """Whole image: rgb (H, W, 3), depth (H, W), alpha (H, W)."""
    rays = camera_rays(camera)
    o, d = rays["origins"].reshape(-1, 3), rays["directions"].reshape(-1, 3)
    parts = [render_rays(tree, o[s: s + chunk], d[s: s + chunk], opts) for s in range(0, o.shape[0], chunk)]
    h, w = camera.height, camera.width
    return {k: torch.cat([p[k] for p in parts]).reshape(h, w, -1).squeeze(-1).cpu().numpy() for k in parts[0]}


def _ray_setup(tree: Octree, origins, dirs, opts: RenderOptions):
    ot = tree.offset.to(origins) + tree.invradius.to(origins) * origins
    ds = tree.invradius.to(dirs) * dirs
    scale = ds.norm(dim=-1)
    dt = ds / scale[:, None]
    lo = torch.tensor(opts.bbox_min, dtype=origins.dtype)
    hi = torch.tensor(opts.bbox_max, dtype=origins.dtype)
    inv = 1.0 / dt
    ta, tb = (lo - ot) * inv, (hi - ot) * inv
    zero = dt == 0
    outside = zero & ((ot < lo) | (ot > hi))
    t0 = torch.where(zero, torch.full_like(ta, -1e9), torch.minimum(ta, tb)).amax(-1).clamp_min(0.0)
    t1 = torch.where(zero, torch.full_like(ta, 1e9), torch.maximum(ta, tb)).amin(-1).clamp_max(1e9)
    t1 = torch.where(outside.any(-1), torch.full_like(t1, -1.0), t1)
    return ot, dt, 1.0 / scale, t0, t1


@torch.no_grad()
def trace_reference(tree: Octree, origins: torch.Tensor, dirs: torch.Tensor, opts: RenderOptions) -> dict:
    """Samples each ray takes, as packed lists: ray index, flat leaf index, start t and length (world units).
    Transmittance decides early stopping exactly as in the kernel."""
    ot, dt, to_world, t, t_end = _ray_setup(tree, origins, dirs, opts)
    flat = tree.data.reshape(-1, tree.data_dim)
    rays = torch.arange(origins.shape[0])
    T = torch.ones(origins.shape[0], dtype=origins.dtype)
    stopped = torch.zeros(origins.shape[0], dtype=torch.bool)
    out = {"ray": [], "slot": [], "t": [], "delta": []}
    active = t < t_end
    while bool(active.any()):
        a = rays[active]
        p = ot[a] + t[a, None] * dt[a]
        slot, cube, q = tree.descend(p)
        delta = leaf_exit_reference(q, dt[a], cube)
        sigma = flat[slot, -1].to(origins.dtype)
        keep = sigma > opts.sigma_thresh
        dw = delta * to_world[a]
        for k, v in zip(("ray", "slot", "t", "delta"), (a, slot, t[a] * to_world[a], dw)):
            out[k].append(v[keep])
        T[a] = torch.where(keep, T[a] * torch.exp(-dw * sigma), T[a])
        now_stopped = keep & (T[a] < opts.stop_thresh)
        stopped[a] |= now_stopped
        t[a] = t[a] + delta + opts.step_size
        active = (t < t_end) & ~stopped
    cat = {k: torch.cat(v) if v else torch.zeros(0) for k, v in out.items()}
    order = torch.argsort(cat["ray"], stable=True)
    res = {k: v[order] for k, v in cat.items()}
    res["stopped"] = stopped
    return res


def leaf_exit_reference(q: torch.Tensor, d: torch.Tensor, cube: torch.Tensor) -> torch.Tensor:
    """Distance in tree units to where rays leave their leaves: ``q`` (N, 3) the points in leaf-local [0, 1)^3,
    ``d`` (N, 3) tree-space directions, ``cube`` (N,) cells per axis at the leaf's depth (what
    :meth:`Octree.descend` returns) -> (N,). The torch twin of the kernel's step."""
    big = torch.full_like(q, 1e9)
    t = torch.where(d > 0, (1.0 - q) / d, torch.where(d < 0, -q / d, big))
    return t.amin(-1).clamp_max(1e9) / cube


def render_reference(tree: Octree, origins: torch.Tensor, dirs: torch.Tensor, opts: RenderOptions | None = None,
                     data: torch.Tensor | None = None) -> dict:
    """Differentiable (w.r.t. ``data``, default ``tree.data``) torch renderer with the kernel's semantics."""
    opts = opts or RenderOptions()
    lo, hi = opts.basis_range(tree.num_basis)
    data = tree.data if data is None else data
    s = trace_reference(tree, origins, dirs, opts)
    n = origins.shape[0]
    flat = data.reshape(-1, tree.data_dim)[s["slot"]]
    sigma = flat[:, -1]
    nb = tree.num_basis
    basis = sh_basis(4, dirs[s["ray"]].to(flat))[:, :nb]
    basis = torch.where((torch.arange(nb) >= lo) & (torch.arange(nb) < hi), basis, torch.zeros_like(basis))
    coef = flat[:, :-1].reshape(-1, 3, nb)
    color = torch.sigmoid((coef * basis[:, None, :]).sum(-1))
    t0 = s["t"].to(flat)
    w, _ = packed_weights(sigma, t0, t0 + s["delta"].to(flat), s["ray"], n)
    out = packed_composite(w, color, t0, t0 + s["delta"].to(flat), s["ray"], n)
    rgb, acc, depth = out["rgb"], out["acc"], out["depth"]
    T = 1.0 - acc
    bg = torch.tensor(opts.background, dtype=flat.dtype) if tree.env_map is None else \
        sample_equirect(tree.env_map, dirs).to(flat.dtype)
    stopped = s["stopped"][:, None]
    rgb = torch.where(stopped, rgb / (1.0 - T[:, None]).clamp_min(1e-12), rgb + T[:, None] * bg)
    alpha = torch.where(s["stopped"], torch.ones_like(acc), acc)
    return {"rgb": rgb, "depth": depth, "alpha": alpha}


def render_pose_file(tree_path, pose_file, out, opts: RenderOptions, overwrite: bool = False, depth: bool = False) -> list:
    """``nerfbake octree render``: one PNG per pose of a transforms-style JSON (and ``NNNN_depth.npy`` with
    ``depth``) in ``out``, which appears only once every view is written."""
    check_output_folder(out, overwrite, "render")
    tree = load_tree(tree_path, default_device())

    def render(cam):
        img = render_camera(tree, cam, opts)
        return {"rgb": img["rgb"], "depth": img["depth"] if depth else None}

    return render_views_to_folder(render, read_pose_file(pose_file), out, overwrite, desc="octree render")
