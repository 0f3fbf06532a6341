"""Training rate of the hash teacher on an unbounded (contracted) capture, sampler variants in the same process (the
ratio is the trustworthy figure on a noisy machine): proposal sampling with colour for every sample (before),
with colour only for samples that weigh (now), and the occupancy grid over contracted space.

    python benchmarks/unbounded_speed.py --data outputs/bonsai [--downscale 2] [--warmup 300] [--steps 30]

Prints one JSON object: per variant train rays/s, samples per ray, ms per step, render rays/s, and the ratio
against the all-colour proposal path.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import torch

from nerfbake.data.formats import load_dataset
from nerfbake.data.pixels import PixelStore
from nerfbake.teacher.presets import preset
from nerfbake.teacher.train import scene_box
from nerfbake.train.loop import git_revision

sys.path.insert(0, str(Path(__file__).resolve().parent))
from teacher_speed import time_training  # noqa: E402


def _set(**kw):
    def apply(hash_cfg):
        for k, v in kw.items():
            setattr(hash_cfg, k, v)
    return apply


VARIANTS = {
    # what the proposal path did before colour culling: colour for every final sample
    "proposal-all-colour": _set(unbounded_sampler="proposal", color_weight_thresh=-1.0),
    "proposal": _set(unbounded_sampler="proposal"),  # colour only where the weight exceeds 1e-5 (the default)
    "grid": _set(unbounded_sampler="grid"),  # occupancy grid over contracted space, culled gradient pass
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--warmup", type=int, default=300, help="steps before timing (the grid prunes during them)")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--variants", default="proposal-all-colour,proposal,grid", help=", ".join(VARIANTS))
    args = ap.parse_args()
    ds = load_dataset(args.data, downscale=args.downscale)
    box = scene_box(ds)
    if not box.contracted:
        sys.exit(f"{args.data}: not an unbounded (contracted) scene for the teacher; choose a real 360 or forward capture")
    store = PixelStore(ds, "train")
    result = {"benchmark": "unbounded_speed", "data": args.data, "downscale": ds.downscale, "machine": platform.machine(),
              "cpus": torch.get_num_threads(), "device": "cuda" if torch.cuda.is_available() else "cpu",
              "git": git_revision()}
    for name in args.variants.split(","):
        cfg = preset("hash", "cpu-small")
        VARIANTS[name](cfg.hash)
        result[name] = time_training("hash", ds, store, args.warmup, args.steps, cfg)
        print(f"{name}: {result[name]['train_rays_per_s']:.0f} rays/s", file=sys.stderr, flush=True)
    base = result.get("proposal-all-colour")
    for name in args.variants.split(","):
        if base is not None:
            result[name]["train_rays_over_all_colour_proposal"] = result[name]["train_rays_per_s"] / base["train_rays_per_s"]
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
