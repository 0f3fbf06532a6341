"""``nerfbake <verb>``: a thin command layer over the library (one entry point, one sub-command per stage).

Errors caused by input (missing files, bad values) print one line ``error: ...`` and exit with status 2.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from nerfbake import __version__
from nerfbake.atomic import check_output_file
from nerfbake.data.normalization import NORMALIZATIONS


def _print_json(obj) -> None:
    print(json.dumps(obj, indent=2))


def cmd_data_info(args) -> int:
    from nerfbake.data.formats import load_dataset

    ds = load_dataset(args.path, format=args.format, downscale=args.downscale, normalize=args.normalize)
    info = ds.info()
    if args.json:
        _print_json(info)
    else:
        from rich.table import Table

        from nerfbake.progress import console

        table = Table(title=f"{info['root']} ({info['format']})", show_header=False)
        for k, v in info.items():
            if k not in ("root", "normalization", "extras"):
                table.add_row(k, str(v))
        table.add_row("normalization", f"{info['normalization']['method']}, scale {info['normalization']['scale']:.4g}")
        console.print(table)
    return 0


def cmd_metrics(args) -> int:
    from nerfbake.eval.metrics import compare_image_files

    result = compare_image_files(args.image_a, args.image_b)
    if args.json:
        _print_json(result)
    else:
        for k, v in result.items():
            print(f"{k:10s} {v:.5f}")
    return 0


def cmd_synth(args) -> int:
    from nerfbake.data.synth import SCENES, SynthConfig, render_dataset

    if args.list:
        for name, desc in SCENES.items():
            print(f"{name:10s} {desc}")
        return 0
    if not args.out:
        raise ValueError("synth needs --out DIR (or --list)")
    cfg = SynthConfig(scene=args.scene, width=args.width, height=args.height, views=args.views, spp=args.spp, seed=args.seed)
    from nerfbake.progress import progress_bar

    held = cfg.held_out_views
    with progress_bar(f"synth {cfg.scene}", cfg.views + 2 * held, unit="views") as advance:
        out = render_dataset(cfg, Path(args.out), progress=lambda done, total: advance(), overwrite=args.overwrite)
    print(f"wrote {out} ({cfg.views} train / {held} val / {held} test views, {cfg.width}x{cfg.height})")
    return 0


def cmd_process(args) -> int:
    """Photos or a video -> a posed dataset (pycolmap SfM on the CPU): COLMAP layout + transforms.json."""
    from nerfbake.data.process import ProcessConfig, parse_downscales, process, summary_lines

    cfg = ProcessConfig(out=Path(args.out), images=Path(args.images) if args.images else None,
                        video=Path(args.video) if args.video else None, fps=args.fps, max_images=args.max_images,
                        camera_model=args.camera_model, matcher=args.matcher, downscales=parse_downscales(args.downscales),
                        overwrite=args.overwrite)
    report = process(cfg, log=lambda line: print(line, file=sys.stderr))
    for line in summary_lines(report):
        print(line)
    return 0


def cmd_demo(args) -> int:
    """Built-in scene -> the whole pipeline with shortened CPU settings -> report and the commands to view each result."""
    from nerfbake.data.formats import load_dataset
    from nerfbake.pipeline import run_demo

    out = Path(args.out)
    results = run_demo(out, args.width, args.views, args.spp, args.eval_views, _methods(args.methods),
                       log=lambda line: print(line, file=sys.stderr, flush=True),
                       **{n: getattr(args, n) for n in ("teacher_steps", "octree_grid", "distill_steps", "student_sparse",
                                                        "student_triplane")})
    _print_summary(out, results)
    _print_json({"scene": load_dataset(out / "scene").info(), "methods": results["methods"], "report": str(out / "report.md")})
    return 0


def _methods(text: str) -> tuple[str, ...]:
    return tuple(m.strip() for m in text.split(",") if m.strip())


def _print_summary(run: Path, results: dict) -> None:
    from rich.table import Table

    from nerfbake.progress import console
    from nerfbake.report import view_commands

    table = Table(title=f"nerfbake results: {run}")
    for col in ("method", "PSNR", "SSIM", "LPIPS", "ms/frame", "memory MB", "disk MB"):
        table.add_column(col, justify="left" if col == "method" else "right")
    for r in results.get("methods", []):
        table.add_row(r["method"], f"{r['psnr']:.2f}", f"{r['ssim']:.4f}", f"{r['lpips']:.4f}", f"{r['ms_per_frame']:.1f}",
                      f"{r['memory_bytes'] / 1e6:.1f}", f"{r['disk_bytes'] / 1e6:.2f}")
    console.print(table)
    console.print(f"report: {run / 'report.md'}")
    for cmd in view_commands(run, results):
        console.print(f"view:   {cmd}")


def cmd_pipeline(args) -> int:
    from nerfbake.pipeline import PipelineConfig, run_pipeline
    from nerfbake.smerf.run import config_from_file as distill_config
    from nerfbake.teacher.run import config_from_file as teacher_config

    cfg = PipelineConfig(data=args.data, out=args.out, preset=args.preset, methods=_methods(args.methods), k=args.k,
                         eval_views=args.eval_views or None, teacher_steps=args.teacher_steps,
                         distill_steps=args.distill_steps, octree_grid=args.octree_grid, octree_epochs=args.octree_epochs,
                         octree_lr=args.octree_lr, bake_stride=args.bake_stride, downscale=args.downscale,
                         normalize=args.normalize,
                         teacher=teacher_config(args.teacher_config) if args.teacher_config else None,
                         distill=distill_config(args.distill_config) if args.distill_config else None)
    results = run_pipeline(cfg, stop_after=args.stop_after, log=lambda line: print(line, file=sys.stderr, flush=True))
    if results:
        _print_summary(Path(args.out), results)
    return 0


def cmd_report(args) -> int:
    from nerfbake.pipeline import collect_results
    from nerfbake.report import write_report

    path = write_report(args.run, collect_results(args.run))
    print(path)
    return 0


def cmd_teacher_train(args) -> int:
    from nerfbake.teacher.presets import preset
    from nerfbake.teacher.run import config_from_file
    from nerfbake.teacher.train import train_teacher

    cfg = config_from_file(args.config) if args.config else preset(args.field, args.preset)
    cfg = _override(cfg, args, ("steps", "batch_rays", "downscale", "appearance", "normalize"))
    cfg.seed = args.seed
    cfg.tensorboard = cfg.tensorboard or args.tensorboard
    train_teacher(args.data, args.out, cfg, resume=args.resume)
    return 0


def cmd_teacher_eval(args) -> int:
    from nerfbake.teacher.evaluate import evaluate_teacher

    result = evaluate_teacher(Path(args.run), args.split, args.max_views, write_images=not args.no_images,
                              appearance_fit=args.appearance_fit)
    if args.json:
        _print_json(result)
    else:
        print(f"{result['split']}: PSNR {result['psnr']:.2f}  SSIM {result['ssim']:.4f}  "
              f"LPIPS-{result['lpips_net']} {result['lpips_' + result['lpips_net']]:.4f}  "
              f"({result['num_views']} views, {result['seconds_per_view']:.2f} s/view)")
    return 0


def cmd_teacher_render(args) -> int:
    from nerfbake.teacher.evaluate import render_poses

    written = render_poses(Path(args.run), Path(args.pose_file), Path(args.out), overwrite=args.overwrite)
    print(f"wrote {len(written)} images to {args.out}")
    return 0


def _octree_opts(args):
    from nerfbake.octree.render import RenderOptions

    return RenderOptions.from_text(args.step_size, getattr(args, "sh_range", None), getattr(args, "slice", None))


def _override(cfg, args, names: tuple[str, ...]):
    """A preset's dataclass with the options the user gave on the command line (None = not given)."""
    from dataclasses import replace

    return replace(cfg, **{n: getattr(args, n) for n in names if getattr(args, n) is not None})


