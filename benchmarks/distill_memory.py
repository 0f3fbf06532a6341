"""RSS over the steps of a SMERF distillation, with nerfbake's two memory guards on or off, in a fresh process.

The guards: glibc's heap trimmed after every training step (``train/loop.HEAP_TRIM``) and oneDNN's primitive cache
capped at 64 shapes (``ONEDNN_PRIMITIVE_CACHE_CAPACITY``, set in ``nerfbake/__init__.py``). Run it once per mode,
nothing else on the machine, and compare ``peak_rss_bytes`` and the timeline's slope:

    python benchmarks/distill_memory.py --teacher WORK/teacher [--k 2] [--steps 150] [--mode both|trim|cap|none]

``WORK/teacher`` is a finished teacher, e.g. ``benchmarks/smerf_partition.py --scene house --work WORK``'s (the
house's grid-marching teacher is where RSS climbed; S = 32, T = 128 students as in that benchmark).
    -> one JSON object on stdout: peak RSS, seconds, the training rays/s logged every 25 steps, (seconds, RSS) every 15 s
"""
from __future__ import annotations

import argparse
import os
import sys

ap = argparse.ArgumentParser()
ap.add_argument("--teacher", required=True)
ap.add_argument("--k", type=int, default=2)
ap.add_argument("--steps", type=int, default=150)
ap.add_argument("--mode", choices=("both", "trim", "cap", "none"), default="both")
args = ap.parse_args()
if args.mode in ("trim", "none") and "ONEDNN_PRIMITIVE_CACHE_CAPACITY" not in os.environ:
    # oneDNN reads it at its first matmul; re-run with the library's default 1024 before anything imports nerfbake
    os.environ["ONEDNN_PRIMITIVE_CACHE_CAPACITY"] = "1024"
    os.execv(sys.executable, [sys.executable, *sys.argv])

import json  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

from nerfbake.smerf.distill import distill  # noqa: E402
from nerfbake.smerf.run import distill_preset  # noqa: E402
from nerfbake.smerf.student import StudentConfig  # noqa: E402
from nerfbake.train import loop  # noqa: E402


def main() -> None:
    if args.mode in ("cap", "none"):
        loop.HEAP_TRIM = None
    timeline: list[tuple[float, int]] = []

    def watch() -> None:
        page = os.sysconf("SC_PAGE_SIZE")
        while True:
            timeline.append((time.time(), int(Path("/proc/self/statm").read_text().split()[1]) * page))
            time.sleep(1)

    threading.Thread(target=watch, daemon=True).start()
    cfg = replace(distill_preset("cpu-small", args.k), steps=1000, warm_start=True, val_every=100_000,
                  student=StudentConfig(sparse_resolution=32, triplane_resolution=128))
    out = Path(tempfile.mkdtemp(prefix="distill-memory-")) / "student"
    t0 = time.time()
    try:
        distill(args.teacher, out, cfg, stop_at=args.steps)
        rates = [round(json.loads(line)["rays_per_s"]) for line in (out / "metrics.jsonl").open() if "rays_per_s" in line]
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)
    print(json.dumps({
        "mode": args.mode, "k": args.k, "steps": args.steps,
        "onednn_primitive_cache_capacity": os.environ.get("ONEDNN_PRIMITIVE_CACHE_CAPACITY"),
        "heap_trim": loop.HEAP_TRIM is not None,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "seconds": round(time.time() - t0, 1), "rays_per_s": rates,
        "rss_timeline": [(round(t - t0), r) for t, r in timeline[::15]]}))


if __name__ == "__main__":
    main()
