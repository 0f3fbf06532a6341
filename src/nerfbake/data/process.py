"""``nerfbake process``: a user's photos or video -> a posed dataset (structure from motion with pycolmap on the CPU).

Stages, each with a progress bar: intake (the folder's readable images, or the sharpest frame of each window of
a video; :mod:`nerfbake.data.frames`), SIFT feature extraction (one shared camera per video or per EXIF
camera), matching (exhaustive for photo folders, sequential for video), incremental mapping, and writing.
The largest registered model is kept. Output, written to a temporary folder beside ``out`` and renamed at the
end so a failure leaves nothing behind::

    out/images/               the input images (EXIF orientation applied), or the extracted video frames
    out/images_2/ _4/ _8/     area-downscaled copies (``--downscales``), sizes round(W/F) x round(H/F)
    out/sparse/0/             the COLMAP model (cameras.bin, images.bin, points3D.bin)
    out/transforms.json       nerfstudio / instant-ngp: OpenGL c2w, fl_x fl_y cx cy w h (+ k1 k2 p1 p2)
    out/sparse_pc.ply         the sparse point cloud (same world frame as the poses)
    out/process_report.json   registered / dropped / skipped images, mean reprojection error, timings

``transforms.json`` comes first in nerfbake's format detection; ``load_dataset(out, format="colmap")`` reads
the same cameras from ``sparse/0``.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from nerfbake.atomic import atomic_folder, check_output_folder
from nerfbake.data.cameras import opencv_to_opengl
from nerfbake.data.errors import DatasetError
from nerfbake.data.formats.colmap import colmap_camera
from nerfbake.data.frames import Intake, intake_images, intake_video, video_info
from nerfbake.progress import progress_bar
from nerfbake.signals import terminate_like_ctrl_c

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")  # what nerfbake's readers read
MATCHERS = ("exhaustive", "sequential")
MIN_IMAGES = 3
REPORT_NAME = "process_report.json"


@dataclass
class ProcessConfig:
    out: Path
    images: Path | None = None
    video: Path | None = None
    fps: float | None = None  # video: frames kept per second of video (at most max_images in all)
    max_images: int | None = None  # folder: all by default; video: 100 by default
    camera_model: str = "SIMPLE_RADIAL"
    matcher: str | None = None  # None: sequential for video, exhaustive for folders
    downscales: tuple[int, ...] = (2, 4, 8)
    min_registered_fraction: float = 0.5  # fail when fewer of the images register
    max_image_size: int = 3200  # SIFT works on images at most this large (COLMAP's default)
    affine_dsp: bool = True  # affine-adapted, domain-size-pooled SIFT (slower, many more matches)
    seed: int = 0
    overwrite: bool = False  # replace a non-empty ``out`` (swapped in only once the new dataset is complete)


def parse_downscales(text: str) -> tuple[int, ...]:
    """'2,4,8' -> (2, 4, 8); '' or 'none' -> ()."""
    if text.strip().lower() in ("", "none", "0"):
        return ()
    try:
        values = tuple(sorted({int(v) for v in text.split(",") if v.strip()}))
    except ValueError:
        raise DatasetError(f"--downscales {text!r}: give comma-separated integers such as 2,4,8") from None
    if any(v < 2 for v in values):
        raise DatasetError(f"--downscales {text!r}: factors must be integers of at least 2 (e.g. 2,4,8)")
    return values


def _check_config(cfg: ProcessConfig) -> None:
    if (cfg.images is None) == (cfg.video is None):
        raise DatasetError("process needs exactly one of --images DIR or --video FILE")
    if cfg.camera_model not in CAMERA_MODELS:
        raise DatasetError(f"--camera-model {cfg.camera_model!r} is not supported; choose one of {', '.join(CAMERA_MODELS)}")
    if cfg.matcher is not None and cfg.matcher not in MATCHERS:
        raise DatasetError(f"--matcher {cfg.matcher!r}: choose exhaustive or sequential")
    if cfg.fps is not None and not (cfg.fps > 0 and math.isfinite(cfg.fps)):
        raise DatasetError(f"--fps {cfg.fps}: must be a positive number of frames per second")
    if cfg.max_images is not None and cfg.max_images < MIN_IMAGES:
        raise DatasetError(f"--max-images {cfg.max_images}: structure from motion needs at least {MIN_IMAGES} images")
    out = Path(cfg.out)
    check_output_folder(out, cfg.overwrite, "dataset")


@contextlib.contextmanager
def _quiet_colmap():
    """COLMAP logs every step to stderr; keep errors only while we run (our report says what happened). Importing
    pycolmap hands SIGTERM to glog, which aborts: take it back so a killed run cleans up."""
    import pycolmap


    terminate_like_ctrl_c()
    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _stage(description: str, total: int, unit: str):
    return progress_bar(description, max(1, total), unit=unit)


def process(cfg: ProcessConfig, log=print) -> dict:
    """Run the whole pipeline; returns (and saves in ``out``) the report. Raises DatasetError on bad input."""
    _check_config(cfg)
    out = Path(cfg.out)
    timings: dict[str, float] = {}
    with atomic_folder(out, cfg.overwrite, "dataset") as tmp:
        with _quiet_colmap():
            intake = _intake(cfg, tmp / "images", timings)
            if intake.skipped:
                for s in intake.skipped:
                    log(f"skipped {s['file']}: {s['reason']}")
            n = len(intake.names)
            if n < MIN_IMAGES:
                skipped = "; skipped unreadable: " + ", ".join(f"{s['file']} ({s['reason']})" for s in intake.skipped) \
                    if intake.skipped else ""
                raise DatasetError(f"{intake.source}: only {n} readable image(s), structure from motion needs at least "
                                   f"{MIN_IMAGES}{skipped}")
            work = tmp / ".sfm"
            sfm_images = _sfm_inputs(tmp / "images", work / "images", intake.names)
            db = work / "database.db"
            _extract(db, sfm_images, intake, cfg, timings)
            matcher = cfg.matcher or ("sequential" if cfg.video is not None else "exhaustive")
            _match(db, matcher, n, timings)
            rec, num_models = _map(db, sfm_images, work / "sparse", n, cfg, timings)
            registered = sorted(im.name for im in rec.images.values() if im.has_pose) if rec is not None else []
            needed = max(MIN_IMAGES, math.ceil(cfg.min_registered_fraction * n))
            if len(registered) < needed:
                raise DatasetError(_too_few_message(intake, db, registered, n, needed, matcher))
            report = _write_outputs(rec, tmp, intake, registered, cfg, matcher, num_models, timings)
            shutil.rmtree(work, ignore_errors=True)
            (tmp / REPORT_NAME).write_text(json.dumps(report, indent=1))
    report["out"] = str(out)
    return report


def _intake(cfg: ProcessConfig, dest: Path, timings: dict) -> Intake:
    t0 = time.perf_counter()
    if cfg.video is not None:
        video = Path(cfg.video)
        if not video.exists():
            raise DatasetError(f"{video}: no such video file; check the path given to --video")
        if not video.is_file():
            raise DatasetError(f"{video}: not a file; pass --video FILE (or --images DIR for a folder of photos)")
        count, fps = video_info(video)
        with _stage("process: video frames", count, "frames") as advance:
            intake = intake_video(video, dest, cfg.fps, cfg.max_images or 100, progress=advance, known=(count, fps))
    else:
        folder = Path(cfg.images)
        total = sum(1 for _ in folder.iterdir()) if folder.is_dir() else 0
        with _stage("process: read images", min(total, cfg.max_images or total), "images") as advance:
            intake = intake_images(folder, dest, cfg.max_images, progress=advance)
        if not intake.names and not intake.skipped:
            raise DatasetError(f"{folder}: no images found (looked for .jpg, .jpeg, .png, .tif, .bmp, .webp files)")
    timings["intake_s"] = time.perf_counter() - t0
    return intake


def _sfm_inputs(images: Path, dest: Path, names: list[str]) -> Path:
    """The images SfM sees: links to the dataset's images, or RGB copies composited on white where they have alpha
    (so features come from what training sees, not from the colour under transparent pixels)."""
    dest.mkdir(parents=True)
    for name in names:
        src = images / name
        with Image.open(src) as im:
            has_alpha = im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info)
            if has_alpha:
                rgba = np.asarray(im.convert("RGBA")).astype(np.float32) / 255.0
                rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
                Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(dest / name, format="PNG")
                continue
        try:
            os.link(src, dest / name)
        except OSError:
            shutil.copyfile(src, dest / name)
    return dest


def _extract(db: Path, images: Path, intake: Intake, cfg: ProcessConfig, timings: dict) -> None:
    """SIFT on the CPU; images of one group (video, or one EXIF camera and size) share one camera."""
    import pycolmap

    t0 = time.perf_counter()
    groups: dict[str, list[str]] = {}
    for name in intake.names:
        groups.setdefault(intake.groups[name], []).append(name)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = cfg.max_image_size
    extraction.use_gpu = False
    # Affine-adapted, domain-size-pooled SIFT: ~30% slower on the CPU, many more verified matches across the wide
    # baselines of hand-held photo sets (on 320x320 synthetic views: 437 instead of 283 matched pairs of 780).
    extraction.sift.estimate_affine_shape = cfg.affine_dsp
    extraction.sift.domain_size_pooling = cfg.affine_dsp
    chunk = 8  # images per call: the bar moves while SIFT still runs on every core within a call
    with _stage("process: features", len(intake.names), "images") as advance:
        for names in groups.values():
            camera_id = -1
            for start in range(0, len(names), chunk):
                part = names[start:start + chunk]
                reader = pycolmap.ImageReaderOptions()
                reader.camera_model = cfg.camera_model
                reader.existing_camera_id = camera_id
                pycolmap.extract_features(db, images, image_names=part, camera_mode=pycolmap.CameraMode.SINGLE,
                                          reader_options=reader, extraction_options=extraction,
                                          device=pycolmap.Device.cpu)
                if camera_id < 0:
                    with pycolmap.Database.open(db) as d:
                        image = d.read_image_with_name(part[0])
                        if image is None:
                            raise DatasetError(f"{images / part[0]}: COLMAP could not read this image")
                        camera_id = image.camera_id
                advance(len(part))
    timings["features_s"] = time.perf_counter() - t0


def _match(db: Path, matcher: str, n: int, timings: dict) -> None:
    import pycolmap

    t0 = time.perf_counter()
    pairs = n * (n - 1) // 2 if matcher == "exhaustive" else n * 10
    with _stage(f"process: {matcher} matching (~{pairs} pairs)", 1, "stage") as advance:
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = 10
            pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
        advance()
    timings["matching_s"] = time.perf_counter() - t0


def _map(db: Path, images: Path, sparse: Path, n: int, cfg: ProcessConfig, timings: dict):
    """Incremental mapping; returns (the model with the most registered images or None, number of models)."""
    import pycolmap

    t0 = time.perf_counter()
    sparse.mkdir(parents=True, exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = MIN_IMAGES
    # Small images (video frames, thumbnails) have a few hundred features: accept an initial pair with 50 inliers
    # and register an image from 15 (COLMAP: 100 and 30), still RANSAC-verified against the model.
    options.mapper.init_min_num_inliers = 50
    options.mapper.abs_pose_min_num_inliers = 15
    options.random_seed = cfg.seed
    options.mapper.random_seed = cfg.seed
    options.triangulation.random_seed = cfg.seed
    pycolmap.set_random_seed(cfg.seed)
    with _stage("process: mapping", n, "images") as advance:
        models = pycolmap.incremental_mapping(db, images, sparse, options, next_image_callback=lambda: advance())
    timings["mapping_s"] = time.perf_counter() - t0
    if not models:
        return None, 0
    best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    return best, len(models)


def _too_few_message(intake: Intake, db: Path, registered: list[str], n: int, needed: int, matcher: str) -> str:
    import pycolmap

    with pycolmap.Database.open(db) as d:
        feats = [d.num_keypoints_for_image(im.image_id) for im in d.read_all_images()]
        _, geometries = d.read_two_view_geometries()
        verified = sum(len(g.inlier_matches) >= 15 for g in geometries)
    why = (f"median {int(np.median(feats)) if feats else 0} features per image, {verified} image pairs share enough "
           "verified matches")
    try_other = "--matcher exhaustive" if matcher == "sequential" else "--matcher sequential for video or ordered captures"
    return (f"{intake.source}: only {len(registered)} of {n} images registered in one model (need at least {needed}); "
            f"{why}. Try: photos with more overlap (every part of the scene seen from 3+ nearby views), {try_other}, "
            "fewer blurry frames (steady shots, lower --fps)")


def camera_fields(cam) -> dict:
    """transforms.json intrinsics of one COLMAP camera (OPENCV with k1 k2 p1 p2 when the model distorts)."""
    fx, fy, cx, cy, dist, model = colmap_camera(cam, Path("sparse/0"))
    fields = {"camera_model": "OPENCV" if model in ("SIMPLE_RADIAL", "RADIAL", "OPENCV") else "PINHOLE",
              "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": int(cam.width), "h": int(cam.height)}
    if fields["camera_model"] == "OPENCV":
        fields.update({k: float(dist.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2")})
    return fields


def c2w_opengl(image) -> np.ndarray:
    w2c = np.eye(4)
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    w2c[:3, :4] = pose.matrix()
    return opencv_to_opengl(np.linalg.inv(w2c))


def transforms_dict(rec) -> dict:
    """nerfstudio / instant-ngp transforms.json for a reconstruction: shared intrinsics at the top level when
    there is one camera, per frame otherwise. ``scale``/``offset`` place the scene in instant-ngp's unit cube."""
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    cams = {cid: camera_fields(rec.cameras[cid]) for cid in sorted({im.camera_id for im in images})}
    meta: dict = dict(next(iter(cams.values()))) if len(cams) == 1 else {}
    frames = []
    centres = []
    for im in images:
        c2w = c2w_opengl(im)
        centres.append(c2w[:3, 3])
        fr = {"file_path": f"images/{im.name}", "transform_matrix": c2w.tolist(), "colmap_im_id": int(im.image_id)}
        if len(cams) > 1:
            fr.update(cams[im.camera_id])
        frames.append(fr)
    centres = np.array(centres)
    centre = centres.mean(0)
    radius = float(np.mean(np.linalg.norm(centres - centre, axis=1))) or 1.0
    # instant-ngp maps p -> scale * (p_y, p_z, p_x) + offset; colmap2nerf puts cameras ~4 units out at scale 0.33.
    scale = 0.33 * 4.0 / radius
    meta.update({"aabb_scale": 16, "scale": scale,
                 "offset": (0.5 - scale * centre[[1, 2, 0]]).tolist(), "ply_file_path": "sparse_pc.ply", "frames": frames})
    return meta


