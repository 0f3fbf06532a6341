"""Where a hash teacher's training step goes on the CPU: the field's and the proposal network's hash encodings
(forward and backward), the MLPs, the SH colour, the proposal sampling and its losses, Adam, and the rest, as
seconds a step and shares of it.

Runs the preset's training step (``teacher.train``'s own batch draw, loss and optimiser) on a dataset: ``--warmup``
steps uncounted, then ``--steps`` under torch's profiler, whose per-op CPU times are summed into the parts below
(``rest`` is the wall time of a step less the parts; the SH colour and the proposal parts are their forward
passes, their backward ops count in ``rest``). Run it alone: on 2 cores a second busy process makes torch's
worker threads spin and the shares meaningless. Step times on this machine vary by ±15 % between windows, so the
shares are the figure to read, not one window's seconds.

    python benchmarks/teacher_profile.py --data outputs/real/bonsai_data --downscale 2 [--steps 10] [--warmup 40]
    -> {"seconds_per_step": ..., "rays_per_s": ..., "parts": {"field_hash_backward": {"seconds_per_step": ...,
        "share": ...}, ...}}
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile, record_function

from nerfbake.data.formats import load_dataset
from nerfbake.data.pixels import PixelStore
from nerfbake.teacher import models as teacher_models
from nerfbake.teacher.models import build_teacher
from nerfbake.teacher.presets import preset
from nerfbake.teacher.proposal import ProposalSampler
from nerfbake.teacher.train import make_optimizer, scene_box
from nerfbake.train.loop import DataParallel, git_revision

sys.path.insert(0, str(Path(__file__).resolve().parent))
from teacher_speed import train_step  # noqa: E402


def labelled(name: str, fn):
    """``fn`` with its calls recorded under ``name`` in the profile (forward parts that are no single op)."""
    def wrapped(*args, **kwargs):
        with record_function(name):
            return fn(*args, **kwargs)
    return wrapped


def part_of(event, field_levels: int) -> str | None:
    """The part a profiled op belongs to, or None for ops counted inside another part (or in ``rest``)."""
    name = event.name
    if name in ("HashEncodeFunction", "HashEncodeFunctionBackward"):
        shapes = event.input_shapes or []
        if name == "HashEncodeFunction":  # inputs: points, table (L, T, 2), ...
            levels = shapes[1][0] if len(shapes) > 1 and shapes[1] else -1
        else:  # input: the gradient of the (N, 2L) encoding
            levels = shapes[0][1] // 2 if shapes and len(shapes[0]) == 2 else -1
        who = "field" if levels == field_levels else "proposal"
        return f"{who}_hash_{'backward' if name.endswith('Backward') else 'forward'}"
    if name == "_ChunkedReLUMLP":
        return "mlp_forward"
    if name == "_ChunkedReLUMLPBackward":
        return "mlp_backward"
    if name.startswith("Optimizer.step#"):
        return "adam"
    if name.startswith("Optimizer.zero_grad#"):
        return "zero_grad"
    if name in ("sh_colour", "proposal_sampling", "proposal_losses"):
        return name
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--preset", default="cpu-small")
    ap.add_argument("--steps", type=int, default=10, help="profiled steps")
    ap.add_argument("--warmup", type=int, default=40, help="steps before the profile (not counted)")
    args = ap.parse_args()
    dp = DataParallel()  # first: sets the CPU threads' float mode as a trainer does
    ds = load_dataset(args.data, downscale=args.downscale)
    store = PixelStore(ds, "train")
    cfg = preset("hash", args.preset)
    model = build_teacher("hash", cfg.model_config, scene_box(ds)).to(dp.device)
    opt = make_optimizer(model, cfg)
    teacher_models.eval_sh_color = labelled("sh_colour", teacher_models.eval_sh_color)
    ProposalSampler.sample = labelled("proposal_sampling", ProposalSampler.sample)
    ProposalSampler.losses = labelled("proposal_losses", ProposalSampler.losses)

    def step(s: int) -> None:
        loss, _ = train_step(model, opt, store, cfg, dp, s)
        float(loss)  # waits for the step, as the trainer's logging does

    for s in range(args.warmup):
        step(s)
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        t = time.perf_counter()
        for s in range(args.warmup, args.warmup + args.steps):
            step(s)
        total = time.perf_counter() - t
    seconds: dict[str, float] = {}
    field_levels = model.field.grid.levels

    def inner_parts(event) -> float:
        """CPU seconds of the parts nested inside ``event`` (the proposal sampling runs its own hash encoding and
        MLP), so that each op counts in one part only."""
        return sum(c.cpu_time_total / 1e6 if part_of(c, field_levels) else inner_parts(c) for c in event.cpu_children or [])

    for event in prof.events():
        part = part_of(event, field_levels)
        if part is not None:
            seconds[part] = seconds.get(part, 0.0) + event.cpu_time_total / 1e6 - inner_parts(event)
    seconds["rest"] = total - sum(seconds.values())
    parts = {name: {"seconds_per_step": round(s / args.steps, 4), "share": round(s / total, 3)}
             for name, s in sorted(seconds.items(), key=lambda kv: -kv[1])}
    print(json.dumps({"benchmark": "teacher_profile", "data": args.data, "downscale": args.downscale,
                      "preset": args.preset, "contracted": model.box.contracted, "git": git_revision(),
                      "torch_threads": torch.get_num_threads(), "steps_counted": args.steps,
                      "seconds_per_step": round(total / args.steps, 4),
                      "rays_per_s": round(cfg.batch_rays * args.steps / total),
                      "parts": parts}, indent=1))


if __name__ == "__main__":
    main()
