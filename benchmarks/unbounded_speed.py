"""Training rate of the hash teacher on an unbounded (contracted) capture: the occupancy grid over contracted space
against proposal-network sampling, in the same process (the ratio is the trustworthy figure on a noisy machine).

    python benchmarks/unbounded_speed.py --data outputs/bonsai [--downscale 2] [--warmup 300] [--steps 30]

Prints one JSON object: per sampler train rays/s, samples per ray, ms per step, render rays/s; and the ratio.
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


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--warmup", type=int, default=300, help="steps before timing (the grid prunes during them)")
    ap.add_argument("--steps", type=int, default=30)
    args = ap.parse_args()
    ds = load_dataset(args.data, downscale=args.downscale)
    box = scene_box(ds)
    if not box.contracted:
        sys.exit(f"{args.data}: not an unbounded (contracted) scene for the teacher; choose a real 360 or forward capture")
    store = PixelStore(ds, "train")
    result = {"benchmark": "unbounded_speed", "data": args.data, "downscale": ds.downscale, "machine": platform.machine(),
              "cpus": torch.get_num_threads(), "device": "cuda" if torch.cuda.is_available() else "cpu",
              "git": git_revision()}
    for sampler in ("grid", "proposal"):
        cfg = preset("hash", "cpu-small")
        cfg.hash.unbounded_sampler = sampler
        result[sampler] = time_training("hash", ds, store, args.warmup, args.steps, cfg)
        print(f"{sampler}: {result[sampler]['train_rays_per_s']:.0f} rays/s", file=sys.stderr)
    result["grid_over_proposal_train_rays"] = result["grid"]["train_rays_per_s"] / result["proposal"]["train_rays_per_s"]
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
