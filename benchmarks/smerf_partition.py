"""SMERF's camera partition on the two-room synthetic scene: one teacher, students with K = 1, 2 (, 3), each baked.

Prints, per K: alive submodels, student and baked test PSNR / SSIM / LPIPS, ``disk_bytes`` and
``peak_submodel_bytes`` (the whole scene against the largest submodel a viewer holds at once; also without the
deferred-MLP file, which holds the MLPs of every submodel and which each folder repeats), times. Then, for the
test cameras nearest a boundary between two alive cells, the camera rendered by its home submodel and by the
neighbour across that boundary (:mod:`nerfbake.smerf.seams`), from the student and from the baked assets.

Every K uses the same per-submodel resolution (``--sparse``, ``--triplane``), so a larger K buys more submodels,
not bigger ones.

    python benchmarks/smerf_partition.py [--size 128] [--views 80] [--spp 64] [--teacher-steps 2000]
                                         [--steps 2000] [--ks 1,2] [--boundary-views 3] [--work DIR]
    -> one JSON object on stdout; per boundary camera a PNG row in WORK: teacher | home | neighbour | baked home |
       baked neighbour
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from nerfbake.data.formats import load_dataset
from nerfbake.data.synth import SynthConfig, render_dataset
from nerfbake.smerf.assets import SceneAssets
from nerfbake.smerf.bake import bake_student
from nerfbake.smerf.distill import distill
from nerfbake.smerf.run import distill_preset, load_student
from nerfbake.smerf.evaluate import asset_summary, evaluate_assets, evaluate_student
from nerfbake.smerf.seams import boundary_cameras, compare_across_boundary
from nerfbake.smerf.student import StudentConfig
from nerfbake.teacher.evaluate import evaluate_teacher
from nerfbake.teacher.presets import preset
from nerfbake.teacher.run import load_teacher
from nerfbake.teacher.train import train_teacher
from nerfbake.train.loop import git_revision

QUALITY = ("psnr", "ssim", "lpips_vgg", "ms_per_frame")


def finished_with(folder: Path, section: str, **values) -> bool:
    """Whether ``folder`` holds a finished run whose config ``section`` has these values (else it is redone)."""
    path = folder / "config.json"
    if not path.is_file():
        return False
    meta = json.loads(path.read_text())
    cfg = meta.get(section, {})
    return bool(meta.get("complete")) and all(cfg.get(k) == v for k, v in values.items())


def run_seconds(folder: Path) -> float:
    """How long a run took when it ran (so a reused run reports its own time): the folder's recorded ``seconds``,
    else the span of its metrics log (teachers)."""
    meta = json.loads((folder / "config.json").read_text())
    if "seconds" in meta:
        return round(float(meta["seconds"]), 1)
    times = [json.loads(line)["time"] for line in (folder / "metrics.jsonl").open() if '"time"' in line]
    return round(times[-1] - times[0], 1)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--views", type=int, default=80, help="training views (val/test add a quarter each)")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--teacher-steps", type=int, default=2000)
    ap.add_argument("--steps", type=int, default=2000, help="distillation steps for every K")
    ap.add_argument("--sparse", type=int, default=128, help="sparse grid S per submodel, every K")
    ap.add_argument("--triplane", type=int, default=512, help="triplane T per submodel, every K")
    ap.add_argument("--ks", default="1,2")
    ap.add_argument("--boundary-views", type=int, default=3)
    ap.add_argument("--work", help="keep everything here and reuse what is finished (default: a temporary folder)")
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="smerf-partition-"))
    work.mkdir(parents=True, exist_ok=True)
    scene = work / "scene"
    if not (scene / "transforms_test.json").is_file():
        render_dataset(SynthConfig("rooms", args.size, args.size, views=args.views, spp=args.spp, seed=0), scene)
    teacher_dir = work / "teacher"
    if not finished_with(teacher_dir, "train", steps=args.teacher_steps):
        shutil.rmtree(teacher_dir, ignore_errors=True)
        train_teacher(scene, teacher_dir, replace(preset("hash", "cpu-small"), steps=args.teacher_steps))
    teacher_eval = evaluate_teacher(teacher_dir, "test", write_images=False)
    result = {"git": git_revision(), "scene": f"rooms {args.size}x{args.size}, {args.views} training views, spp {args.spp}",
              "teacher": {"steps": args.teacher_steps, "seconds": run_seconds(teacher_dir),
                          **{k: round(teacher_eval[k], 4) for k in ("psnr", "ssim", "lpips_vgg")}},
              "student_config": {"steps": args.steps, "sparse_resolution": args.sparse, "triplane_resolution": args.triplane},
              "per_k": {}, "boundary": {}}
    teacher = load_teacher(teacher_dir)[0].eval()
    ds = load_dataset(scene)
    test_origins = np.stack([ds.frames[i].camera.origin for i in ds.split("test")])
    for k in (int(v) for v in args.ks.split(",")):
        student_dir, assets = work / f"student_k{k}", work / f"assets_k{k}"
        cfg = distill_preset("cpu-small", k)
        cfg = replace(cfg, steps=args.steps, student=StudentConfig(sparse_resolution=args.sparse,
                                                                     triplane_resolution=args.triplane))
        if not finished_with(student_dir, "distill", steps=args.steps, student=asdict(cfg.student)):
            shutil.rmtree(student_dir, ignore_errors=True)
            shutil.rmtree(assets, ignore_errors=True)
            distill(teacher_dir, student_dir, cfg)
        if not (assets / "bake.json").is_file():
            bake_student(student_dir, assets)
        s_eval = evaluate_student(student_dir, write_images=False)
        b_eval = evaluate_assets(assets, write_images=False)
        sizes = asset_summary(assets)
        result["per_k"][k] = {
            "num_submodels": b_eval["num_submodels"], "distill_seconds": run_seconds(student_dir),
            "bake_seconds": round(json.loads((assets / "bake.json").read_text())["seconds"], 1),
            "disk_bytes": b_eval["disk_bytes"],
            "peak_submodel_bytes": b_eval["peak_submodel_bytes"],
            "peak_submodel_grid_bytes": sizes["peak_submodel_grid_bytes"], "deferred_mlp_bytes": sizes["deferred_mlp_bytes"],
            "student": {m: round(s_eval[m], 4) for m in QUALITY}, "baked": {m: round(b_eval[m], 4) for m in QUALITY},
            "format_problems": b_eval["format_problems"]}
        if k > 1:
            student = load_student(student_dir)[0]
            pairs = boundary_cameras(student.partition, test_origins, args.boundary_views)
            result["boundary"][k] = compare_across_boundary(student, teacher, ds, "test", pairs, SceneAssets.open(assets),
                                                            image_dir=work)
    ks = sorted(result["per_k"])
    disks = [result["per_k"][k]["disk_bytes"] for k in ks]
    peaks = [result["per_k"][k]["peak_submodel_bytes"] for k in ks]
    grids = [result["per_k"][k]["peak_submodel_grid_bytes"] for k in ks]
    result["checks"] = {
        "disk_grows_with_k": all(a < b for a, b in zip(disks, disks[1:])),
        "peak_submodel_over_k1_peak": [round(p / peaks[0], 3) for p in peaks],
        "peak_submodel_grid_over_k1": [round(g / grids[0], 3) for g in grids],
        "boundary_seamless": all(q["seamless"] for qs in result["boundary"].values() for q in qs),
    }
    print(json.dumps(result, indent=1))
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