def _downscale_all(root: Path, names: list[str], factors: tuple[int, ...]) -> None:
    if not factors:
        return
    with _stage("process: downscales " + ",".join(map(str, factors)), len(names) * len(factors), "images") as advance:
        for name in names:
            with Image.open(root / "images" / name) as im:
                im.load()
                for f in factors:
                    d = root / f"images_{f}"
                    d.mkdir(exist_ok=True)
                    size = (max(1, round(im.width / f)), max(1, round(im.height / f)))
                    small = im.resize(size, Image.Resampling.BOX)
                    kwargs = {"quality": 95} if Path(name).suffix.lower() in (".jpg", ".jpeg") else {}
                    exif = im.getexif()
                    if exif:
                        kwargs["exif"] = exif.tobytes()
                    small.save(d / name, **kwargs)
                    advance()


def _write_outputs(rec, tmp: Path, intake: Intake, registered: list[str], cfg: ProcessConfig, matcher: str,
                   num_models: int, timings: dict) -> dict:
    t0 = time.perf_counter()
    sparse = tmp / "sparse" / "0"
    sparse.mkdir(parents=True)
    rec.write(sparse)
    rec.export_PLY(tmp / "sparse_pc.ply")
    (tmp / "transforms.json").write_text(json.dumps(transforms_dict(rec), indent=1))
    _downscale_all(tmp, intake.names, cfg.downscales)
    timings["write_s"] = time.perf_counter() - t0
    dropped = [name for name in intake.names if name not in set(registered)]
    cams = [camera_fields(c) for c in rec.cameras.values()]
    report = {
        "source": intake.source, "kind": intake.info.get("kind"), "num_images": len(intake.names),
        "num_registered": len(registered), "registered": registered, "dropped": dropped,
        "skipped_unreadable": intake.skipped, "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "num_points3D": int(rec.num_points3D()), "mean_track_length": float(rec.compute_mean_track_length()),
        "num_models": num_models, "num_cameras": len(cams), "cameras": cams, "matcher": matcher,
        "camera_model": cfg.camera_model, "downscales": list(cfg.downscales),
        "timings_s": {k: round(v, 2) for k, v in timings.items()},
        "options": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
    }
    if intake.info.get("kind") == "video":
        report["video"] = intake.info
    return report


def summary_lines(report: dict) -> list[str]:
    """What the CLI prints after a run."""
    lines = [f"registered {report['num_registered']} of {report['num_images']} images "
             f"(mean reprojection error {report['mean_reprojection_error_px']:.3f} px, {report['num_points3D']} points, "
             f"{report['num_cameras']} camera(s), {report['matcher']} matching)"]
    if report["dropped"]:
        lines.append(f"dropped (not registered): {', '.join(report['dropped'])}")
    if report["skipped_unreadable"]:
        lines.append("skipped (unreadable): " + ", ".join(s["file"] for s in report["skipped_unreadable"]))
    lines.append(f"wrote {report['out']} (COLMAP sparse/0, transforms.json, sparse_pc.ply; report in {REPORT_NAME})")
    return lines
