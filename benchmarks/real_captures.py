"""Real captures end to end: photos or a phone clip -> ``nerfbake process`` (where the scene has no poses) ->
``nerfbake pipeline`` at the CPU preset -> one JSON object with registration, per-method quality on held-out views,
stage times, peak memory and disk, plus one picture per scene (ground truth | teacher | octree | SMERF baked).

    python benchmarks/real_captures.py --work outputs/real [--scenes bonsai,fern,fox,phone]
        [--bonsai-images 100] [--bonsai-matcher exhaustive] [--downscale bonsai=2] [--teacher-steps N]
        [--distill-steps N] [--eval-views 25]
        [--pipeline-args '--octree-grid 128 ...']

Scenes (``../shared/data``): bonsai_800 (292 photos, no poses; every 8th photo held out), fern (LLFF images_8),
fox (instant-ngp transforms.json), phone (phone_video/beer.mp4 through ``process --video``). Finished work in
``--work`` is reused (SfM outputs, pipeline stages), so a long run can be resumed or extended scene by scene.
"""
from __future__ import annotations

import argparse
import json
import resource
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def run(cmd: list[str], log: Path) -> float:
    """Run a nerfbake command, its output in ``log``; seconds taken. Fails loudly with the log's tail."""
    t = time.perf_counter()
    with log.open("a") as f:
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        tail = log.read_text()[-2000:]
        sys.exit(f"{' '.join(cmd)} failed ({proc.returncode}); the end of {log}:\n{tail}")
    return time.perf_counter() - t


def option_mismatches(report: dict, source: list[str]) -> list[str]:
    """Where a finished ``process_report.json`` was made with other options than ``source`` asks for (its matcher,
    or how many photos it took under ``--max-images``)."""
    asked = dict(zip(source[::2], source[1::2]))
    done = report.get("options", {})
    wrong = []
    if "--matcher" in asked and report.get("matcher") != asked["--matcher"]:
        wrong.append(f"matcher {report.get('matcher')} (asked {asked['--matcher']})")
    if "--max-images" in asked:
        n, had = int(asked["--max-images"]), done.get("max_images")
        took_all_within = had is None and report.get("num_images", n + 1) <= n
        if had != n and not took_all_within:
            wrong.append(f"{report.get('num_images')} photos (asked --max-images {n})")
    return wrong


def processed(name: str, source: list[str], work: Path, log: Path) -> tuple[Path, dict]:
    """The dataset ``nerfbake process`` makes from ``source`` (reused when already there and made with the same
    options) and its report."""
    out = work / f"{name}_data"
    report_path = out / "process_report.json"
    if report_path.is_file():
        wrong = option_mismatches(json.loads(report_path.read_text()), source)
        if wrong:  # structure from motion can take most of an hour: never delete a finished one silently
            sys.exit(f"{out} was processed with other options: {'; '.join(wrong)}. Delete it to process again, "
                     "or pass another --work")
    else:
        if out.exists():
            shutil.rmtree(out)
        run([sys.executable, "-m", "nerfbake", "process", *source, "--out", str(out)], log)
    report = json.loads(report_path.read_text())
    return out, {k: report[k] for k in ("num_images", "num_registered", "mean_reprojection_error_px", "num_points3D",
                                        "matcher", "timings_s") if k in report}


def scene_sources(args) -> dict[str, dict]:
    return {
        "bonsai": {"process": ["--images", str(SHARED / "bonsai_800" / "images"), "--max-images", str(args.bonsai_images),
                               "--matcher", args.bonsai_matcher]},
        "fern": {"data": SHARED / "fern"},
        "fox": {"data": SHARED / "fox"},
        "phone": {"process": ["--video", str(SHARED / "phone_video" / "beer.mp4")]},
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", default="outputs/real_captures")
    ap.add_argument("--scenes", default="bonsai,fern,fox,phone")
    ap.add_argument("--bonsai-images", type=int, default=100,
                    help="an even subset of bonsai_800's 292 photos (SfM time grows fast with it: 100 took ~6 min)")
    ap.add_argument("--bonsai-matcher", default="exhaustive", choices=("exhaustive", "sequential"),
                    help="SfM matching for bonsai (sequential: each photo with its capture-order neighbours, for all 292)")
    ap.add_argument("--downscale", default="bonsai=2", help="per-scene downscale, e.g. bonsai=2,fox=4 (others: automatic)")
    ap.add_argument("--teacher-steps", type=int)
    ap.add_argument("--distill-steps", type=int)
    ap.add_argument("--eval-views", type=int, default=25)
    ap.add_argument("--pipeline-args", default="", help="more nerfbake pipeline options for every scene, e.g. "
                    "'--octree-grid 128 --octree-epochs 1 --bake-stride 4'")
    args = ap.parse_args()
    work = Path(args.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    downscales = dict(kv.split("=") for kv in args.downscale.split(",") if kv)
    sources = scene_sources(args)
    result = {"benchmark": "real_captures", "work": str(work), "scenes": {}}
    for name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        if name not in sources:
            sys.exit(f"unknown scene {name!r}; choose from {', '.join(sources)}")
        log = work / f"{name}.log"
        entry: dict = {}
        src = sources[name]
        if "process" in src:
            t = time.perf_counter()
            data, entry["registration"] = processed(name, src["process"], work, log)
            entry["registration"]["seconds_this_run"] = time.perf_counter() - t
        else:
            data = src["data"]
        run_dir = work / name
        cmd = [sys.executable, "-m", "nerfbake", "pipeline", "--data", str(data), "--out", str(run_dir),
               "--eval-views", str(args.eval_views)]
        if name in downscales:
            cmd += ["--downscale", downscales[name]]
        if args.teacher_steps:
            cmd += ["--teacher-steps", str(args.teacher_steps)]
        if args.distill_steps:
            cmd += ["--distill-steps", str(args.distill_steps)]
        cmd += shlex.split(args.pipeline_args)
        entry["pipeline_seconds_this_run"] = run(cmd, log)
        results = json.loads((run_dir / "results.json").read_text())
        entry["downscale"] = results["config"].get("downscale")
        entry["downscale_why"] = results["config"].get("downscale_why")
        entry["methods"] = [{k: r.get(k) for k in ("method", "psnr", "ssim", "lpips", "lpips_net", "num_views",
                                                   "ms_per_frame", "disk_bytes", "memory_bytes")} for r in results["methods"]]
        entry["stage_seconds"] = {k: round(v["seconds"], 1) for k, v in results["stages"].items()}
        entry["skipped"] = {k: v["skipped"] for k, v in results["stages"].items() if v.get("skipped")}
        entry["disk_bytes"] = folder_bytes(run_dir)
        entry["picture"] = str(run_dir / "report" / "strip.png")
        result["scenes"][name] = entry
        print(json.dumps({name: entry}), file=sys.stderr, flush=True)
    result["peak_rss_bytes_children"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
