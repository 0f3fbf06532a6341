"""PlenOctree renderer throughput on a built tree: rays/s and ms/frame at 400x400 and 800x800 (lego's test
cameras, intrinsics scaled), the Warp kernel against the vectorised torch reference on the same rays (the ratio is
the trustworthy figure on a noisy machine), and the analytic backward's rays/s.

    python benchmarks/octree_render.py --tree TREE.npz [--data ../shared/data/lego_400] [--views 3]
    -> one JSON object on stdout
"""
from __future__ import annotations

import argparse
import json
import platform
import time

import torch

from nerfbake.data.formats import load_dataset
from nerfbake.data.rays import camera_rays
from nerfbake.kernels.octree import render_backward
from nerfbake.octree.evaluate import time_frames
from nerfbake.octree.io import load_tree
from nerfbake.octree.render import RenderOptions, render_reference, render_rays
from nerfbake.train.loop import default_device, git_revision


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tree", required=True)
    ap.add_argument("--data", default="../shared/data/lego_400")
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--reference-rays", type=int, default=20000)
    args = ap.parse_args()
    device = default_device()
    tree = load_tree(args.tree, device)
    ds = load_dataset(args.data)
    cams = [ds.frames[i].camera for i in ds.split("test")[:: max(1, len(ds.split("test")) // args.views)][: args.views]]
    opts = RenderOptions()
    out = {"tree": args.tree, "num_leaves": tree.num_leaves, "device": str(device), "threads": torch.get_num_threads(),
           "machine": platform.processor() or platform.machine(), "git": git_revision(), "options": vars(opts)}
    for size in (400, 800):
        sec = time_frames(tree, [c.scaled(c.width / size) for c in cams], opts, args.repeats)
        out[f"ms_per_frame_{size}"] = 1000 * sec
        out[f"fps_{size}"] = 1 / sec
        out[f"rays_per_s_{size}"] = size * size / sec
    rays = camera_rays(cams[0])
    o, d = rays["origins"].reshape(-1, 3), rays["directions"].reshape(-1, 3)
    sel = torch.randperm(o.shape[0], generator=torch.Generator().manual_seed(0))[: args.reference_rays]
    o, d = o[sel].to(device), d[sel].to(device)
    render_rays(tree, o, d, opts)
    t = time.perf_counter()
    k = render_rays(tree, o, d, opts)
    t_kernel = time.perf_counter() - t
    t = time.perf_counter()
    r = render_reference(tree.to("cpu"), o.cpu(), d.cpu(), opts)
    t_ref = time.perf_counter() - t
    out.update(reference_rays_per_s=len(sel) / t_ref, kernel_rays_per_s_same_rays=len(sel) / t_kernel,
               kernel_speedup_vs_reference=t_ref / t_kernel,
               kernel_vs_reference_max_abs_rgb=float((k["rgb"].cpu() - r["rgb"]).abs().max()))
    train = RenderOptions.training()
    rgb = render_rays(tree, o, d, train)["rgb"]
    t = time.perf_counter()
    render_backward(tree, o, d, train, rgb, torch.ones_like(rgb))
    out["backward_rays_per_s"] = len(sel) / (time.perf_counter() - t)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
