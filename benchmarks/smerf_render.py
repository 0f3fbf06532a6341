"""Baked SMERF renderer throughput (the Warp re-implementation of the viewer's ray marcher): rays/s and ms/frame
for the test_frames.json views of an asset directory (default: the shared one-submodel fixture).

    python benchmarks/smerf_render.py [--assets DIR] [--width 800 --height 500] [--repeats 3]
    -> one JSON object on stdout
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from nerfbake.smerf.assets import SceneAssets
from nerfbake.smerf.baked_render import ViewerCamera, read_test_frames, render_baked
from nerfbake.train.loop import default_device, git_revision


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--assets", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "smerf_tiny"))
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--height", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    device = str(default_device())
    scene = SceneAssets.open(args.assets)
    frames = scene.root / f"sm_{scene.params['params_to_sm'][0]:03d}" / "test_frames.json"
    cams = read_test_frames(frames, args.width, args.height) if frames.is_file() else [
        ViewerCamera.perspective([0, 0, 0], np.diag([-1.0, 1.0, -1.0]), 40.0, args.width, args.height)]
    render_baked(scene, cams[0], device=device)  # warm-up: kernel load, submodel upload
    start = time.perf_counter()
    for _ in range(args.repeats):
        for cam in cams:
            render_baked(scene, cam, device=device)
    sec = (time.perf_counter() - start) / (args.repeats * len(cams))
    print(json.dumps({
        "assets": args.assets, "views": len(cams), "resolution": [args.width, args.height], "device": device,
        "threads": torch.get_num_threads(), "ms_per_frame": 1000 * sec, "rays_per_s": args.width * args.height / sec,
        "note": "includes the per-frame MLP weight interpolation, the deferred MLP in torch and host transfers",
        "machine": platform.processor() or platform.machine(), "git": git_revision(),
    }, indent=2))


if __name__ == "__main__":
    main()
