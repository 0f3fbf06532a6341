"""What subnormal floats cost a trainer's Adam step on the CPU, and what ``flush_denormals`` buys back.

A SMERF student's grid cells that stop getting gradients keep Adam moments that decay by β each step; after ~800
steps a share of them is subnormal (8 % of a lego student's sparse-grid first moments at step 2300), and x86
arithmetic on subnormals is an order of magnitude slower. Each mode runs in its own process (the mode is per thread
and torch's threads copy it when they start), on a fused Adam step over the same decayed state:

    python benchmarks/subnormal_floats.py [--values 20000000] [--share 0.1] [--steps 5]
    -> {"ms_per_step": {"subnormals": ..., "flushed": ...}, "speedup": ...}
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import torch

from nerfbake.kernels import flush_denormals


def adam_step_ms(values: int, share: float, steps: int) -> float:
    """Mean ms of a fused Adam step whose moments hold ``share`` subnormal values (the rest zero, as in a student's
    untouched cells) and whose gradient is zero."""
    param = torch.nn.Parameter(torch.zeros(values))
    opt = torch.optim.Adam([param], lr=1e-2, betas=(0.9, 0.99), eps=1e-15, fused=True)
    param.grad = torch.zeros(values)
    opt.step()
    subnormal = torch.rand(values, generator=torch.Generator().manual_seed(0)) < share
    for name in ("exp_avg", "exp_avg_sq"):
        opt.state[param][name].copy_(torch.where(subnormal, torch.tensor(1e-39), torch.tensor(0.0)))
    t = time.perf_counter()
    for _ in range(steps):
        opt.step()
    return (time.perf_counter() - t) / steps * 1000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--values", type=int, default=20_000_000)
    ap.add_argument("--share", type=float, default=0.1, help="share of the moments that are subnormal")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--mode", choices=("subnormals", "flushed"), help=argparse.SUPPRESS)  # one child process
    args = ap.parse_args()
    if args.mode:
        if args.mode == "flushed":
            flush_denormals()
        print(adam_step_ms(args.values, args.share, args.steps))
        return
    ms = {}
    for mode in ("subnormals", "flushed"):
        out = subprocess.run([sys.executable, __file__, "--mode", mode, "--values", str(args.values), "--share",
                              str(args.share), "--steps", str(args.steps)], capture_output=True, text=True, check=True)
        ms[mode] = round(float(out.stdout.strip().splitlines()[-1]), 1)
    print(json.dumps({"values": args.values, "subnormal_share": args.share, "ms_per_step": ms,
                      "speedup": round(ms["subnormals"] / ms["flushed"], 2), "torch_threads": torch.get_num_threads()},
                     indent=2))


if __name__ == "__main__":
    main()
