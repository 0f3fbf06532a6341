"""``nerfbake pipeline``: teacher -> PlenOctree (build, fine-tune, compress) -> SMERF (distil, bake) -> evaluation of
every method on the same held-out views -> report.

Each stage writes into its own folder under the run and a record ``RUN/stages/<name>.json`` (its result, the
settings it ran with, the seconds it took, and a fingerprint: a hash of the settings it depends on, of the data's
files for the teacher, and of the fingerprints of the stages it reads). A re-run skips a finished stage whose
fingerprint is unchanged and resumes an interrupted one: teacher training and distillation continue from their last
checkpoint, file-producing stages write to a temporary name and rename, so a crash never leaves a file that looks
finished. A stage whose fingerprint changed (a different ``--teacher-steps``, ``--octree-grid``, ``--eval-views``,
data...) runs again from scratch, and so does everything downstream of it, each saying why.

Under ``torchrun`` the training stages (teacher, distillation) run data-parallel on every rank, octree building
deals its grid slabs, cameras and leaf chunks out over the ranks, and baking its submodels; the other stages run on
rank 0 while the other ranks wait at a barrier.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

from nerfbake.data.formats import load_dataset
from nerfbake.data.synth import SynthConfig, render_dataset
from nerfbake.errors import NerfbakeError, RunFolderError
from nerfbake.octree.build import build_octree, build_preset, unbuildable_reason
from nerfbake.octree.compress import compress_tree
from nerfbake.octree.evaluate import evaluate_tree
from nerfbake.octree.io import load_tree
from nerfbake.octree.optimize import optimize_preset, optimize_tree
from nerfbake.progress import progress_bar
from nerfbake.report import write_report
from nerfbake.smerf.bake import bake_student
from nerfbake.smerf.distill import distill
from nerfbake.smerf.evaluate import evaluate_assets, evaluate_student
from nerfbake.smerf.run import distill_preset
from nerfbake.teacher.clearance import CameraClearance
from nerfbake.teacher.evaluate import evaluate_teacher
from nerfbake.teacher.presets import preset
from nerfbake.teacher.run import CHECKPOINT, load_teacher
from nerfbake.teacher.train import train_teacher
from nerfbake.train.loop import RUN_CONFIG, DataParallel, git_revision, run_complete, write_json_atomic

METHODS = ("octree", "smerf")
# Photos larger than this on their long side are downscaled by a power of two when no --downscale is given (the
# ``images_N/`` folders written by ``nerfbake process`` and shipped with LLFF/mip-NeRF 360 data are used for them).
WORKING_SIZE = {"cpu-small": 800, "paper": 1600}


@dataclass
class PipelineConfig:
    data: str
    out: str
    preset: str = "cpu-small"
    methods: tuple[str, ...] = METHODS
    k: int = 1
    field: str = "hash"
    downscale: float | None = None  # None: automatic, from the photos' size and the preset's WORKING_SIZE
    downscale_why: str = ""  # how the downscale was chosen (filled in by run_pipeline)
    normalize: str | None = None  # the teacher's scene normalisation; None: its own (auto: decided from the cameras)
    eval_views: int | None = 25  # evenly spaced test views (None: the whole split)
    # Overrides of the presets (None keeps the preset's value); the demo uses them to fit in minutes.
    teacher_steps: int | None = None
    octree_grid: int | None = None
    octree_box_scale: float | None = None  # unbounded scenes only (octree build --box-scale); bounded ones ignore it
    octree_epochs: int | None = None
    octree_lr: float | None = None
    distill_steps: int | None = None
    student_sparse: int | None = None
    student_triplane: int | None = None
    bake_stride: int = 2
    timing_repeats: int = 1
    # Whole training configs instead of the presets (tests use tiny ones).
    teacher: object | None = None
    distill: object | None = None


@dataclass
class Stage:
    name: str
    method: str  # "teacher", "octree" or "smerf": which --methods entry needs it
    run: Callable[["PipelineConfig", Path], dict]
    parallel: bool = False  # every rank takes part (data-parallel training); otherwise rank 0 only
    keys: tuple[str, ...] = ()  # the PipelineConfig fields its result depends on (with the preset they resolve its config)
    after: tuple[str, ...] = ()  # the stages whose outputs it reads
    output: str | None = None  # folder under the run that a changed stage starts afresh in (trainers resume otherwise)


def resolve_downscale(cfg: PipelineConfig) -> tuple[float, str]:
    """(downscale, why): the one every stage trains and evaluates at. An explicit ``--downscale`` (or a whole teacher
    config's) wins; otherwise the smallest power of two that brings the photos' long side within the preset's
    working size (readers count their ``images_N/`` folders in: fern's images_8 is already 8)."""
    if cfg.downscale is not None:
        return float(cfg.downscale), f"--downscale {cfg.downscale:g}"
    if cfg.teacher is not None:
        return float(cfg.teacher.downscale), "the teacher config's downscale"

    ds = load_dataset(cfg.data)
    cam = ds.frames[0].camera
    longest, limit = max(cam.width, cam.height), WORKING_SIZE.get(cfg.preset, 800)
    factor = 1
    while longest / factor > limit:
        factor *= 2
    total = ds.downscale * factor
    if factor == 1:
        return total, f"{cam.width}x{cam.height} images fit the {cfg.preset} preset's {limit} px (downscale {total:g})"
    return total, (f"{cam.width}x{cam.height} images are over the {cfg.preset} preset's {limit} px on the long side: "
                   f"downscale {total:g} ({cam.width // factor}x{cam.height // factor}); --downscale 1 keeps them whole")


def skip_reason(stage: Stage, run: Path) -> str | None:
    """Why a method cannot run on this scene (the pipeline then skips its stages with that one line), or None:
    the octree route where :func:`unbuildable_reason` finds no box to cover."""
    if stage.method != "octree":
        return None
    meta = json.loads((run / "teacher" / RUN_CONFIG).read_text())
    train = meta["train"]
    cameras = load_dataset(meta["data"], downscale=train["downscale"], normalize=train["normalize"]).cameras("train")
    return unbuildable_reason(meta, CameraClearance.of_teacher(meta, cameras))


# --- stages ---------------------------------------------------------------------------------------------------------

def teacher_config(cfg: PipelineConfig):
    t = cfg.teacher or preset(cfg.field, cfg.preset)
    if cfg.teacher_steps:
        t.steps = cfg.teacher_steps
    if cfg.downscale is not None:
        t.downscale = cfg.downscale
    if cfg.normalize is not None:
        t.normalize = cfg.normalize
    return t


def teacher_normalize(run: Path) -> str:
    """The normalisation the run's teacher was trained in: trees live in its frame, so fine-tuning and evaluating
    them must load the photos the same way."""
    return json.loads((run / "teacher" / RUN_CONFIG).read_text())["train"].get("normalize", "auto")


def require_complete(folder: Path) -> None:
    """Trainers catch Ctrl-C to save a checkpoint and return; the pipeline must not record such a stage as done."""
    if not run_complete(folder):
        raise KeyboardInterrupt(f"{folder}: training stopped before its last step; re-run the pipeline to resume")


def run_teacher(cfg: PipelineConfig, run: Path) -> dict:
    train_teacher(cfg.data, run / "teacher", teacher_config(cfg), resume=True)
    require_complete(run / "teacher")
    return {"run": str(run / "teacher")}


def eval_teacher(cfg: PipelineConfig, run: Path) -> dict:
    res = evaluate_teacher(run / "teacher", "test", cfg.eval_views)
    model = load_teacher(run / "teacher")[0]
    weights = 4 * sum(p.numel() for p in model.parameters())
    ckpt = run / "teacher" / CHECKPOINT
    return {"method": f"teacher ({cfg.field})", **metrics_of(res), "ms_per_frame": 1000 * res["seconds_per_view"],
            "memory_bytes": weights, "disk_bytes": ckpt.stat().st_size, "images": str(run / "teacher" / "eval" / "test")}


def octree_paths(run: Path) -> dict[str, Path]:
    d = run / "octree"
    return {"raw": d / "tree.npz", "optimized": d / "tree_opt.npz", "compressed": d / "tree_c.npz"}


def run_octree_build(cfg: PipelineConfig, run: Path) -> dict:
    b = build_preset(cfg.preset)
    if cfg.octree_grid:
        b = replace(b, grid=cfg.octree_grid, autoscale_grid=max(8, min(b.autoscale_grid, cfg.octree_grid // 2)))
    if cfg.octree_box_scale and json.loads((run / "teacher" / RUN_CONFIG).read_text())["box"].get("contracted"):
        b = replace(b, box_scale=cfg.octree_box_scale)
    return build_octree(run / "teacher", octree_paths(run)["raw"], b)


def run_octree_optimize(cfg: PipelineConfig, run: Path) -> dict:
    o = optimize_preset(cfg.preset)
    if cfg.octree_epochs is not None:  # 0: no fine-tuning (the route's figure on bonsai moved 0.00 dB in an epoch)
        o = replace(o, epochs=cfg.octree_epochs)
    if cfg.octree_lr:
        o = replace(o, lr=cfg.octree_lr)
    o = replace(o, downscale=cfg.downscale or 1.0, normalize=teacher_normalize(run))
    p = octree_paths(run)
    res = optimize_tree(p["raw"], cfg.data, p["optimized"], o)
    return {k: v for k, v in res.items() if k != "history"} | {"history": res.get("history", [])}


def run_octree_compress(cfg: PipelineConfig, run: Path) -> dict:
    p = octree_paths(run)
    return compress_tree(p["optimized"], p["compressed"], data=cfg.data, downscale=cfg.downscale or 1.0,
                         normalize=teacher_normalize(run)) or {}


def eval_octree(cfg: PipelineConfig, run: Path) -> dict:
    out = {}
    normalize = teacher_normalize(run)
    for name, path in octree_paths(run).items():
        r = evaluate_tree(path, cfg.data, "test", cfg.eval_views, downscale=cfg.downscale or 1.0, repeats=cfg.timing_repeats,
                          normalize=normalize)
        tree = load_tree(path)
        resident = 4 * (tree.data.numel() + tree.child.numel())  # what the renderers hold (float32 leaves)
        out[name] = {"method": f"PlenOctree {name}", **metrics_of(r), "ms_per_frame": r["ms_per_frame"],
                     "memory_bytes": resident, "disk_bytes": r["file_bytes"],
                     "num_leaves": r["num_leaves"], "device": r.get("device"),
                     "images": str(path.parent / f"{path.stem}_eval" / "test")}
    return out


def distill_config(cfg: PipelineConfig):
    d = replace(cfg.distill, k=cfg.k) if cfg.distill else distill_preset(cfg.preset, k=cfg.k)
    d.student = replace(d.student)  # the overrides below must not reach the caller's config
    if cfg.distill_steps:
        d.steps = cfg.distill_steps
        d.warmup_steps = min(d.warmup_steps, max(1, d.steps // 10))  # a short run still leaves its warm-up
    if cfg.student_sparse:
        d.student.sparse_resolution = cfg.student_sparse
    if cfg.student_triplane:
        d.student.triplane_resolution = cfg.student_triplane
    return d


def run_distill(cfg: PipelineConfig, run: Path) -> dict:
    distill(run / "teacher", run / "smerf" / "student", distill_config(cfg), resume=True)
    require_complete(run / "smerf" / "student")
    return {"student": str(run / "smerf" / "student")}


def eval_student(cfg: PipelineConfig, run: Path) -> dict:
    r = evaluate_student(run / "smerf" / "student", cfg.data, "test", cfg.eval_views)
    return {"method": "SMERF student", **metrics_of(r), "ms_per_frame": r["ms_per_frame"],
            "memory_bytes": r["peak_submodel_bytes"], "disk_bytes": r["disk_bytes"], "num_submodels": r["num_submodels"],
            "images": str(run / "smerf" / "student" / "eval" / "test")}


def run_bake(cfg: PipelineConfig, run: Path) -> dict:
    return bake_student(run / "smerf" / "student", run / "smerf" / "assets", stride=cfg.bake_stride, overwrite=True)


def eval_assets(cfg: PipelineConfig, run: Path) -> dict:
    r = evaluate_assets(run / "smerf" / "assets", cfg.data, "test", cfg.eval_views)
    return {"method": "SMERF baked", **metrics_of(r), "ms_per_frame": r["ms_per_frame"],
            "memory_bytes": r["peak_submodel_bytes"], "disk_bytes": r["disk_bytes"], "num_submodels": r["num_submodels"],
            "images": str(run / "smerf" / "assets_eval" / "test")}


def metrics_of(r: dict) -> dict:
    net = r.get("lpips_net", "vgg")
    return {"psnr": r["psnr"], "ssim": r["ssim"], "lpips": r[f"lpips_{net}"], "lpips_net": net, "num_views": r["num_views"]}


EVAL_KEYS = ("data", "downscale", "eval_views", "timing_repeats")
STAGES = [
    Stage("teacher", "teacher", run_teacher, parallel=True,
          keys=("data", "preset", "field", "downscale", "normalize", "teacher_steps", "teacher"), output="teacher"),
    Stage("teacher_eval", "teacher", eval_teacher, keys=EVAL_KEYS, after=("teacher",)),
    Stage("octree_build", "octree", run_octree_build, parallel=True, keys=("preset", "octree_grid", "octree_box_scale"),
          after=("teacher",)),
    Stage("octree_optimize", "octree", run_octree_optimize,
          keys=("data", "preset", "downscale", "octree_epochs", "octree_lr"), after=("octree_build",)),
    Stage("octree_compress", "octree", run_octree_compress, after=("octree_optimize",)),
    Stage("octree_eval", "octree", eval_octree, keys=EVAL_KEYS, after=("octree_build", "octree_optimize", "octree_compress")),
    Stage("distill", "smerf", run_distill, parallel=True,
          keys=("preset", "k", "distill_steps", "student_sparse", "student_triplane", "distill"), after=("teacher",),
          output="smerf/student"),
    Stage("student_eval", "smerf", eval_student, keys=EVAL_KEYS, after=("distill",)),
    Stage("bake", "smerf", run_bake, parallel=True, keys=("bake_stride",), after=("distill",)),
    Stage("assets_eval", "smerf", eval_assets, keys=EVAL_KEYS, after=("bake",)),
]


# --- running -----------------------------------------------------------------------------------------------------------

def stage_record(run: Path, name: str, complete_only: bool = True) -> dict | None:
    path = run / "stages" / f"{name}.json"
    if path.is_file():
        try:
            rec = json.loads(path.read_text())
        except json.JSONDecodeError:
            return None
        if isinstance(rec, dict) and (rec.get("complete") or not complete_only):
            return rec
    return None


def data_fingerprint(data: str | Path) -> list:
    """What identifies a dataset cheaply: its resolved path and the size and mtime of its top-level and ``sparse/*``
    files (poses, intrinsics, point clouds live there; images are named by them)."""
    root = Path(data).resolve()
    base = root if root.is_dir() else root.parent
    files = [p for p in base.iterdir() if p.is_file()] if base.is_dir() else []
    files += [p for p in base.glob("sparse/*/*") if p.is_file()]
    return [str(root)] + sorted([str(p.relative_to(base)), p.stat().st_size, p.stat().st_mtime_ns] for p in files)


# Settings added after runs were recorded, with the value that means "not given": at that value they are left out
# of the fingerprint, so a finished stage of an earlier version is not redone for a setting it could not have had.
ADDED_SETTINGS = {"normalize": None, "octree_box_scale": None}


def stage_settings(stage: Stage, settings: dict) -> dict:
    return {k: settings[k] for k in stage.keys if k not in ADDED_SETTINGS or settings[k] != ADDED_SETTINGS[k]}


def fingerprints(stages: list[Stage], settings: dict) -> dict[str, str]:
    out = {}
    for stage in stages:
        body = {"settings": stage_settings(stage, settings), "after": [out.get(a) for a in stage.after]}
        if stage.name == "teacher":
            body["data_files"] = data_fingerprint(settings["data"])
        out[stage.name] = hashlib.sha256(json.dumps(body, sort_keys=True, default=str).encode()).hexdigest()[:16]
    return out


def why_changed(stage: Stage, old: dict, settings: dict, rerun: set[str]) -> str:
    """One line: which settings or upstream stages make a recorded stage stale."""
    if "fingerprint" not in old:
        return "recorded by an older nerfbake without stage fingerprints"
    before = old.get("settings", {})
    now = json.loads(json.dumps(stage_settings(stage, settings), default=str))  # as recorded: tuples become lists
    short = lambda v: (r if len(r := repr(v)) <= 60 else r[:57] + "...")  # noqa: E731 -- whole configs are long
    diffs = [f"{k} {short(before.get(k))} -> {short(now[k])}" for k in now if before.get(k) != now[k]]
    ups = [a for a in stage.after if a in rerun]
    parts = ([", ".join(diffs)] if diffs else []) + ([f"{', '.join(ups)} ran again"] if ups else [])
    return "; ".join(parts) or "its data files changed"


def recorded_data_name(run: Path, data: str | Path) -> str:
    """``data`` as this run's teacher stage recorded it when both name the same folder (one relative, one absolute, or
    spelled otherwise), so naming the dataset another way does not retrain a finished teacher; else ``data``
    resolved. (The teacher's fingerprint also holds the data files' identity, so this only forgives the name.)"""
    here = Path(data).resolve()
    old = ((stage_record(run, "teacher", complete_only=False) or {}).get("settings") or {}).get("data")
    return old if isinstance(old, str) and Path(old).resolve() == here else str(here)


def run_pipeline(cfg: PipelineConfig, stop_after: str | None = None, log: Callable[[str], None] = print) -> dict:
    """Run (or resume) every stage the chosen methods need; returns the collected results (``RUN/results.json``)."""
    for m in cfg.methods:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r} in --methods; choose from {', '.join(METHODS)}")
    run = Path(cfg.out)
    dp = DataParallel()
    stages = [s for s in STAGES if s.method == "teacher" or s.method in cfg.methods]
    names = [s.name for s in stages]
    if stop_after is not None and stop_after not in names:
        raise NerfbakeError(f"--stop-after {stop_after!r}: no such stage in this run; choose one of {', '.join(names)}")
    downscale, why = resolve_downscale(cfg)
    cfg = replace(cfg, downscale=downscale, downscale_why=why, data=recorded_data_name(run, cfg.data))
    log(f"pipeline: {why}")
    settings = asdict(cfg)
    prints = fingerprints(stages, settings)
    if dp.is_main:
        run.mkdir(parents=True, exist_ok=True)
        write_json_atomic(run / "pipeline.json", {"config": settings, "stages": names})
    t_start = time.perf_counter()
    said = set()  # methods whose skip reason was printed
    rerun: set[str] = set()  # stages run in this invocation (their dependants are stale)
    for i, stage in enumerate(stages, 1):
        prefix = f"pipeline [{i}/{len(stages)}] {stage.name}"
        record = {"fingerprint": prints[stage.name], "settings": stage_settings(stage, settings)}
        old = stage_record(run, stage.name, complete_only=False)
        if old is not None and old.get("fingerprint") == prints[stage.name] and old.get("complete"):
            log(f"{prefix}: done before ({old['seconds']:.0f} s), skipped")
            continue
        if old is not None and old.get("fingerprint") != prints[stage.name]:
            log(f"{prefix}: runs again: {why_changed(stage, old, settings, rerun)}")
            if dp.is_main and stage.output and (run / stage.output).exists():
                shutil.rmtree(run / stage.output)  # a stale training run must not be resumed
            dp.barrier()
        rerun.add(stage.name)
        reason = skip_reason(stage, run)
        if reason is not None:
            log(f"{prefix}: skipped" + (f" (the {stage.method} route, above)" if stage.method in said else f": {reason}"))
            said.add(stage.method)
            if dp.is_main:
                write_json_atomic(run / "stages" / f"{stage.name}.json",
                                  {"complete": True, "seconds": 0.0, "result": None, "skipped": reason, **record})
            continue
        log(f"{prefix}: running (total elapsed {time.perf_counter() - t_start:.0f} s)")
        if dp.is_main:  # an interrupted stage with this record resumes; one with another fingerprint starts over
            write_json_atomic(run / "stages" / f"{stage.name}.json", {"complete": False, **record})
        t = time.perf_counter()
        result = None
        if stage.parallel or dp.is_main:
            result = stage.run(cfg, run)
        dp.barrier()
        if dp.is_main:
            write_json_atomic(run / "stages" / f"{stage.name}.json", {
                "complete": True, "seconds": time.perf_counter() - t, "result": result, **record})
        dp.barrier()
        if stop_after == stage.name:
            log(f"{prefix}: stopping here as asked")
            return {}
    results = collect_results(run)
    if dp.is_main:
        write_report(run, results)  # with results.json
    dp.barrier()
    return results


def collect_results(run: Path) -> dict:
    """``results.json``: one row per method (quality, speed, memory, disk) plus every stage's record."""
    run = Path(run)
    if not (run / "stages").is_dir():
        raise RunFolderError(f"{run}: no stages/ folder; not a `nerfbake pipeline` run")
    rows = []
    stages = {}
    for stage in STAGES:  # in pipeline order
        rec = stage_record(run, stage.name)
        if rec is not None:
            stages[stage.name] = {"seconds": rec["seconds"], "result": rec["result"],
                                  **({"skipped": rec["skipped"]} if rec.get("skipped") else {})}
    for name in ("teacher_eval", "octree_eval", "student_eval", "assets_eval"):
        res = stages.get(name, {}).get("result")
        if not res:
            continue
        for row in (res.values() if name == "octree_eval" else [res]):
            rows.append(row)
    cfg = json.loads((run / "pipeline.json").read_text())["config"] if (run / "pipeline.json").is_file() else {}

    return {"run": str(run), "config": cfg, "methods": rows, "stages": stages, "git": git_revision()}


def demo_config(out: str, data: str, eval_views: int = 6) -> PipelineConfig:
    """Every stage on the built-in scene, shortened to fit in about ten minutes on two CPU cores.

    The distillation takes twice the steps of half the preset's batch, and a quarter of its empty-space points: at
    the demo's size most of a step's cost does not grow with its rays, and the student gains with steps far more
    than with rays (same teacher at 33.49 dB, S = 64, T = 256, baked PSNR on the 6 test views: 600 steps of 4608
    rays 30.45 dB in 219 s; 1200 of 4608 31.39 in 423 s; 1200 of 2304 31.22 in 367 s, and with 8192 empty-space
    points 31.25 in 209 s; 1600 of 2304 30.96: about 0.3 dB is run-to-run spread). At 600 steps a larger S (128: +0.1
    dB), origin jitter (0.15: -0.1) and the warm start (-0.1; on by default for what it buys real captures and
    K > 1) bought nothing. T = 512 scored 31.67 and 31.74 (with a doubled grid learning rate) but doubles the
    viewer's steps through the scene and adds ~40 s; the demo keeps 256.

    One deferred MLP instead of the 5^3 lattice (the default, :func:`~nerfbake.smerf.student.mlp_lattice_size`)
    and the core grown to fill the objects (``core_fill_quantile`` 0.98, now the cpu-small preset's; factor 4.0) took
    the baked scene from 30.91 / 30.61 dB (seeds 0 / 1, P = 5, factor 2.5) to 32.73 / 32.47, within 1.0 dB of the
    33.50 dB teacher (P = 1 alone: 32.11; the fill alone: 31.44 / 30.85). The fill costs the viewer finer steps
    through the object (the viewer-exact renderer 31 -> 35-41 ms a frame)."""
    distill = replace(distill_preset("cpu-small"), batch_patches=256, empty_space_points=8192)
    return PipelineConfig(data=data, out=out, preset="cpu-small", eval_views=eval_views, teacher_steps=1000,
                          octree_grid=128, octree_epochs=2, octree_lr=1e5, distill_steps=1200, student_sparse=64,
                          student_triplane=256, bake_stride=2, distill=distill)



def run_demo(out: str | Path, width: int = 160, views: int = 48, spp: int = 32, eval_views: int = 6,
             methods: tuple[str, ...] = METHODS, log=print, **overrides) -> dict:
    """``nerfbake demo``: the built-in synthetic scene (rendered once into ``out/scene``), then the whole pipeline with
    :func:`demo_config`'s shortened settings (``overrides``: its step and size fields, None keeps them)."""
    out = Path(out)
    scene_dir = out / "scene"
    scene = SynthConfig(scene="objects", width=width, height=width, views=views, spp=spp, seed=0)
    if not (scene_dir / "transforms_train.json").is_file():
        with progress_bar("demo: synthesize scene", scene.views + 2 * scene.held_out_views, unit="views") as advance:
            render_dataset(scene, scene_dir, progress=lambda d, t: advance())
    cfg = replace(demo_config(str(out), str(scene_dir), eval_views=eval_views), methods=tuple(methods),
                  **{k: v for k, v in overrides.items() if v is not None})
    return run_pipeline(cfg, log=log)
