"""Every benchmark in one go, one JSON summary: teacher training/rendering rays/s per field, a short pipeline on the
built-in scene (build and bake times, each stage's peak memory), the octree and baked-SMERF renderers' rays/s and
ms/frame on its outputs, the browser's ms/frame for both scene kinds, and the SfM pose accuracy. ~10-15 minutes on
2 CPU cores; each script runs in its own process so its peak resident memory is its own. Left to be run on their
own, being long: the teacher comparison of ``process_quality.py --teacher-steps`` and ``smerf_partition.py``.

    python benchmarks/run_all.py [--out outputs/bench] [--data ../shared/data/lego_400]
    -> writes OUT/summary.json and prints it
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from nerfbake import atomic

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def run(cmd: list[str], log: Path) -> tuple[dict | None, float, float]:
    """(JSON printed on stdout or None, seconds, peak resident MB of the process)."""
    t = time.perf_counter()
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, cwd=ROOT, text=True)
        out = proc.stdout.read()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - t
    peak_mb = usage.ru_maxrss / 1024  # kilobytes on Linux
    if proc.returncode != 0:
        print(f"FAILED ({proc.returncode}): {' '.join(cmd)}; see {log}", file=sys.stderr)
        return None, seconds, peak_mb
    try:
        start = out.index("{")
        return json.loads(out[start:]), seconds, peak_mb
    except ValueError:  # a command that prints no JSON (synth, pipeline): its success is the result
        return {"returncode": 0}, seconds, peak_mb


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="outputs/bench")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "lego_400"))
    args = ap.parse_args()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    nb = [py, "-m", "nerfbake"]
    summary: dict = {"machine": {"processor": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
                                 "python": platform.python_version()}}
    from nerfbake.train.loop import default_device, git_revision

    summary.update(git=git_revision(), device=str(default_device()))

    def step(name, cmd):
        print(f"[run_all] {name}: {' '.join(str(c) for c in cmd)}", file=sys.stderr, flush=True)
        res, sec, mb = run([str(c) for c in cmd], out / f"{name}.log")
        summary[name] = {"seconds": sec, "peak_rss_mb": mb, "result": res}
        atomic.write_json(out / "summary.json", summary)
        return res

    # 1. teacher fields: training and rendering rays/s, the Warp hash kernel against torch
    step("teacher_speed", [py, HERE / "teacher_speed.py", "--data", args.data, "--steps", 10, "--warmup", 60])
    # 2. the pipeline on the built-in scene: every stage's time, outputs for the renderer benchmarks
    run_dir = out / "pipeline"
    scene = out / "scene"
    if not (scene / "transforms_train.json").is_file():
        step("synth", nb + ["synth", "--scene", "objects", "--out", scene, "--width", 128, "--height", 128, "--views", 40,
                            "--spp", 16])
    step("pipeline", nb + ["pipeline", "--data", scene, "--out", run_dir, "--eval-views", 4, "--teacher-steps", 800,
                           "--distill-steps", 400, "--octree-grid", 128])
    stages = {}
    for rec in sorted((run_dir / "stages").glob("*.json")):
        stages[rec.stem] = json.loads(rec.read_text())["seconds"]
    summary["stage_seconds"] = stages
    tree, assets = run_dir / "octree" / "tree_opt.npz", run_dir / "smerf" / "assets"
    # 3. renderers on those outputs (Python/Warp)
    step("octree_render", [py, HERE / "octree_render.py", "--tree", tree, "--data", scene, "--views", 2])
    step("smerf_render", [py, HERE / "smerf_render.py", "--assets", assets, "--width", 400, "--height", 300, "--repeats", 2])
    # 4. the browser (headless chromium; SwiftShader unless a GPU is there)
    browser = ["--benchmark", "--frames", 2, "--warmup", 1, "--max-views", 2, "--json"]
    step("browser_octree", nb + ["view", run_dir / "octree" / "tree_c.npz", *browser])
    step("browser_smerf", nb + ["view", assets, *browser])
    # 5. SfM pose accuracy on synthetic views
    step("process_quality", [py, HERE / "process_quality.py", "--size", 160, "--views", 24, "--spp", 8])

    def get(name, *keys):
        v = (summary.get(name) or {}).get("result") or {}
        for k in keys:
            v = v.get(k, {}) if isinstance(v, dict) else {}
        return v if v != {} else None

    summary["figures"] = {
        "train_rays_per_s_hash": get("teacher_speed", "hash", "train_rays_per_s"),
        "train_rays_per_s_nerf_sh": get("teacher_speed", "nerf_sh", "train_rays_per_s"),
        "render_rays_per_s_hash": get("teacher_speed", "hash", "render_rays_per_s"),
        "render_rays_per_s_nerf_sh": get("teacher_speed", "nerf_sh", "render_rays_per_s"),
        "octree_rays_per_s_400": get("octree_render", "rays_per_s_400"),
        "octree_ms_per_frame_400": get("octree_render", "ms_per_frame_400"),
        "octree_ms_per_frame_800": get("octree_render", "ms_per_frame_800"),
        "smerf_rays_per_s": get("smerf_render", "rays_per_s"),
        "smerf_ms_per_frame": get("smerf_render", "ms_per_frame"),
        "browser_octree_ms_per_frame_512": get("browser_octree", "ms_per_frame_512x512"),
        "browser_octree_ms_per_frame_1280x720": get("browser_octree", "ms_per_frame_1280x720"),
        "browser_smerf_ms_per_frame_512": get("browser_smerf", "ms_per_frame_512x512"),
        "browser_smerf_ms_per_frame_1280x720": get("browser_smerf", "ms_per_frame_1280x720"),
        "browser_renderer": get("browser_smerf", "renderer"),
        "octree_build_seconds": stages.get("octree_build"),
        "bake_seconds": stages.get("bake"),
        "teacher_train_seconds": stages.get("teacher"),
        "distill_seconds": stages.get("distill"),
        "peak_rss_mb": {k: v["peak_rss_mb"] for k, v in summary.items() if isinstance(v, dict) and "peak_rss_mb" in v},
        "total_seconds": sum(v["seconds"] for v in summary.values() if isinstance(v, dict) and "seconds" in v),
    }
    atomic.write_json(out / "summary.json", summary)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
