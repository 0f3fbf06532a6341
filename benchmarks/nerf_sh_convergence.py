"""Does the paper-size NeRF-SH learn? Its ``paper`` architecture (8 x 256, 10 frequencies, skip at 4) against the
``cpu-small`` one (4 x 128) at the same steps, rays per step, samples per ray and image size, on lego_400 at
``--downscale 4`` (100 x 100), each from a fresh start with the same seed; held-out PSNR on the first test views.

With PlenOctrees' ReLU density (``--paper-activation relu``) the paper field's density goes dead everywhere in its
first Adam steps (Adam's first updates are the full learning rate in the sign of the gradient, on every weight at
once) and training stays at the background-only 12-14 dB; the preset's softplus cannot die. See the preset's comment.

    python benchmarks/nerf_sh_convergence.py [--steps 400] [--batch-rays 256] [--samples 32,64] [--views 3]
                                             [--paper-activation softplus|relu]
    -> one JSON object: per preset held-out PSNR, training-PSNR curve, seconds; paper_minus_small_db
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from nerfbake.teacher.evaluate import evaluate_teacher
from nerfbake.teacher.presets import preset
from nerfbake.teacher.train import train_teacher
from nerfbake.train.loop import git_revision, training_curve

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def run_preset(name: str, data: str, out: Path, args) -> dict:
    cfg = preset("nerf-sh", name)
    cfg.steps, cfg.batch_rays, cfg.downscale = args.steps, args.batch_rays, args.downscale
    cfg.val_every, cfg.checkpoint_every = 0, 10 ** 9
    if name == "paper" and args.paper_activation:
        cfg.nerf_sh.field.density_activation = args.paper_activation
    if args.samples:
        cfg.nerf_sh.coarse_samples, cfg.nerf_sh.fine_samples = (int(v) for v in args.samples.split(","))
    t = time.perf_counter()
    train_teacher(data, out, cfg)
    seconds = time.perf_counter() - t
    ev = evaluate_teacher(out, "test", max_views=args.views, write_images=False)
    curve = [[r["step"], round(r["psnr"], 2)] for r in training_curve(out, "psnr", points=10)]
    f = cfg.nerf_sh.field
    return {"architecture": f"{f.depth}x{f.width}, {f.num_freqs} freqs, skip {f.skip}, {f.density_activation}",
            "samples": [cfg.nerf_sh.coarse_samples, cfg.nerf_sh.fine_samples], "lr": cfg.lr,
            "warmup_steps": cfg.warmup_steps, "test_psnr": ev["psnr"], "test_ssim": ev.get("ssim"),
            "train_seconds": round(seconds, 1), "train_psnr_curve": curve}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(SHARED / "lego_400"))
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--batch-rays", type=int, default=256)
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--samples", default="32,64", help="coarse,fine for both ('' keeps each preset's own)")
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--paper-activation", choices=("relu", "softplus"), help="override the paper preset's density")
    ap.add_argument("--out", help="keep the two runs here (default: a temporary folder)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.out or tmp)
        res = {name: run_preset(name, args.data, root / name, args) for name in ("cpu-small", "paper")}
    res.update(steps=args.steps, batch_rays=args.batch_rays, downscale=args.downscale, git=git_revision(),
               paper_minus_small_db=res["paper"]["test_psnr"] - res["cpu-small"]["test_psnr"])
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