def cmd_octree_build(args) -> int:
    from dataclasses import replace

    from nerfbake.octree.build import build_octree, build_preset

    cfg = _override(build_preset(args.preset), args, ("grid", "weight_thresh", "samples_per_leaf", "ray_stride",
                                                       "env_map_height"))
    if args.no_autoscale:
        cfg = replace(cfg, autoscale=False)
    cfg.depth  # validates --grid before any work
    check_output_file(args.out, args.overwrite)
    summary = build_octree(args.teacher, args.out, cfg)
    _print_json(summary) if args.json else print(
        f"wrote {summary['tree']}: {summary['num_leaves']:,} leaves ({summary['kept_voxels']:,} kept voxels at "
        f"{cfg.grid}^3), {summary['file_bytes'] / 1e6:.1f} MB in {summary['seconds']:.0f} s; covers {summary['region']}")
    return 0


def cmd_octree_optimize(args) -> int:
    from dataclasses import replace

    from nerfbake.octree.optimize import optimize_preset, optimize_tree

    cfg = _override(optimize_preset(args.preset), args, ("epochs", "lr", "val_every", "downscale", "normalize"))
    if args.continue_on_decrease:
        cfg = replace(cfg, continue_on_decrease=True)
    check_output_file(args.out, args.overwrite)
    summary = optimize_tree(args.tree, args.data, args.out, cfg)
    _print_json(summary) if args.json else print(
        f"wrote {summary['tree']}: best validation PSNR {summary['best_val_psnr']:.2f} dB at epoch {summary['best_epoch']}")
    return 0


