"""How good are the poses ``nerfbake process`` recovers? Synthetic views with known cameras -> SfM -> pose errors
after a similarity (Umeyama) alignment, and (``--teacher-steps`` > 0) test PSNR of a hash teacher trained on the
recovered poses against one trained on the ground-truth poses (same preset, same images, same split).

    python benchmarks/process_quality.py [--size 400] [--views 32] [--spp 16] [--teacher-steps 1000] [--work DIR]
                                         [--camera-model SIMPLE_RADIAL] [--plain-sift]
    -> one JSON object on stdout
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from nerfbake.data.process import ProcessConfig, process
from nerfbake.data.synth import SynthConfig, render_dataset
from nerfbake.eval.poses import angle_deg, umeyama
from nerfbake.train.loop import git_revision


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=400, help="image side; at 256 the low views register from few points")
    ap.add_argument("--views", type=int, default=32, help="training views rendered (val/test add a quarter each)")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--teacher-steps", type=int, default=0, help="0 skips the teacher comparison")
    ap.add_argument("--camera-model", default="SIMPLE_RADIAL", help="COLMAP camera model for nerfbake process")
    ap.add_argument("--plain-sift", action="store_true", help="SIFT without affine shapes and domain-size pooling")
    ap.add_argument("--work", help="keep everything here (default: a temporary folder, removed)")
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="process-quality-"))
    scene = work / "scene"
    if not (scene / "transforms_train.json").is_file():
        render_dataset(SynthConfig("textured", args.size, args.size, views=args.views, spp=args.spp, seed=0), scene)
    photos, gt, angle_x = work / "photos", {}, None
    photos.mkdir(exist_ok=True)
    for split in ("train", "val", "test"):
        meta = json.loads((scene / f"transforms_{split}.json").read_text())
        angle_x = meta["camera_angle_x"]
        for fr in meta["frames"]:
            stem = Path(fr["file_path"]).name
            as_photo(scene / split / f"{stem}.png", photos / f"{split}_{stem}.png")
            gt[f"{split}_{stem}.png"] = np.array(fr["transform_matrix"])
    out = work / "processed"
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    report = process(ProcessConfig(out=out, images=photos, camera_model=args.camera_model,
                                   affine_dsp=not args.plain_sift), log=lambda line: None)
    seconds = time.perf_counter() - t0
    meta = json.loads((out / "transforms.json").read_text())
    rec = {Path(f["file_path"]).name: np.array(f["transform_matrix"]) for f in meta["frames"]}
    names = sorted(rec)
    a, b = np.stack([rec[n][:3, 3] for n in names]), np.stack([gt[n][:3, 3] for n in names])
    s, r, t = umeyama(a, b)
    size = float(np.linalg.norm(b.max(0) - b.min(0)))
    centre = np.linalg.norm(s * a @ r.T + t - b, axis=1) / size
    rel = np.array([angle_deg((rec[p][:3, :3].T @ rec[q][:3, :3]).T @ (gt[p][:3, :3].T @ gt[q][:3, :3]))
                    for i, p in enumerate(names) for q in names[i + 1:]])
    result = {
        "git": git_revision(), "scene": f"textured {args.size}x{args.size}, {len(gt)} views, spp {args.spp}",
        "process_seconds": round(seconds, 1), "timings_s": report["timings_s"],
        "registered": report["num_registered"], "images": report["num_images"],
        "mean_reprojection_error_px": report["mean_reprojection_error_px"],
        "focal_px": meta.get("fl_x"), "focal_gt_px": 0.5 * args.size / np.tan(0.5 * angle_x),
        "centre_error_frac_of_scene": {"max": float(centre.max()), "mean": float(centre.mean())},
        "relative_rotation_error_deg": {"max": float(rel.max()), "p95": float(np.percentile(rel, 95)),
                                        "mean": float(rel.mean()), "median": float(np.median(rel))},
    }
    if args.teacher_steps > 0:
        result["teacher"] = compare_teachers(work, out, gt, angle_x, args.size, args.teacher_steps, (s, r, t))
    print(json.dumps(result, indent=1))
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)


def as_photo(render: Path, dest: Path) -> None:
    """A camera has no alpha: the render's transparent sky becomes white. (Left as RGBA, readers that drop alpha
    see a black sky that the teacher leaves part transparent, and evaluation on white scores ~10 dB.)"""
    rgba = np.asarray(Image.open(render).convert("RGBA")).astype(np.float32) / 255.0
    rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
    Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(dest)


def compare_teachers(work: Path, processed: Path, gt: dict, angle_x: float, size: int, steps: int,
                     to_gt: tuple) -> dict:
    """Train the same preset on recovered and on ground-truth poses (same images, same every-8th test split, the
    same sparse points carried into the ground-truth frame by the similarity ``to_gt``, so both get the same
    near plane)."""
    from nerfbake.data.formats.ply import read_ply_points

    from nerfbake.teacher.evaluate import evaluate_teacher
    from nerfbake.teacher.presets import preset
    from nerfbake.teacher.train import train_teacher

    gt_dir = work / "gt_poses"
    gt_dir.mkdir(exist_ok=True)
    if not (gt_dir / "images").exists():
        (gt_dir / "images").symlink_to((processed / "images").resolve())
    focal = 0.5 * size / np.tan(0.5 * angle_x)
    frames = [{"file_path": f"images/{n}", "transform_matrix": gt[n].tolist()} for n in sorted(gt)]
    s, r, t = to_gt
    points = s * read_ply_points(processed / "sparse_pc.ply") @ r.T + t
    ply = [f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header"]
    (gt_dir / "sparse_pc.ply").write_text("\n".join(ply + [f"{x} {y} {z}" for x, y, z in points]) + "\n")
    (gt_dir / "transforms.json").write_text(json.dumps({"fl_x": focal, "fl_y": focal, "cx": size / 2, "cy": size / 2,
                                                         "w": size, "h": size, "ply_file_path": "sparse_pc.ply",
                                                         "frames": frames}))
    out = {}
    for name, data in (("ground_truth_poses", gt_dir), ("recovered_poses", processed)):
        cfg = preset("hash", "cpu-small")
        cfg.steps = steps
        run = work / f"teacher_{name}"
        shutil.rmtree(run, ignore_errors=True)  # a rerun in the same --work trains afresh
        t0 = time.perf_counter()
        train_teacher(data, run, cfg)
        res = evaluate_teacher(run, "test", write_images=False)
        out[name] = {"test_psnr": res["psnr"], "ssim": res["ssim"], "views": res["num_views"],
                     "train_seconds": round(time.perf_counter() - t0, 1)}
    out["psnr_gap_db"] = out["ground_truth_poses"]["test_psnr"] - out["recovered_poses"]["test_psnr"]
    out["steps"] = steps
    return out


if __name__ == "__main__":
    main()
