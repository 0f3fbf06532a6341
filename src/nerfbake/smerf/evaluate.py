"""``nerfbake smerf eval`` and ``smerf info``: quality of a student (rendered on the teacher's intervals) or of baked
assets (rendered by the viewer-exact baked renderer) on a held-out split, with the size figures SMERF reports."""
from __future__ import annotations

import json
from pathlib import Path

from nerfbake.data.formats import load_dataset
from nerfbake.eval.views import evaluate_views
from nerfbake.smerf.assets import AssetError, SceneAssets, read_params
from nerfbake.smerf.bake import viewer_camera
from nerfbake.smerf.baked_render import render_baked
from nerfbake.smerf.distill import render_student_camera
from nerfbake.smerf.partition import Partition
from nerfbake.smerf.run import load_student
from nerfbake.smerf.validate import asset_problems
from nerfbake.teacher.run import load_teacher
from nerfbake.train.loop import default_device, git_revision, write_json_atomic


def asset_summary(root: str | Path) -> dict:
    """Submodels, their disk sizes (the whole scene and the largest one a viewer holds at a time, with and without the
    deferred-MLP file every folder repeats) and format check."""
    scene = SceneAssets.open(root)
    subs = []
    for params_idx, sm in enumerate(scene.params["params_to_sm"]):
        folder = scene.root / f"sm_{sm:03d}"
        p = read_params(folder)
        mlp = folder / "deferred_mlp.json.gz"  # every folder repeats the MLPs of all submodels; the viewer reads one
        subs.append({"params_idx": params_idx, "submodel": sm, "folder": str(folder),
                     "disk_bytes": sum(f.stat().st_size for f in folder.iterdir() if f.is_file()),
                     "deferred_mlp_bytes": mlp.stat().st_size if mlp.is_file() else 0,
                     **{k: p.get(k) for k in ("triplane_resolution", "sparse_grid_resolution", "atlas_width", "atlas_height",
                                              "atlas_depth", "submodel_scale")}})
    return {"assets": str(scene.root), "num_submodels": len(subs), "grid": round(2.0 / scene.params["submodel_voxel_size"]),
            "disk_bytes": sum(s["disk_bytes"] for s in subs), "peak_submodel_bytes": max(s["disk_bytes"] for s in subs),
            "peak_submodel_grid_bytes": max(s["disk_bytes"] - s["deferred_mlp_bytes"] for s in subs),
            "deferred_mlp_bytes": max(s["deferred_mlp_bytes"] for s in subs),
            "deferred_mlp_grid": list(scene.mlp["ResampleDense_0/kernel"].shape[1:4]), "submodels": subs,
            "format_problems": asset_problems(scene.root)}


def _finish(result: dict, out_dir: Path, split: str, extra: dict) -> dict:
    result["ms_per_frame"] = 1000.0 * result["seconds_per_view"]
    result.update(extra, git=git_revision())
    write_json_atomic(out_dir / f"results_{split}.json", result)
    return result


def evaluate_student(student_dir: str | Path, data: str | Path | None = None, split: str = "test",
                     max_views: int | None = None, write_images: bool = True, downscale: float | None = None) -> dict:
    """``downscale`` None evaluates at the one the student was distilled at."""
    student_dir = Path(student_dir)
    student, cfg, meta = load_student(student_dir)
    dev = default_device()
    student.to(dev)
    teacher = load_teacher(Path(meta["teacher"]))[0].to(dev)
    ds = load_dataset(data or meta["data"], downscale=downscale or meta.get("downscale", 1.0),
                      normalize=meta.get("normalize", "auto"))
    out_dir = student_dir / "eval"
    result = evaluate_views(lambda cam, bg: render_student_camera(student, teacher, cam, bg), ds, split, max_views,
                            out_dir / split if write_images else None, desc="student")
    n = student.partition.num_alive
    param_bytes = 4 * sum(p.numel() for p in student.parameters())  # float32 weights, no optimiser state
    return _finish(result, out_dir, split, {
        "method": "smerf-student", "student": str(student_dir), "num_submodels": n, "disk_bytes": param_bytes,
        "peak_submodel_bytes": param_bytes // n, "config": meta["distill"]})


def bake_record(assets: Path) -> dict:
    """``bake.json`` of a baked folder: the partition and the world-to-viewer transform that evaluation against a
    dataset needs."""
    path = Path(assets) / "bake.json"
    if not path.is_file():
        raise AssetError(f"{path}: missing; evaluating against a dataset needs the world-to-viewer transform that "
                         "nerfbake bake records there (use `nerfbake smerf render` for other asset directories)")
    return json.loads(path.read_text())


def evaluate_assets(assets: str | Path, data: str | Path | None = None, split: str = "test",
                    max_views: int | None = None, write_images: bool = True, step_mult: int = 1,
                    downscale: float | None = None) -> dict:
    """Quality of baked assets on ``split`` of ``data`` (the dataset ``bake.json`` records when None), rendered
    by the viewer-exact renderer at ``step_mult`` x the viewer's step; metrics, ms per frame, submodels, bytes."""
    assets = Path(assets)
    record = bake_record(assets)
    partition = Partition.from_json(record["partition"])
    scene = SceneAssets.open(assets)
    if data is None:
        data = record.get("data")
    ds = load_dataset(data, downscale=downscale or record.get("downscale", 1.0), normalize=record.get("normalize", "auto"))
    out_dir = assets.with_name(assets.name + "_eval")

    def render(cam, bg):
        partition.assign(cam.origin[None], strict=True)  # a clear error for cameras outside the cube
        return render_baked(scene, viewer_camera(cam, partition), step_mult=step_mult)

    result = evaluate_views(render, ds, split, max_views, out_dir / split if write_images else None, desc="baked")
    summary = asset_summary(assets)
    return _finish(result, out_dir, split, {
        "method": "smerf-baked", "assets": str(assets), "num_submodels": summary["num_submodels"],
        "disk_bytes": summary["disk_bytes"], "peak_submodel_bytes": summary["peak_submodel_bytes"],
        "format_problems": summary["format_problems"]})