def cmd_octree_compress(args) -> int:
    from nerfbake.octree.compress import compress_tree

    band = {"band_bits": [int(b) for b in args.band_bits.split(",")]} if args.band_bits else {}
    check_output_file(args.out, args.overwrite)
    summary = compress_tree(args.tree, args.out, bits=args.bits, retain=args.retain, sigma_thresh=args.sigma_thresh,
                            sh_degree=args.sh_degree, min_extent=args.min_extent, data=args.data, target_db=args.target_db,
                            downscale=args.downscale, normalize=args.normalize or "auto", views=args.views,
                            codebook=args.codebook, **band)
    if args.json:
        _print_json(summary)
        return 0
    how = (f"measured loss {summary['measured_loss_db']:.2f} dB on {summary['measured_on']} (target {args.target_db})"
           if summary["allocation"] == "measured" else summary["allocation"])
    print(f"wrote {summary['tree']}: {summary['file_bytes'] / 1e6:.2f} MB ({summary['ratio']:.1f}x smaller); "
          f"bits per basis {','.join(map(str, summary['band_bits']))}, sigma > {summary['sigma_thresh']:g}; {how}")
    return 0


def cmd_octree_eval(args) -> int:
    from nerfbake.octree.evaluate import evaluate_tree

    result = evaluate_tree(args.tree, args.data, args.split, args.max_views, args.downscale, args.repeats,
                           _octree_opts(args), write=not args.no_images, normalize=args.normalize)
    if args.json:
        _print_json(result)
    else:
        print(f"{result['split']}: PSNR {result['psnr']:.2f}  SSIM {result['ssim']:.4f}  "
              f"LPIPS-{result['lpips_net']} {result['lpips_' + result['lpips_net']]:.4f}  "
              f"{result['ms_per_frame']:.1f} ms/frame ({result['fps']:.1f} FPS, {result['device']})")
    return 0


def cmd_octree_info(args) -> int:
    from nerfbake.octree.io import tree_info

    info = tree_info(args.tree)
    if args.json:
        _print_json(info)
    else:
        for k, v in info.items():
            print(f"{k:22s} {v}")
    return 0


def cmd_octree_render(args) -> int:
    from nerfbake.octree.render import render_pose_file

    written = render_pose_file(args.tree, args.pose_file, args.out, _octree_opts(args), args.overwrite, args.depth)
    print(f"wrote {len(written)} images to {args.out}")
    return 0


def cmd_smerf_info(args) -> int:
    from nerfbake.smerf.evaluate import asset_summary

    info = asset_summary(args.assets)
    if args.json:
        _print_json(info)
    else:
        print(f"{info['assets']}: {info['num_submodels']} submodel(s) on a {info['grid']}^3 grid, "
              f"{info['disk_bytes'] / 1e6:.2f} MB on disk (largest submodel {info['peak_submodel_bytes'] / 1e6:.2f} MB)")
        for msg in info["format_problems"]:
            print(f"format problem: {msg}")
    return 0


def cmd_distill(args) -> int:
    from nerfbake.smerf.distill import distill
    from nerfbake.smerf.run import config_from_file, distill_preset

    cfg = config_from_file(args.config) if args.config else distill_preset(args.preset, args.k or 1)
    cfg = _override(cfg, args, ("k", "steps", "batch_patches", "downscale"))
    cfg.tensorboard = cfg.tensorboard or args.tensorboard
    distill(args.teacher, args.out, cfg, resume=args.resume)
    return 0


def cmd_bake(args) -> int:
    from nerfbake.smerf.bake import bake_student

    stats = bake_student(args.student, args.out, stride=args.ray_stride, overwrite=args.overwrite)
    print(f"baked {stats['num_submodels']} submodel(s) into {args.out} in {stats['seconds']:.0f} s "
          f"(render with: nerfbake smerf render --assets {args.out} --out DIR)")
    return 0


def cmd_smerf_eval(args) -> int:
    from nerfbake.smerf.evaluate import evaluate_assets, evaluate_student

    if args.student:
        result = evaluate_student(args.student, args.data, args.split, args.max_views, write_images=not args.no_images,
                                  downscale=args.downscale)
    else:
        result = evaluate_assets(args.assets, args.data, args.split, args.max_views, write_images=not args.no_images,
                                 downscale=args.downscale)
    if args.json:
        _print_json(result)
    else:
        print(f"{result['method']} {result['split']}: PSNR {result['psnr']:.2f}  SSIM {result['ssim']:.4f}  "
              f"LPIPS-{result['lpips_net']} {result['lpips_' + result['lpips_net']]:.4f}  "
              f"{result['ms_per_frame']:.0f} ms/frame  {result['disk_bytes'] / 1e6:.1f} MB")
    return 0


