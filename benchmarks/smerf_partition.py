"""SMERF's camera partition on a synthetic indoor scene (``rooms``: two rooms; ``house``: seven rooms on two storeys):
one teacher, students with K = 1, 2 (, 3), each baked.

Prints, per K: alive submodels, student and baked test PSNR / SSIM / LPIPS, distillation and bake time and the peak
memory (RSS) of that K's distillation and bake, run in a child process of their own, ``disk_bytes`` and
``peak_submodel_bytes`` (the whole scene against the largest submodel a viewer holds at once; also without the
deferred-MLP file, which holds the MLPs of every submodel and which each folder repeats), times. Then, for the
test cameras nearest a boundary between two alive cells, the camera rendered by its home submodel and by the
neighbour across that boundary (:mod:`nerfbake.smerf.seams`), from the student and from the baked assets.

Every K uses the same per-submodel resolution (``--sparse``, ``--triplane``), so a larger K buys more submodels,
not bigger ones.

    python benchmarks/smerf_partition.py [--scene rooms|house] [--size 128] [--views N] [--spp 64]
                                         [--teacher-steps 2000] [--steps 2000] [--steps-per-submodel] [--k 1,2,3]
                                         [--seed 0] [--boundary-views 3] [--teacher-floor 25] [--walkthrough]
                                         [--work DIR]

``paired``: each K against the previous one view by view (mean PSNR difference ± its standard error), over every
test view and over the views the teacher renders at ``--teacher-floor`` dB or better: where the teacher fails, the
students' differences are noise.

``--walkthrough`` also flies the viewer along the test cameras (room after room) over each K's assets in headless
chromium: per-frame p50/p95/max, frames drawn while a submodel loaded, blank frames, the most submodels resident.
    -> one JSON object on stdout; per boundary camera a PNG row in WORK: teacher | home | neighbour | baked home |
       baked neighbour
"""
from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from nerfbake.data.formats import load_dataset
from nerfbake.data.synth import SynthConfig, render_dataset
from nerfbake.signals import terminate_like_ctrl_c
from nerfbake.smerf.assets import SceneAssets
from nerfbake.smerf.run import CHECKPOINT as STUDENT_CHECKPOINT, distill_preset, load_student
from nerfbake.smerf.evaluate import asset_summary, evaluate_assets, evaluate_student
from nerfbake.smerf.seams import boundary_cameras, compare_across_boundary
from nerfbake.smerf.student import StudentConfig
from nerfbake.teacher.evaluate import evaluate_teacher
from nerfbake.teacher.presets import preset
from nerfbake.teacher.run import CHECKPOINT as TEACHER_CHECKPOINT, load_teacher
from nerfbake.teacher.train import train_teacher
from nerfbake.train.loop import git_revision, run_complete

QUALITY = ("psnr", "ssim", "lpips_vgg", "ms_per_frame")


def run_state(folder: Path, section: str, checkpoint: str, **values) -> str | None:
    """What ``folder`` holds of a run whose config ``section`` has these values: "finished", "stopped" (it stopped
    at its ``checkpoint``, e.g. when a session ended: resuming it gives the run an uninterrupted one would, every step
    drawing its own randomness) or None (nothing, or a run of other values: it is redone)."""
    path = folder / "config.json"
    if not path.is_file():
        return None
    meta = json.loads(path.read_text())
    cfg = meta.get(section, {})
    if not all(cfg.get(k) == v for k, v in values.items()):
        return None
    if meta.get("complete"):
        return "finished"
    return "stopped" if (folder / checkpoint).is_file() else None


def run_seconds(folder: Path) -> float:
    """How long a run took when it ran (so a reused run reports its own time): the folder's recorded ``seconds``,
    else the span of its metrics log (teachers)."""
    meta = json.loads((folder / "config.json").read_text())
    if "seconds" in meta:
        return round(float(meta["seconds"]), 1)
    times = [json.loads(line)["time"] for line in (folder / "metrics.jsonl").open() if '"time"' in line]
    return round(times[-1] - times[0], 1)


