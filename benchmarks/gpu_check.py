"""The GPU paths in one run of about ten minutes on one CUDA GPU, one JSON summary on stdout (issue 25):

1. the kernel tests on CUDA (every Warp kernel against its torch twin, forward and backward);
2. the hash ``cpu-small`` teacher on lego_400, time-boxed, then its held-out PSNR on 5 test views;
3. the NeRF-SH ``paper`` preset on lego_400 for a fixed number of minutes, with its training-PSNR curve and held-out
   PSNR (the preset that stalled at 12.6-13.3 dB on an H100 before the learning-rate warm-up);
4. ``benchmarks/octree_render.py`` at 400x400 and 800x800 on a tree built from (2) (PlenOctrees: 167.68 FPS on a
   V100 at 800x800);
5. ``nerfbake view --benchmark --gpu`` on the shared baked SMERF scene, in chromium on the GPU.

Without CUDA every part is reported as skipped with the reason, and the script exits 0 (the CPU paths have their own
tests and benchmarks). Training parts are stopped with SIGINT when their minutes are up, which the trainers turn
into a checkpoint and a clean exit, so what they learnt in the time is evaluated.

    bash benchmarks/gpu_check.sh [--out outputs/gpu_check] [--data ../shared/data/lego_400] [--minutes-nerf-sh 5]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SHARED = ROOT.parent / "shared" / "data"
PAPER_V100_FPS_800 = 167.68  # PlenOctrees Table 1, NeRF-synthetic at 800x800


def run_timeboxed(cmd: list[str], log: Path, budget_s: float, grace_s: float = 60.0) -> dict:
    """Run ``cmd`` (output to ``log``); after ``budget_s`` send SIGINT (trainers checkpoint and stop), after a further
    ``grace_s`` kill it. Returns {returncode, seconds, interrupted, stdout} (stdout: what it printed)."""
    t = time.perf_counter()
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, cwd=ROOT, text=True)
        interrupted = False
        try:
            out, _ = proc.communicate(timeout=budget_s)
        except subprocess.TimeoutExpired:
            interrupted = True
            proc.send_signal(signal.SIGINT)
            try:
                out, _ = proc.communicate(timeout=grace_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, _ = proc.communicate()
    return {"returncode": proc.returncode, "seconds": round(time.perf_counter() - t, 1), "interrupted": interrupted,
            "stdout": out}


def last_json(text: str) -> dict | None:
    """The JSON object a command printed last (commands print one object, possibly after progress lines)."""
    start = text.find("{")
    while start >= 0:
        try:
            return json.loads(text[start:])
        except ValueError:
            start = text.find("{", start + 1)
    return None


def psnr_curve(run: Path, points: int = 12) -> list[list[float]]:
    """[step, training PSNR, seconds since the first record] at about ``points`` evenly spaced records."""
    from nerfbake.train.loop import training_curve

    recs = training_curve(run, "psnr", points)
    return [[r["step"], round(r["psnr"], 2), round(r["time"] - recs[0]["time"], 1)] for r in recs]


def teacher_part(nb: list[str], data: Path, run: Path, log_dir: Path, budget_s: float, args: list[str],
                 eval_views: int = 5) -> dict:
    """Train a teacher for at most ``budget_s`` (resuming nothing), then evaluate ``eval_views`` test views."""
    train = run_timeboxed([*nb, "teacher", "train", "--data", str(data), "--out", str(run), *args],
                          log_dir / f"{run.name}_train.log", budget_s)
    res = {"train_seconds": train["seconds"], "stopped_by_time": train["interrupted"]}
    if not (run / "checkpoint.pt").is_file():
        return {**res, "status": "failed", "reason": f"training left no checkpoint; see {log_dir / (run.name + '_train.log')}"}
    res["curve_step_psnr_seconds"] = psnr_curve(run)
    ev = run_timeboxed([*nb, "teacher", "eval", "--run", str(run), "--max-views", str(eval_views), "--json"],
                       log_dir / f"{run.name}_eval.log", 300)
    got = last_json(ev["stdout"]) if ev["returncode"] == 0 else None
    if got is None:
        return {**res, "status": "failed", "reason": f"teacher eval failed; see {log_dir / (run.name + '_eval.log')}"}
    return {**res, "status": "ok", "test_psnr": got.get("psnr"), "test_ssim": got.get("ssim")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="outputs/gpu_check")
    ap.add_argument("--data", default=str(SHARED / "lego_400"))
    ap.add_argument("--smerf-assets", default=str(SHARED / "smerf_tiny"))
    ap.add_argument("--minutes-hash", type=float, default=1.5)
    ap.add_argument("--minutes-nerf-sh", type=float, default=5.0)
    ap.add_argument("--downscale", type=float, default=1.0, help="teacher image downscale (the CPU check uses 4)")
    ap.add_argument("--eval-views", type=int, default=5)
    ap.add_argument("--octree-grid", type=int,
                    help="grid of the tree built for the octree part (default: the cpu-small preset's; 128 with --cpu, "
                         "whose 512^3 build alone outlasts the part's 3 minutes on 2 cores)")
    ap.add_argument("--cpu", action="store_true",
                    help="run every part on the CPU anyway, to check this script (slow; its figures mean nothing)")
    args = ap.parse_args()
    import torch

    out = Path(args.out).resolve()
    py = sys.executable
    nb = [py, "-m", "nerfbake"]
    summary: dict = {"machine": {"processor": platform.processor() or platform.machine(), "cpus": os.cpu_count()},
                     "torch": torch.__version__, "cuda": torch.cuda.is_available()}
    parts = ("kernel_tests", "hash_teacher", "nerf_sh_paper", "octree_render", "viewer_gpu")
    if not torch.cuda.is_available() and not args.cpu:
        reason = "no CUDA device (torch.cuda.is_available() is False): the GPU paths were not run"
        print(f"gpu_check: {reason}", file=sys.stderr)
        summary.update({p: {"status": "skipped", "reason": reason} for p in parts})
        print(json.dumps(summary, indent=2))
        return
    out.mkdir(parents=True, exist_ok=True)
    summary["gpu"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none (--cpu)"
    t_all = time.perf_counter()

    r = run_timeboxed([py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/kernels",
                       *(["-k", "cuda"] if torch.cuda.is_available() else [])],
                      out / "kernel_tests.log", 180)
    summary["kernel_tests"] = {"status": "ok" if r["returncode"] == 0 else "failed", "seconds": r["seconds"],
                               "pytest": (r["stdout"].strip().splitlines() or ["(no output)"])[-1]}

    ds = ["--downscale", str(args.downscale)]
    hash_run = out / "hash_teacher"
    summary["hash_teacher"] = teacher_part(nb, Path(args.data), hash_run, out, 60 * args.minutes_hash,
                                           ["--preset", "cpu-small", "--steps", "3000", *ds], args.eval_views)
    summary["nerf_sh_paper"] = teacher_part(nb, Path(args.data), out / "nerf_sh_paper", out, 60 * args.minutes_nerf_sh,
                                            ["--field", "nerf-sh", "--preset", "paper", *ds], args.eval_views)

    if summary["hash_teacher"]["status"] == "ok":
        tree = out / "lego_tree.npz"
        grid = args.octree_grid or (128 if not torch.cuda.is_available() else None)
        b = run_timeboxed([*nb, "octree", "build", "--teacher", str(hash_run), "--out", str(tree), "--preset", "cpu-small",
                           *(["--grid", str(grid)] if grid else [])], out / "octree_build.log", 180)
        if b["returncode"] == 0 and tree.is_file():
            r = run_timeboxed([py, str(HERE / "octree_render.py"), "--tree", str(tree), "--data", args.data],
                              out / "octree_render.log", 180)
            got = last_json(r["stdout"]) if r["returncode"] == 0 else None
            summary["octree_render"] = ({"status": "failed", "reason": "see octree_render.log"} if got is None else
                                        {"status": "ok", "build_seconds": b["seconds"], "grid": grid or "preset",
                                         **{k: got[k] for k in got if
                                         k.startswith(("fps_", "ms_per_frame_", "num_leaves", "kernel_speedup"))},
                                         "paper_v100_fps_800": PAPER_V100_FPS_800})
        else:
            summary["octree_render"] = {"status": "failed", "reason": "octree build failed; see octree_build.log"}
    else:
        summary["octree_render"] = {"status": "skipped", "reason": "no hash teacher to build a tree from"}

    gpu_flag = [] if args.cpu else ["--gpu"]
    r = run_timeboxed([*nb, "view", args.smerf_assets, "--benchmark", *gpu_flag, "--json"], out / "viewer_gpu.log", 180)
    got = last_json(r["stdout"]) if r["returncode"] == 0 else None
    summary["viewer_gpu"] = ({"status": "failed", "reason": "see viewer_gpu.log"} if got is None else
                             {"status": "ok", "seconds": r["seconds"], "renderer": got.get("renderer"),
                              "timer": got.get("timer"),  # gpu: ms_per_frame_* are timer-query GPU times
                              **{k: v for k, v in got.items() if k.startswith(("ms_per_frame", "wall_ms_per_frame"))}})
    summary["seconds"] = round(time.perf_counter() - t_all, 1)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