def cmd_smerf_render(args) -> int:
    from nerfbake.smerf.baked_render import render_frames_to_folder

    written = render_frames_to_folder(args.assets, args.out, args.frames, args.width, args.height, args.step_mult,
                                      args.overwrite)
    print(f"wrote {len(written)} images to {args.out}")
    return 0


def _overwrite_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output (only once the new one is complete)")


NORMALIZE_ARG = dict(choices=NORMALIZATIONS, default="auto",
                     help="scene normalisation: auto decides from the cameras (forward-facing or 360/object-centric; "
                          "nerfbake data info says which and why); the others override it (not for Blender scenes)")
TREE_NORMALIZE_HELP = "the --normalize the tree's teacher was trained with (the tree lives in its frame)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="nerfbake", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    parser.add_argument("--version", action="version", version=f"nerfbake {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    data = sub.add_parser("data", help="inspect datasets").add_subparsers(dest="data_command", required=True)
    info = data.add_parser("info", help="summarise a dataset (format auto-detected)")
    info.add_argument("path")
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.add_argument("--downscale", type=float, default=1.0, help="image downscale factor (intrinsics scale with it)")
    info.add_argument("--format", choices=["blender", "llff", "colmap", "transforms"], help="skip auto-detection")
    info.add_argument("--normalize", **NORMALIZE_ARG)
    info.set_defaults(func=cmd_data_info)

    met = sub.add_parser("metrics", help="PSNR, SSIM, LPIPS (alex, vgg) between two images (RGBA on white)")
    met.add_argument("image_a", help="reference image")
    met.add_argument("image_b", help="image to score")
    met.add_argument("--json", action="store_true")
    met.set_defaults(func=cmd_metrics)

    syn = sub.add_parser("synth", help="render a synthetic Blender-format dataset with Mitsuba 3")
    syn.add_argument("--scene", default="objects")
    syn.add_argument("--out")
    _overwrite_flag(syn)
    syn.add_argument("--width", type=int, default=200)
    syn.add_argument("--height", type=int, default=200)
    syn.add_argument("--views", type=int, default=60, help="training views (val and test get a quarter each, at least 4)")
    syn.add_argument("--spp", type=int, default=64, help="samples per pixel")
    syn.add_argument("--seed", type=int, default=0)
    syn.add_argument("--list", action="store_true", help="list the scenes")
    syn.set_defaults(func=cmd_synth)

    pr = sub.add_parser("process", help="your own photos or video -> a posed dataset (structure from motion, CPU)")
    src = pr.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", help="folder of photos (EXIF orientation honoured; unreadable files are skipped)")
    src.add_argument("--video", help="video file: the sharpest frame of each evenly spaced window is kept")
    pr.add_argument("--out", required=True, help="dataset folder to create (images/, sparse/0/, transforms.json)")
    _overwrite_flag(pr)
    pr.add_argument("--fps", type=float, help="video: frames kept per second of video (default: --max-images in all)")
    pr.add_argument("--max-images", type=int, help="use at most N images, evenly spread (video default 100; folder: all)")
    pr.add_argument("--camera-model", default="SIMPLE_RADIAL",
                    choices=["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"],
                    help="COLMAP camera model, one per video or per EXIF camera (default SIMPLE_RADIAL)")
    pr.add_argument("--matcher", choices=["exhaustive", "sequential"],
                    help="default: sequential for video, exhaustive for a folder")
    pr.add_argument("--downscales", default="2,4,8", help="also write images_F/ for these factors ('none' for none)")
    pr.set_defaults(func=cmd_process)

    teacher = sub.add_parser("teacher", help="train, evaluate and render teacher fields").add_subparsers(
        dest="teacher_command", required=True)
    tt = teacher.add_parser("train", help="train a teacher (presets: cpu-small = 2-core CPU in minutes; paper = GPU scale)")
    tt.add_argument("--data", required=True)
    tt.add_argument("--out", required=True)
    tt.add_argument("--field", choices=["hash", "nerf-sh"], default="hash",
                    help="hash: hash-grid SH field, fast (default); nerf-sh: the PlenOctrees NeRF-SH MLP")
    tt.add_argument("--preset", choices=["cpu-small", "paper"], default="cpu-small")
    tt.add_argument("--steps", type=int)
    tt.add_argument("--batch-rays", type=int)
    tt.add_argument("--downscale", type=float)
    tt.add_argument("--normalize", **{**NORMALIZE_ARG, "default": None})
    tt.add_argument("--appearance", choices=["auto", "affine", "none"],
                    help="per-image exposure/white-balance corrections (default none; auto: affine for photographs, none "
                         "for RGBA renders); held-out views are scored at the mean appearance")
    tt.add_argument("--seed", type=int, default=0)
    tt.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint.pt")
    tt.add_argument("--config", help="training config JSON (e.g. another run's config.json) instead of a preset")
    tt.add_argument("--tensorboard", action="store_true", help="also write TensorBoard scalars to RUN/tensorboard")
    tt.set_defaults(func=cmd_teacher_train)
    te = teacher.add_parser("eval", help="render a split and print PSNR/SSIM/LPIPS")
    te.add_argument("--run", required=True)
    te.add_argument("--split", default="test")
    te.add_argument("--max-views", type=int)
    te.add_argument("--json", action="store_true")
    te.add_argument("--no-images", action="store_true")
    te.add_argument("--appearance-fit", choices=["none", "half"], default="none",
                    help="half: fit an affine colour map on each held-out photo's left half, score its right half "
                         "(NeRF-W's protocol for photos with their own exposure)")
    te.set_defaults(func=cmd_teacher_eval)
    tr = teacher.add_parser("render", help="render camera poses from a transforms-style JSON")
    tr.add_argument("--run", required=True)
    tr.add_argument("--pose-file", required=True)
    tr.add_argument("--out", required=True)
    _overwrite_flag(tr)
    tr.set_defaults(func=cmd_teacher_render)

    octree = sub.add_parser("octree", help="PlenOctrees: build, fine-tune, compress, evaluate, render").add_subparsers(
        dest="octree_command", required=True)
    ob = octree.add_parser("build", help="extract a tree from a trained teacher")
    ob.add_argument("--teacher", required=True, help="teacher run folder")
    ob.add_argument("--out", required=True, help="tree .npz to write")
    _overwrite_flag(ob)
    ob.add_argument("--preset", choices=["cpu-small", "paper"], default="cpu-small")
    ob.add_argument("--grid", type=int, help="dense grid side (power of two; 512 in the paper)")
    ob.add_argument("--weight-thresh", type=float, help="keep voxels with this compositing weight on some training ray")
    ob.add_argument("--samples-per-leaf", type=int, help="teacher samples averaged per leaf (256 paper, 8 fast)")
    ob.add_argument("--ray-stride", type=int, help="use every n-th pixel row/column of the training views for the mask")
    ob.add_argument("--no-autoscale", action="store_true", help="keep the teacher's box instead of fitting one")
    ob.add_argument("--env-map-height", type=int, help="rows of the environment map baked for what lies beyond the box "
                    "of an unbounded scene or a learned background (columns: twice that; 0: constant background)")
    ob.add_argument("--json", action="store_true")
    ob.set_defaults(func=cmd_octree_build)
    oo = octree.add_parser("optimize", help="fine-tune a tree on the training images (analytic gradients, SGD)")
    oo.add_argument("--tree", required=True)
    oo.add_argument("--data", required=True)
    oo.add_argument("--out", required=True)
    _overwrite_flag(oo)
    oo.add_argument("--preset", choices=["cpu-small", "paper"], default="cpu-small")
    oo.add_argument("--epochs", type=int)
    oo.add_argument("--lr", type=float)
    oo.add_argument("--val-every", type=int)
    oo.add_argument("--downscale", type=float)
    oo.add_argument("--normalize", **{**NORMALIZE_ARG, "default": None, "help": TREE_NORMALIZE_HELP})
    oo.add_argument("--continue-on-decrease", action="store_true", help="do not stop when validation PSNR drops")
    oo.add_argument("--json", action="store_true")
    oo.set_defaults(func=cmd_octree_optimize)
    oc = octree.add_parser("compress", help="quantise SH into codebooks + DEFLATE (web trees), bits chosen by measured loss")
    oc.add_argument("--tree", required=True)
    oc.add_argument("--out", required=True)
    _overwrite_flag(oc)
    oc.add_argument("--bits", type=int, default=16, help="codebook size 2^bits (volrend needs 16)")
    oc.add_argument("--retain", type=int, default=0, help="keep the first R SH bases unquantised")
    oc.add_argument("--sigma-thresh", type=float, default=2.0, help="drop leaves with sigma at or below this")
    oc.add_argument("--min-extent", type=float, default=2.0 ** -9,
                    help="do not split codebook cells narrower than this (0 = the authors' always-split median cut)")
    oc.add_argument("--data", help="the scene the tree was built from: bits per SH band and the density threshold are "
                    "then chosen by measured error on its training views (--target-db)")
    oc.add_argument("--target-db", type=float, default=0.5,
                    help="the most PSNR the compressed tree may lose against the uncompressed one (with --data)")
    oc.add_argument("--views", type=int, default=4, help="training views the loss is measured on")
    oc.add_argument("--downscale", type=float, default=1.0, help="image downscale for the measurement (the tree's)")
    oc.add_argument("--normalize", **{**NORMALIZE_ARG, "default": None, "help": TREE_NORMALIZE_HELP})
    oc.add_argument("--band-bits", help="fixed codebook bits per SH band instead, e.g. 16,8,6,4 (the choice without "
                    "--data; capped by --bits; '16' with --codebook median --min-extent 0 = the authors' quantiser)")
    oc.add_argument("--codebook", choices=["kmeans", "median"], default="kmeans",
                    help="median cut refined by k-means (default) or median cut alone")
    oc.add_argument("--sh-degree", type=int, help="keep SH bands up to this degree (smaller files; default: all)")
    oc.add_argument("--json", action="store_true")
    oc.set_defaults(func=cmd_octree_compress)
    oe = octree.add_parser("eval", help="test-split PSNR/SSIM/LPIPS and ms/frame")
    oe.add_argument("--tree", required=True)
    oe.add_argument("--data", required=True)
    oe.add_argument("--split", default="test")
    oe.add_argument("--max-views", type=int)
    oe.add_argument("--downscale", type=float, default=1.0)
    oe.add_argument("--normalize", **{**NORMALIZE_ARG, "help": TREE_NORMALIZE_HELP})
    oe.add_argument("--repeats", type=int, default=3, help="timed passes over the views after a warm-up pass")
    oe.add_argument("--step-size", type=float, help="tree units past each leaf exit (1e-4 default)")
    oe.add_argument("--no-images", action="store_true")
    oe.add_argument("--json", action="store_true")
    oe.set_defaults(func=cmd_octree_eval)
    oi = octree.add_parser("info", help="summarise a tree file (and check it against volrend's loader rules)")
    oi.add_argument("tree")
    oi.add_argument("--json", action="store_true")
    oi.set_defaults(func=cmd_octree_info)
    orr = octree.add_parser("render", help="render camera poses from a transforms-style JSON")
    orr.add_argument("--tree", required=True)
    orr.add_argument("--pose-file", required=True)
    orr.add_argument("--out", required=True)
    _overwrite_flag(orr)
    orr.add_argument("--sh-range", help="SH components lo,hi (half-open) to sum, e.g. 0,1 for the diffuse part")
    orr.add_argument("--slice", help="slicing box xmin,ymin,zmin,xmax,ymax,zmax in tree coordinates")
    orr.add_argument("--step-size", type=float)
    orr.add_argument("--depth", action="store_true", help="also write expected depth as NNNN_depth.npy")
    orr.set_defaults(func=cmd_octree_render)

    smerf = sub.add_parser("smerf", help="SMERF baked scenes: inspect and render asset directories").add_subparsers(
        dest="smerf_command", required=True)
    si = smerf.add_parser("info", help="summarise a baked asset directory (ours or the official export)")
    si.add_argument("assets", help="folder holding sm_XXX/ (or one sm_XXX folder)")
    si.add_argument("--json", action="store_true")
    si.set_defaults(func=cmd_smerf_info)
    se = smerf.add_parser("eval", help="PSNR/SSIM/LPIPS of a student or of baked assets on a held-out split")
    which = se.add_mutually_exclusive_group(required=True)
    which.add_argument("--student", help="a folder written by nerfbake distill")
    which.add_argument("--assets", help="a folder written by nerfbake bake")
    se.add_argument("--data", help="dataset (default: the one the student was distilled on)")
    se.add_argument("--split", default="test")
    se.add_argument("--max-views", type=int)
    se.add_argument("--downscale", type=float, help="image downscale (default: the one the student was distilled at)")
    se.add_argument("--no-images", action="store_true")
    se.add_argument("--json", action="store_true")
    se.set_defaults(func=cmd_smerf_eval)
    sr = smerf.add_parser("render", help="render test_frames.json views as the official viewer's shader does")
    sr.add_argument("--assets", required=True)
    sr.add_argument("--out", required=True)
    _overwrite_flag(sr)
    sr.add_argument("--frames", help="a test_frames.json (default: the first submodel's)")
    sr.add_argument("--width", type=int, default=800)
    sr.add_argument("--height", type=int, default=500)
    sr.add_argument("--step-mult", type=int, default=1, help="the viewer's stepMult, a whole number >= 1 (2 halves the step)")
    sr.set_defaults(func=cmd_smerf_render)

    di = sub.add_parser("distill", help="distil a teacher into SMERF submodels (K^3 camera partition)")
    di.add_argument("--teacher", required=True, help="a teacher run folder")
    di.add_argument("--out", required=True)
    di.add_argument("--k", type=int, help="submodels per axis (default 1)")
    di.add_argument("--preset", default="cpu-small", choices=["cpu-small", "paper"])
    di.add_argument("--config", help="a student's config.json (or a bare distillation config) instead of --preset")
    di.add_argument("--steps", type=int)
    di.add_argument("--batch-patches", type=int, help="3x3 patches per step")
    di.add_argument("--downscale", type=float, help="image downscale of the training photos (default: the teacher's)")
    di.add_argument("--resume", action="store_true")
    di.add_argument("--tensorboard", action="store_true")
    di.set_defaults(func=cmd_distill)
    bk = sub.add_parser("bake", help="bake a student into the SMERF web viewer's asset format")
    bk.add_argument("--student", required=True)
    bk.add_argument("--out", required=True)
    bk.add_argument("--ray-stride", type=int, default=2, help="use every n-th pixel row/column for the alive voxels")
    _overwrite_flag(bk)
    bk.set_defaults(func=cmd_bake)

    vw = sub.add_parser("view", help="serve the web viewer for a baked SMERF folder or a PlenOctree .npz")
    vw.add_argument("scene", help="asset folder (holding sm_XXX/) or tree .npz")
    vw.add_argument("--port", type=int, default=8000)
    vw.add_argument("--host", default="127.0.0.1", help="0.0.0.0 exposes the viewer to other devices on the network")
    vw.add_argument("--benchmark", action="store_true", help="measure ms/frame at 512x512 and 1280x720 in headless chromium")
    vw.add_argument("--frame-mult", type=int, default=1, help="draws per animation frame while benchmarking")
    vw.add_argument("--frames", type=int, default=6, help="timed animation frames per view")
    vw.add_argument("--warmup", type=int, default=2, help="discarded animation frames per view")
    vw.add_argument("--max-views", type=int, help="benchmark only the first N views (default: every test view)")
    vw.add_argument("--gpu", action="store_true", help="benchmark on the machine's GPU instead of SwiftShader, timed by the GPU (EXT_disjoint_timer_query_webgl2) where offered")
    vw.add_argument("--walkthrough", metavar="PATH", help="with --benchmark: fly along a camera path (a test_frames.json, "
                    "{\"frames\": [{position, forward}, ...]}, or 'test' for the scene's test cameras in order) across "
                    "submodel boundaries at 512x512 and print per-frame times, frames drawn while loading, blank frames, "
                    "the most submodels resident and the host cache size")
    vw.add_argument("--json", action="store_true")
    vw.set_defaults(func=cmd_view)

    pl = sub.add_parser("pipeline", help="teacher -> octree -> SMERF -> evaluation -> report, resumable")
    pl.add_argument("--data", required=True)
    pl.add_argument("--out", required=True)
    pl.add_argument("--preset", default="cpu-small", choices=("cpu-small", "paper"),
                    help="cpu-small: a 2-core CPU in tens of minutes; paper: GPU scale")
    pl.add_argument("--methods", default="octree,smerf", help="comma-separated subset of octree,smerf")
    pl.add_argument("--k", type=int, default=1, help="SMERF partition: K^3 submodels")
    pl.add_argument("--eval-views", type=int, default=25, help="evenly spaced test views per evaluation (0: all)")
    pl.add_argument("--normalize", **{**NORMALIZE_ARG, "default": None})
    pl.add_argument("--downscale", type=float, help="image downscale for every stage (default: automatic, photos over "
                    "800 px on the long side for cpu-small, 1600 for paper, are halved until they fit; images_N/ used)")
    pl.add_argument("--teacher-steps", type=int)
    pl.add_argument("--distill-steps", type=int)
    pl.add_argument("--octree-grid", type=int)
    pl.add_argument("--octree-epochs", type=int)
    pl.add_argument("--octree-lr", type=float)
    pl.add_argument("--bake-stride", type=int, default=2)
    pl.add_argument("--teacher-config", help="a teacher training config JSON (e.g. a run's config.json) instead of the preset")
    pl.add_argument("--distill-config", help="a distillation config JSON instead of the preset")
    pl.add_argument("--stop-after", help="stop after this stage (e.g. to test resuming)")
    pl.set_defaults(func=cmd_pipeline)
    dr = sub.add_parser("doctor", help="what this machine gives nerfbake: Python, torch build and device, Warp, "
                        "Mitsuba's libLLVM, pycolmap, LPIPS weights, chromium, free disk")
    dr.set_defaults(func=cmd_doctor)
    rp = sub.add_parser("report", help="write RUN/report.md (table, plots) from a pipeline run")
    rp.add_argument("run")
    rp.set_defaults(func=cmd_report)

    demo = sub.add_parser("demo", help="the whole pipeline on the built-in synthetic scene (CPU, ~10 minutes)")
    demo.add_argument("--out", default="outputs/demo")
    demo.add_argument("--width", type=int, default=160)
    demo.add_argument("--views", type=int, default=48)
    demo.add_argument("--spp", type=int, default=32)
    demo.add_argument("--teacher-steps", type=int, help="hash-teacher steps (default 1000)")
    demo.add_argument("--octree-grid", type=int, help="PlenOctree dense grid side (default 128)")
    demo.add_argument("--distill-steps", type=int, help="SMERF distillation steps (default 600)")
    demo.add_argument("--student-sparse", type=int, help="SMERF sparse grid side S (default 64)")
    demo.add_argument("--student-triplane", type=int, help="SMERF triplane side T (default 256)")
    demo.add_argument("--eval-views", type=int, default=6)
    demo.add_argument("--methods", default="octree,smerf", help="comma-separated subset of octree,smerf")
    demo.set_defaults(func=cmd_demo)
    return parser


def cmd_doctor(args) -> int:
    from nerfbake.doctor import run_checks

    checks = run_checks()
    for c in checks:
        print(c.line())
    missing = [c.name for c in checks if c.required and not c.ok]
    print("everything nerfbake needs is here" if not missing else f"missing: {', '.join(missing)}")
    return 0 if not missing else 1


def cmd_view(args) -> int:
    from nerfbake.viewer.server import ViewerServer, find_scene

    scene = find_scene(args.scene)
    if args.walkthrough and not args.benchmark:
        raise ValueError("--walkthrough flies the viewer headless: give it with --benchmark")
    if args.walkthrough:
        from nerfbake.viewer.browser import read_walkthrough, run_walkthrough

        result = run_walkthrough(scene, read_walkthrough(args.walkthrough), software_gl=not args.gpu)
        if args.json:
            _print_json(result)
        else:
            print(f"{result['frames']} frames: p50 {result['p50_ms']:.1f} ms, p95 {result['p95_ms']:.1f} ms, max "
                  f"{result['max_ms']:.1f} ms; {result['frames_while_loading']} drawn while a submodel loaded, "
                  f"{result['blank_frames']} blank; at most {result['max_resident']} submodels resident, host cache "
                  f"{result['max_host_cache']}")
        return 0
    if args.benchmark:
        from nerfbake.viewer.browser import run_benchmark

        result = run_benchmark(scene, frame_mult=args.frame_mult, frames_per_view=args.frames, warmup=args.warmup,
                               max_views=args.max_views, software_gl=not args.gpu)
        if args.json:
            _print_json(result)
        else:
            for r in result["sizes"]:
                print(f"{r['width']}x{r['height']}: {r['mean_ms_per_frame']:.2f} ms/frame ({r['fps']:.1f} fps) on {r['renderer']}")
        return 0
    server = ViewerServer(scene, host=args.host, port=args.port)
    print(f"serving {scene.kind} scene {scene.name} at {server.url}  (Ctrl-C stops)", flush=True)
    if args.host not in ("127.0.0.1", "localhost"):
        print(f"reachable from other devices on this network at http://<this machine's address>:{server.port}/", flush=True)
    try:
        server.httpd.serve_forever()
    finally:
        server.httpd.server_close()
    return 0


def main(argv: list[str] | None = None) -> int:
    """Exit 0 on success, 2 with one ``error: ...`` line for bad input (the project's errors, missing files, a busy
    port), 130 on Ctrl-C; anything else is a bug, reported in one line as such (``--debug``: the traceback)."""
    from nerfbake.errors import NerfbakeError
    from nerfbake.signals import terminate_like_ctrl_c

    args = build_parser().parse_args(argv)
    terminate_like_ctrl_c()
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (NerfbakeError, ValueError, OSError) as exc:
        if args.debug:
            raise
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 -- the last line of defence against a traceback
        if args.debug:
            raise
        print(f"error: unexpected {type(exc).__name__}: {_one_line(exc)} -- this is a bug in nerfbake; rerun with "
              "--debug for the traceback and report it", file=sys.stderr)
        return 1


def _one_line(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in text:
        text = f"{exc.filename}: {text}"
    return " ".join(text.split())


if __name__ == "__main__":
    sys.exit(main())