CHILD = """
import json, resource, sys
from nerfbake.signals import terminate_like_ctrl_c
from nerfbake.smerf.bake import bake_student
from nerfbake.smerf.distill import distill
from nerfbake.smerf.run import config_from_dict
from nerfbake.train.loop import run_complete
terminate_like_ctrl_c()
teacher, student, assets, cfg, need_distill, resume, camera_radius = json.loads(sys.argv[1])
if need_distill:
    distill(teacher, student, config_from_dict(cfg), resume=resume)
    if not run_complete(student):
        sys.exit(0)  # stopped by a signal at a checkpoint: no bake of a half-trained student (the parent says so)
bake_student(student, assets, camera_radius=camera_radius)
print(json.dumps({"peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""


def interrupted(stage: str, folder: Path) -> SystemExit:
    """The exit for a run that a signal stopped before its last step: no figures come from a half-trained model."""
    return SystemExit(f"the {stage} in {folder} stopped before its last step (interrupted); rerun the benchmark to "
                      "run it again")


def per_view_psnr(evaluation: dict) -> dict[str, float]:
    return {view["name"]: view["psnr"] for view in evaluation["per_image"]}


def paired_differences(by_k: dict[int, dict[str, float]], teacher: dict[str, float], floor: float) -> dict:
    """Each K against the previous one, view by view: the mean PSNR difference, its standard error and the view
    count, over every test view and over those the teacher itself renders at ``floor`` dB or better. Where the
    teacher fails (the house's bedrooms: fog in front of the camera, 9-17 dB), every student copies the failure
    differently and those views' differences are noise that can outweigh the rest."""
    ks = sorted(by_k)
    ok = [n for n, v in teacher.items() if v >= floor]
    out = {"teacher_ok_psnr_by_k": [round(float(np.mean([by_k[k][n] for n in ok])), 4) if ok else None for k in ks]}
    for a, b in zip(ks, ks[1:]):
        entry = {}
        for subset, names in (("all", list(teacher)), ("teacher_ok", ok)):
            diff = np.array([by_k[b][n] - by_k[a][n] for n in names])
            se = round(float(diff.std(ddof=1) / np.sqrt(len(diff))), 3) if len(diff) > 1 else None
            entry[subset] = {"mean_db": round(float(diff.mean()), 3) if len(diff) else None,
                             "standard_error_db": se, "views": len(diff)}
        out[f"{b}-{a}"] = entry
    return out


def distill_and_bake(teacher_dir: Path, student_dir: Path, assets: Path, cfg, need_distill: bool, resume: bool,
                     camera_radius: float) -> int:
    """Distil (unless finished; ``resume``: from its checkpoint) and bake in a child process; its peak RSS in bytes
    (this K's alone)."""
    arg = json.dumps([str(teacher_dir), str(student_dir), str(assets), asdict(cfg), need_distill, resume,
                      camera_radius])
    proc = subprocess.Popen([sys.executable, "-c", CHILD, arg], stdout=subprocess.PIPE, text=True)
    try:
        stdout, _ = proc.communicate()
    except BaseException:  # Ctrl-C or SIGTERM here: stop the child too (its trainer saves a checkpoint first)
        proc.terminate()
        proc.wait()
        raise
    if proc.returncode != 0:
        raise SystemExit(f"distill/bake of {student_dir} failed (exit {proc.returncode})")
    if not run_complete(student_dir):  # stopped by a signal
        raise interrupted("distillation", student_dir)
    return int(json.loads(stdout.strip().splitlines()[-1])["peak_rss_bytes"])


def main() -> None:
    terminate_like_ctrl_c()  # a killed benchmark stops its distillation child too
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", choices=("rooms", "house"), default="rooms")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--views", type=int, help="training views (val/test add a quarter each; default: 80 for rooms, "
                    "280 for the house, 40 a room: with 80 its teacher scored 18.86 dB on the walk, with 280 26.30)")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--teacher-steps", type=int, default=2000)
    ap.add_argument("--steps", type=int, default=2000, help="distillation steps for every K")
    ap.add_argument("--steps-per-submodel", action="store_true", help="--steps for every alive submodel (the "
                    "distillation's --steps-per-submodel) rather than shared by them")
    ap.add_argument("--sparse", type=int, default=128, help="sparse grid S per submodel, every K")
    ap.add_argument("--triplane", type=int, default=512, help="triplane T per submodel, every K")
    ap.add_argument("--mlp-grid", type=int, default=StudentConfig.mlp_grid, help="the deferred-MLP lattice P for "
                    "every K (default: one MLP per submodel, the CPU preset's; 5, the authors', compares with the "
                    "K > 1 figures from before that default)")
    ap.add_argument("--k", "--ks", dest="ks", default="1,2", help="the K values, comma-separated")
    ap.add_argument("--walkthrough", action="store_true", help="also fly the viewer along the test cameras per K")
    ap.add_argument("--warm-start", choices=("on", "off"), help="the students' warm start from the teacher's "
                    "density (default: the preset's)")
    ap.add_argument("--consistency", type=float, help="the consistency loss's weight for K > 1 (default: the "
                    "preset's)")
    ap.add_argument("--camera-radius", type=float, default=1.5, help="bake each submodel from the training cameras "
                    "within this many cell widths of its centre (0: its own; assets_kK_rR/ unless 1.5)")
    ap.add_argument("--seed", type=int, default=0, help="the distillations' seed (their ray draws, jitter and "
                    "initial MLPs), to measure the spread between runs")
    ap.add_argument("--boundary-views", type=int, default=3)
    ap.add_argument("--teacher-floor", type=float, default=25.0,
                    help="the paired K-against-K figures also count only the test views the teacher renders at this "
                    "PSNR or better")
    ap.add_argument("--work", help="keep everything here, reuse what is finished and resume a teacher or "
                    "student that stopped (default: a temporary folder)")
    args = ap.parse_args()
    args.views = args.views or {"rooms": 80, "house": 280}[args.scene]
    work = Path(args.work or tempfile.mkdtemp(prefix="smerf-partition-"))
    work.mkdir(parents=True, exist_ok=True)
    scene = work / "scene"
    if not (scene / "transforms_test.json").is_file():
        render_dataset(SynthConfig(args.scene, args.size, args.size, views=args.views, spp=args.spp, seed=0), scene)
    teacher_dir = work / "teacher"
    teacher_state = run_state(teacher_dir, "train", TEACHER_CHECKPOINT, steps=args.teacher_steps)
    if teacher_state != "finished":
        if teacher_state is None:
            shutil.rmtree(teacher_dir, ignore_errors=True)
        train_teacher(scene, teacher_dir, replace(preset("hash", "cpu-small"), steps=args.teacher_steps),
                      resume=teacher_state == "stopped")
        if run_state(teacher_dir, "train", TEACHER_CHECKPOINT, steps=args.teacher_steps) != "finished":  # a signal
            raise interrupted("teacher", teacher_dir)
    teacher_eval = evaluate_teacher(teacher_dir, "test", write_images=False)
    views = {"student": {}, "baked": {}}  # per K: PSNR per test view
    result = {"git": git_revision(), "scene": f"{args.scene} {args.size}x{args.size}, {args.views} training views, spp {args.spp}",
              "teacher": {"steps": args.teacher_steps, "seconds": run_seconds(teacher_dir),
                          **{k: round(teacher_eval[k], 4) for k in ("psnr", "ssim", "lpips_vgg")}},
              "student_config": {"steps": args.steps, "sparse_resolution": args.sparse, "triplane_resolution": args.triplane,
                                 "warm_start": args.warm_start or "preset", "seed": args.seed,
                                 "consistency_mult": "preset" if args.consistency is None else args.consistency},
              "per_k": {}, "boundary": {}}
    teacher = load_teacher(teacher_dir)[0].eval()
    ds = load_dataset(scene)
    test_origins = np.stack([ds.frames[i].camera.origin for i in ds.split("test")])
    for k in (int(v) for v in args.ks.split(",")):
        student_dir = work / f"student_k{k}"
        assets = work / (f"assets_k{k}" if args.camera_radius == 1.5 else f"assets_k{k}_r{args.camera_radius:g}")
        cfg = distill_preset("cpu-small", k)
        cfg = replace(cfg, steps=args.steps, seed=args.seed, student=StudentConfig(sparse_resolution=args.sparse,
                                                                     triplane_resolution=args.triplane,
                                                                     mlp_grid=args.mlp_grid))
        if args.warm_start:
            cfg = replace(cfg, warm_start=args.warm_start == "on")
        if args.steps_per_submodel:
            cfg = replace(cfg, steps_per_submodel=True)
        if args.consistency is not None:
            cfg = replace(cfg, consistency_mult=args.consistency)
        rss_file = work / f"peak_rss_{assets.name}.json"
        # students from before these options have neither key
        newer = {key: True for key in ("warm_start", "steps_per_submodel") if getattr(cfg, key)}
        student_state = run_state(student_dir, "distill", STUDENT_CHECKPOINT, steps=args.steps,
                                  student=asdict(cfg.student), consistency_mult=cfg.consistency_mult, seed=cfg.seed,
                                  **newer)
        need_distill = student_state != "finished"
        baked_with = json.loads((assets / "bake.json").read_text()).get("camera_radius", 0.0) \
            if (assets / "bake.json").is_file() else None  # bakes before the option used a submodel's own cameras
        if need_distill or baked_with != args.camera_radius or not rss_file.is_file():
            if student_state is None:
                shutil.rmtree(student_dir, ignore_errors=True)
            shutil.rmtree(assets, ignore_errors=True)
            rss = distill_and_bake(teacher_dir, student_dir, assets, cfg, need_distill, student_state == "stopped",
                                   args.camera_radius)
            of = {None: "distill + bake", "stopped": "resumed distill + bake", "finished": "bake only"}[student_state]
            rss_file.write_text(json.dumps({"bytes": rss, "of": of}))
        s_eval = evaluate_student(student_dir, write_images=False)
        b_eval = evaluate_assets(assets, write_images=False)
        sizes = asset_summary(assets)
        views["student"][k], views["baked"][k] = per_view_psnr(s_eval), per_view_psnr(b_eval)
        result["per_k"][k] = {
            "num_submodels": b_eval["num_submodels"], "distill_seconds": run_seconds(student_dir),
            "distill_steps": json.loads((student_dir / "config.json").read_text()).get("total_steps", args.steps),
            "bake_camera_radius": args.camera_radius,
            "bake_seconds": round(json.loads((assets / "bake.json").read_text())["seconds"], 1),
            **{f"peak_rss_{key}": value for key, value in json.loads(rss_file.read_text()).items()},
            "disk_bytes": b_eval["disk_bytes"],
            "peak_submodel_bytes": b_eval["peak_submodel_bytes"],
            "peak_submodel_grid_bytes": sizes["peak_submodel_grid_bytes"], "deferred_mlp_bytes": sizes["deferred_mlp_bytes"],
            "student": {m: round(s_eval[m], 4) for m in QUALITY}, "baked": {m: round(b_eval[m], 4) for m in QUALITY},
            "format_problems": b_eval["format_problems"]}
        if args.walkthrough:
            from nerfbake.viewer.browser import read_walkthrough, run_walkthrough
            from nerfbake.viewer.server import find_scene

            scene_assets = find_scene(assets)  # the walk `nerfbake view --walkthrough test` flies: every test camera
            walk = run_walkthrough(scene_assets, read_walkthrough("test", scene_assets))
            result["per_k"][k]["walkthrough"] = {key: walk[key] for key in (
                "frames", "p50_ms", "p95_ms", "max_ms", "frames_while_loading", "blank_frames", "max_resident",
                "max_host_cache")}
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
        "student_psnr_by_k": [result["per_k"][k]["student"]["psnr"] for k in ks],
        "baked_psnr_by_k": [result["per_k"][k]["baked"]["psnr"] for k in ks],
    }
    teacher_views = per_view_psnr(teacher_eval)
    result["paired"] = {"teacher_floor_db": args.teacher_floor, **{
        kind: paired_differences(views[kind], teacher_views, args.teacher_floor) for kind in views}}
    result["benchmark_peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps(result, indent=1))
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        raise SystemExit("interrupted; a rerun with the same --work reuses every finished teacher, student and bake "
                         "and resumes an unfinished teacher or student from its last checkpoint") from None
