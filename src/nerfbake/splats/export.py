"""``nerfbake export``: a tree (or a teacher, through a tree built from it) -> a splat file and its frame record."""
from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from nerfbake.atomic import check_output_file, write_json
from nerfbake.progress import progress_bar
from nerfbake.data.dataset import Dataset
from nerfbake.data.formats import load_dataset
from nerfbake.eval.views import evaluate_views, pick_views
from nerfbake.octree.build import build_octree, build_preset
from nerfbake.octree.io import load_tree
from nerfbake.splats.fit import FitConfig, fit_gaussians
from nerfbake.splats.from_tree import environment_shell, gaussians_from_tree
from nerfbake.splats.gaussians import Gaussians, concatenate
from nerfbake.kernels.splat_raster import REFERENCE, WEB
from nerfbake.splats.io import SplatFileError, check_format, web_quantized, write_splats
from nerfbake.splats.rasterize import render_gaussians
from nerfbake.teacher.evaluate import render_camera
from nerfbake.teacher.run import load_teacher


def input_frame(ds: Dataset | None) -> dict:
    """How the splats' coordinates (the teacher's normalised frame) map back to the input photos' coordinates: the
    dataset's normalisation and the 4x4 matrix ``to_input_frame`` (p_input = M @ [p, 1]); without a dataset, a
    note that the frame is the normalised one."""
    if ds is None:
        return {"frame": "the tree's world frame (the teacher's normalised frame); pass --data to record the "
                         "transform to the photos' frame", "to_input_frame": np.eye(4).tolist()}
    norm = ds.normalization
    rotation, translation = norm.transform[:3, :3], norm.transform[:3, 3]
    back = np.eye(4)
    back[:3, :3] = rotation.T / norm.scale
    back[:3, 3] = -rotation.T @ translation
    return {"frame": f"normalised by {norm.method} ({ds.root})", "normalization": norm.to_json(),
            "to_input_frame": back.tolist()}


VIEWER_RULES = {"web": WEB, "reference": REFERENCE}


def evaluate_splats(g: Gaussians, ds: Dataset, split: str = "test", max_views: int | None = 5,
                    viewer_rules: str = "reference") -> dict:
    """PSNR / SSIM / LPIPS of the Gaussians on a held-out split, drawn by our rasteriser (the same protocol as every
    other renderer's evaluation) as the ``viewer_rules`` viewer would: for ``web``, the 8-bit colours, opacities and
    rotations it loads (:func:`web_quantized`) under its compositing."""
    if viewer_rules == "web":
        g = web_quantized(g)
    rules = VIEWER_RULES[viewer_rules]
    result = evaluate_views(lambda cam, bg: render_gaussians(g, cam, bg, rules).clamp(0, 1).numpy(), ds, split,
                            max_views, desc="splats eval")
    return {k: result[k] for k in ("psnr", "ssim", f"lpips_{result['lpips_net']}", "lpips_net", "num_views",
                                   "seconds_per_view", "split")}


def target_views(ds: Dataset, num_views: int, teacher=None) -> list:
    """(camera, image) pairs to fit splats to: ``num_views`` evenly spread training cameras with the teacher's renders
    when there is a teacher, else the training photos."""
    background = tuple(ds.background or (1.0, 1.0, 1.0))
    views = []
    with progress_bar("splat fit targets", num_views, unit="view") as advance:
        for i in pick_views(ds.split("train"), num_views):
            camera = ds.frames[i].camera
            image = render_camera(teacher, camera, background)["rgb"] if teacher is not None else ds.image(i)[..., :3]
            views.append((camera, np.asarray(image, np.float32)))
            advance()
    return views


def export_splats(out: str | Path, fmt: str, tree: str | Path | None = None, teacher: str | Path | None = None,
                  sh_degree: int | None = None, max_splats: int | None = None, data: str | None = None,
                  normalize: str = "auto", grid: int = 256, overwrite: bool = False, eval_views: int = 0,
                  downscale: float = 1.0, fit_steps: int = 0, fit_views: int = 20,
                  viewer_rules: str = "web") -> dict:
    """Write the Gaussians of ``tree`` (or of a ``grid``^3 tree built from ``teacher``) to ``out`` in ``fmt`` and
    ``<out>.json`` beside it (counts, sizes, :func:`input_frame` and, with ``eval_views``, :func:`evaluate_splats`
    on that many test views of ``data``); returns that record. ``fit_steps`` > 0 first fits the Gaussians to
    ``fit_views`` :func:`target_views`; fit and evaluation follow ``viewer_rules`` (``web`` or ``reference``)."""
    start = time.time()
    out = Path(out)
    check_format(out, fmt)  # every check before any work
    if viewer_rules not in VIEWER_RULES:
        raise ValueError(f"viewer_rules must be one of {', '.join(VIEWER_RULES)}, not {viewer_rules!r}")
    if (tree is None) == (teacher is None):
        raise ValueError("export needs exactly one of --tree TREE.npz and --teacher RUN")
    if data is None and teacher is None and (fit_steps or eval_views):
        raise ValueError("--fit-steps and --eval-views use a dataset's views: give --data (or --teacher)")
    check_output_file(out, overwrite)
    model = None
    with tempfile.TemporaryDirectory(prefix="nerfbake-export-") as tmp:
        if teacher is not None:
            model, tcfg, meta, _ = load_teacher(Path(teacher))  # a clear error for a folder of the wrong kind
            data, normalize, downscale = data or meta["data"], tcfg.normalize, tcfg.downscale
            tree = build_octree(teacher, Path(tmp) / "tree.npz", replace(build_preset("cpu-small"), grid=grid))["tree"]
        octree = load_tree(tree)
        g = gaussians_from_tree(octree, 0 if fmt == "splat" else sh_degree, max_splats)  # .splat: colour only
    ds = None if data is None else load_dataset(data, downscale=downscale, normalize=normalize)
    if len(g) == 0:
        raise SplatFileError(f"{tree}: no leaf is opaque enough to become a splat (an empty tree); check it with "
                             "nerfbake octree info")
    shell = environment_shell(octree, g.sh_degree)  # what lies beyond the box of an unbounded scene
    if shell is not None:
        g = concatenate([g, shell])
    record = {"file": str(out), "format": fmt, "source": str(teacher or tree), "num_splats": len(g),
              "environment_splats": 0 if shell is None else len(shell), "sh_degree": g.sh_degree,
              "viewer_rules": viewer_rules, **input_frame(ds)}
    if fit_steps:
        views = target_views(ds, fit_views, model.eval() if model is not None else None)
        g, history = fit_gaussians(g, views, FitConfig(steps=fit_steps, rules=VIEWER_RULES[viewer_rules]))
        record["fit"] = {"steps": fit_steps, "views": len(views), "targets": "teacher" if model is not None else "photos",
                         "crop_psnr_first_last_50": [float(np.mean(history[:50])), float(np.mean(history[-50:]))]}
    if eval_views:
        record["eval"] = evaluate_splats(g, ds, max_views=eval_views, viewer_rules=viewer_rules)
    write_splats(g, out, fmt)
    record.update(file_bytes=out.stat().st_size, seconds=round(time.time() - start, 1))
    write_json(Path(f"{out}.json"), record)
    return record
