"""Training rate of the hash teacher on an unbounded (contracted) capture, variants in the same process (the ratio is
the trustworthy figure on a noisy machine):

* ``before``: the path before the cache-sized MLP pass: 64 proposal + 32 final samples, float32 MLPs run as one
  whole-batch layer sequence;
* ``chunked``: the same samples and precision, MLPs in 4096-row chunks (fields/encoding.py: MLP);
* ``now``: the cpu-small preset (chunked, bfloat16 MLPs where the CPU has them);
* ``32+16``: ``now`` with 32 proposal + 16 final samples (twice the rate, but 0.45 dB lower held-out on bonsai
  at equal time);
* ``grid``: the occupancy grid over contracted space instead of proposal sampling;
* ``table18``, ``table17``: ``now`` with the field's hash tables at 2^18 or 2^17 rows a level instead of 2^19 (a
  level's table of 2^17 rows is 1 MB, one core's L2 cache here; 2^19 rows are 4 MB). Bonsai at 400 px, same
  process: 1.18-1.37x the training rays/s (1.3x at 2^18), but whole training runs only 1.08x (0.465 against 0.50 s
  a step): the hash encoding is a quarter of a step.

    python benchmarks/unbounded_speed.py --data outputs/real/bonsai_data --downscale 2 [--warmup 300] [--steps 30]

Prints one JSON object: per variant train rays/s, samples per ray, ms per step, render rays/s, and the ratio
against ``before``.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import torch
from torch import nn

from nerfbake.data.formats import load_dataset
from nerfbake.data.pixels import PixelStore
from nerfbake.fields.encoding import MLP
from nerfbake.teacher.presets import preset
from nerfbake.teacher.train import scene_box
from nerfbake.train.loop import git_revision

sys.path.insert(0, str(Path(__file__).resolve().parent))
from teacher_speed import time_training  # noqa: E402


def _set(mlp_forward=None, **kw):
    """A variant: settings of the preset's hash teacher, and optionally the MLPs' forward."""
    def apply(cfg):
        for k, v in kw.items():
            part, _, key = k.rpartition("__")  # "field__log2_table": the field's, not the proposal network's
            owner = getattr(cfg.hash, part) if part else cfg.hash.proposal if hasattr(cfg.hash.proposal, k) else cfg.hash
            setattr(owner, key, v)
        return mlp_forward or MLP.forward
    return apply


VARIANTS = {
    "before": _set(nn.Sequential.forward, proposal_samples=64, final_samples=32, unbounded_mlp_dtype="float32"),
    "chunked": _set(proposal_samples=64, final_samples=32, unbounded_mlp_dtype="float32"),
    "now": _set(),
    "32+16": _set(proposal_samples=32, final_samples=16),
    "64+16": _set(final_samples=16),
    "64+32+16": _set(refine_samples=32, final_samples=16),  # a second proposal level
    "64+32+12": _set(refine_samples=32, final_samples=12),
    "grid": _set(unbounded_sampler="grid"),
    "table18": _set(field__log2_table=18),
    "table17": _set(field__log2_table=17),
    # Narrower final field on top of 64 + 16: one hidden colour layer (15 -> 64 -> 48 instead of two), or 12 hash
    # levels instead of 16, or 48 proposal samples.
    "64+16c1": _set(final_samples=16, field__color_layers=1),
    "64+16l12": _set(final_samples=16, field__levels=12),
    "48+16c1": _set(proposal_samples=48, final_samples=16, field__color_layers=1),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--warmup", type=int, default=300, help="steps before timing (the grid prunes during them)")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--variants", default="before,chunked,now", help=", ".join(VARIANTS))
    args = ap.parse_args()
    ds = load_dataset(args.data, downscale=args.downscale)
    box = scene_box(ds)
    if not box.contracted:
        sys.exit(f"{args.data}: not an unbounded (contracted) scene for the teacher; choose a real 360 or forward capture")
    store = PixelStore(ds, "train")
    result = {"benchmark": "unbounded_speed", "data": args.data, "downscale": ds.downscale, "machine": platform.machine(),
              "cpus": torch.get_num_threads(), "device": "cuda" if torch.cuda.is_available() else "cpu",
              "git": git_revision()}
    chunked_forward = MLP.forward
    for name in args.variants.split(","):
        cfg = preset("hash", "cpu-small")
        MLP.forward = VARIANTS[name](cfg)
        try:
            result[name] = time_training("hash", ds, store, args.warmup, args.steps, cfg)
        finally:
            MLP.forward = chunked_forward
        print(f"{name}: {result[name]['train_rays_per_s']:.0f} rays/s", file=sys.stderr, flush=True)
    base = result.get("before")
    for name in args.variants.split(","):
        if base is not None:
            result[name]["train_rays_over_before"] = result[name]["train_rays_per_s"] / base["train_rays_per_s"]
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
