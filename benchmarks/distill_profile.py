"""Where a distillation step's time goes: the teacher's render, the student's render and backward pass, the
regularisers, Adam and zeroing the gradients, as seconds a step and shares of it.

Runs the real ``distill`` loop on a finished teacher for a few steps (into a scratch folder it deletes), timing the
functions it calls; the first ``--warmup`` steps (kernel loading, first allocations) are not counted. Run it alone:
on 2 cores a second busy process makes torch's worker threads spin and the shares meaningless (a profile taken
beside another training run put the teacher at 66 % of a bonsai step; alone it is 19 %).

``--dense-baseline`` runs the same steps a second time as distillation ran before RowAdam (torch's fused dense
Adam over the whole grids, no row masks) and reports the ratio of the two step times.

    python benchmarks/distill_profile.py --teacher outputs/real/bonsai/teacher \
        [--config outputs/real/bonsai/smerf/student/config.json] [--steps 16] [--warmup 3] [--dense-baseline]
    -> {"seconds_per_step": ..., "parts": {"backward": {"seconds_per_step": ..., "share": ...}, ...},
        "dense_baseline": {"seconds_per_step": ..., "parts": ...}, "speedup_over_dense": ...}
"""
from __future__ import annotations

import argparse
import collections
import json
import shutil
import tempfile
import time
from dataclasses import replace

import torch

from nerfbake.smerf import distill as distill_module
from nerfbake.smerf.run import config_from_file, distill_preset
from nerfbake.smerf.student import Student
from nerfbake.train.row_adam import RowAdam


class StepTimer:
    """Seconds spent in each wrapped function once ``counting_since`` is set (at the first step after the warm-up)."""

    def __init__(self):
        self.seconds = collections.defaultdict(float)
        self.counting_since = None

    def wrap(self, name: str, fn):
        def timed(*args, **kwargs):
            t = time.perf_counter()
            out = fn(*args, **kwargs)
            if self.counting_since is not None:
                self.seconds[name] += time.perf_counter() - t
            return out
        return timed


def instrument(timer: StepTimer, warmup: int) -> None:
    """Wrap what a distillation step calls (module-level names the loop looks up at call time)."""
    d = distill_module
    d.empty_space_loss = timer.wrap("empty_space", d.empty_space_loss)
    d.free_space_loss = timer.wrap("free_space", d.free_space_loss)
    d.patch_dssim = timer.wrap("dssim", d.patch_dssim)
    d.PixelStore.sample_rays = timer.wrap("sample_rays", d.PixelStore.sample_rays)
    Student.render = timer.wrap("student_render", Student.render)
    for opt in (RowAdam, torch.optim.Adam):
        opt.step = timer.wrap("adam", opt.step)
        opt.zero_grad = timer.wrap("zero_grad", opt.zero_grad)
    torch.Tensor.backward = timer.wrap("backward", torch.Tensor.backward)
    load_teacher = d.load_teacher

    def loaded(*args, **kwargs):
        out = load_teacher(*args, **kwargs)
        out[0].render_rays = timer.wrap("teacher_render", out[0].render_rays)
        return out
    d.load_teacher = loaded
    run_steps = d.run_steps

    def counted_run_steps(out, dp, title, steps, start, seed, one_step, *args, **kwargs):
        def step_fn(step, gen):
            if step == start + warmup:
                timer.counting_since = time.perf_counter()
            return one_step(step, gen)
        return run_steps(out, dp, title, steps, start, seed, step_fn, *args, **kwargs)
    d.run_steps = counted_run_steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--teacher", required=True, help="a finished teacher run folder")
    ap.add_argument("--config", help="a student's config.json or a distillation config (default: the cpu-small preset)")
    ap.add_argument("--steps", type=int, default=16, help="steps to run, warm-up included")
    ap.add_argument("--warmup", type=int, default=3, help="first steps not counted")
    ap.add_argument("--dense-baseline", action="store_true",
                    help="also run the steps under dense Adam and report the speed-up of the row-wise one")
    args = ap.parse_args()
    if args.steps <= args.warmup:
        ap.error("--steps must exceed --warmup")
    cfg = config_from_file(args.config) if args.config else distill_preset("cpu-small")
    cfg = replace(cfg, val_every=10 ** 9, checkpoint_every=10 ** 9, tensorboard=False)
    timer = StepTimer()
    instrument(timer, args.warmup)
    result = {"benchmark": "distill_profile", "teacher": args.teacher, "config": args.config,
              "steps_counted": args.steps - args.warmup, "torch_threads": torch.get_num_threads(),
              **profile(timer, args.teacher, cfg, args.steps, args.warmup)}
    if args.dense_baseline:
        row_masks, row_adam = Student.row_masks, distill_module.RowAdam
        Student.row_masks = lambda self: {}  # the lookup records no rows
        distill_module.RowAdam = lambda groups, row_masks, **kw: torch.optim.Adam(groups, fused=True, **kw)
        try:
            result["dense_baseline"] = profile(timer, args.teacher, cfg, args.steps, args.warmup)
        finally:
            Student.row_masks, distill_module.RowAdam = row_masks, row_adam
        result["speedup_over_dense"] = round(result["dense_baseline"]["seconds_per_step"]
                                             / result["seconds_per_step"], 3)
    print(json.dumps(result, indent=1))


def profile(timer: StepTimer, teacher: str, cfg, steps: int, warmup: int) -> dict:
    """Seconds a step and each part's share over ``steps - warmup`` steps of a scratch distillation."""
    timer.seconds.clear()
    timer.counting_since = None
    scratch = tempfile.mkdtemp(prefix="distill_profile_")
    try:
        distill_module.distill(teacher, f"{scratch}/student", cfg, stop_at=steps)
        total = time.perf_counter() - timer.counting_since
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    counted = steps - warmup
    parts = {name: {"seconds_per_step": round(s / counted, 4), "share": round(s / total, 3)}
             for name, s in sorted(timer.seconds.items(), key=lambda kv: -kv[1])}
    return {"seconds_per_step": round(total / counted, 4), "parts": parts}


if __name__ == "__main__":
    main()
