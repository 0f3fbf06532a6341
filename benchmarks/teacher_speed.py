"""Training and rendering throughput of both teacher fields, plus the Warp hash-encoding kernel against the
plain-torch reference in the same process (the ratio is the trustworthy figure on a noisy machine).

    python benchmarks/teacher_speed.py [--data DIR] [--steps N]   -> one JSON object on stdout
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import torch

from nerfbake.data.formats import load_dataset
from nerfbake.data.pixels import PixelStore
from nerfbake.kernels.hashgrid import hash_encode, hash_encode_reference
from nerfbake.teacher.models import build_teacher
from nerfbake.teacher.presets import preset
from nerfbake.teacher.train import draw_batch, loss_terms, make_optimizer, scene_box
from nerfbake.train.loop import DataParallel
from nerfbake.train.loop import default_device, git_revision, step_generator


def sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def train_step(model, opt, store, cfg, dp: DataParallel, step: int):
    """One training step as ``teacher.train`` takes it (its batch draw, loss and optimiser; no learning-rate
    schedule); returns the loss and the render."""
    gen = step_generator(cfg.seed, step)
    model.train()
    model.before_step(step, gen)
    batch = draw_batch(store, model, cfg, gen, dp)
    loss, _, out, _ = loss_terms(model, batch, cfg.batch_rays, gen)
    opt.zero_grad(set_to_none=False)  # as the trainer: keeps the hash gradient buffer
    loss.backward()
    opt.step()
    return loss, out


def time_training(kind: str, ds, store, warmup: int, steps: int, cfg=None) -> dict:
    """Training and rendering rates of one teacher (the preset's, or ``cfg``) after ``warmup`` steps."""
    cfg = cfg or preset(kind, "cpu-small")
    dp = DataParallel()  # first: sets the CPU threads' float mode as a trainer does
    device = dp.device
    model = build_teacher(kind, cfg.model_config, scene_box(ds)).to(device)
    opt = make_optimizer(model, cfg)
    samples = 0
    for step in range(warmup + steps):
        if step == warmup:
            sync()
            t = time.perf_counter()
            samples = 0
        _, out = train_step(model, opt, store, cfg, dp, step)
        samples += out["num_samples"]
    sync()
    dt = time.perf_counter() - t
    model.eval()
    render_batch = {k: v.to(device) for k, v in store.sample_uniform_rays(8192, step_generator(1, 0)).items()}
    white = torch.ones(3, device=device)
    with torch.no_grad():
        model.render_rays(render_batch["origins"][:1024], render_batch["directions"][:1024], white)
        sync()
        t = time.perf_counter()
        model.render_rays(render_batch["origins"], render_batch["directions"], white)
        sync()
        rdt = time.perf_counter() - t
    return {"train_rays_per_s": cfg.batch_rays * steps / dt, "train_samples_per_ray": samples / (cfg.batch_rays * steps),
            "train_ms_per_step": 1000 * dt / steps, "batch_rays": cfg.batch_rays, "render_rays_per_s": 8192 / rdt,
            "note": f"after {warmup} warm-up steps" + (" (occupancy grid pruned)" if hasattr(model, "grid") else "")}


def time_hash_kernel() -> dict:
    res = torch.tensor([int(16 * 1.38**i) for i in range(16)], dtype=torch.int32)
    dense = ((res.long() + 1) ** 3 <= 2**19).int()
    table = torch.randn(16, 2**19, 2) * 1e-2
    x = torch.rand(100_000, 3, generator=torch.Generator().manual_seed(0))
    device = default_device()
    res, dense, table, x = (v.to(device) for v in (res, dense, table, x))

    def best(fn, reps=3):
        out = []
        for _ in range(reps):
            t = time.perf_counter()
            fn()
            sync()
            out.append(time.perf_counter() - t)
        return min(out)

    best(lambda: hash_encode(x, table, res, dense), 1)
    warp_s = best(lambda: hash_encode(x, table, res, dense))
    ref_s = best(lambda: hash_encode_reference(x, table, res, dense), 2)
    return {"points": 100_000, "warp_points_per_s": 1e5 / warp_s, "torch_points_per_s": 1e5 / ref_s,
            "warp_speedup": ref_s / warp_s}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "lego_400"))
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=150)
    args = ap.parse_args()
    ds = load_dataset(args.data)
    store = PixelStore(ds, "train")
    result = {
        "benchmark": "teacher_speed", "data": args.data, "machine": platform.machine(), "cpus": torch.get_num_threads(),
        "device": "cuda" if torch.cuda.is_available() else "cpu", "git": git_revision(),
        "hash_encoding": time_hash_kernel(),
        "hash": time_training("hash", ds, store, args.warmup, args.steps),
        "nerf_sh": time_training("nerf-sh", ds, store, 3, max(3, args.steps // 4)),
    }
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
