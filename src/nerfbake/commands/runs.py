"""Whole runs and their outputs: ``pipeline``, ``demo``, ``report``, ``view``, ``doctor``."""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from nerfbake.commands.spec import JSON, NORMALIZATIONS, NORMALIZE_HELP, PRESETS, Command, option

METHODS = "comma-separated subset of octree,smerf"


def log_line(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def methods(text: str) -> tuple[str, ...]:
    return tuple(m.strip() for m in text.split(",") if m.strip())


def print_summary(run: Path, results: dict) -> None:
    """The results table of a run and the commands that view each method's output."""
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


@dataclass(kw_only=True)
class Pipeline(Command):
    name = "pipeline"
    help = "teacher -> octree -> SMERF -> evaluation -> report, resumable"
    data: str = option(help="a dataset folder")
    out: str = option(help="the run folder (rerunning resumes it)")
    preset: str = option("cpu-small", "cpu-small: a 2-core CPU in tens of minutes; paper: GPU scale", choices=PRESETS)
    methods: str = option("octree,smerf", METHODS)
    k: int = option(1, "SMERF partition: K^3 submodels")
    eval_views: int = option(25, "evenly spaced test views per evaluation (0: all)")
    normalize: str | None = option(None, NORMALIZE_HELP, choices=NORMALIZATIONS)
    downscale: float | None = option(None, "image downscale for every stage (default: automatic, photos over 800 px on "
                                     "the long side for cpu-small, 1600 for paper, are halved until they fit; images_N/ "
                                     "used)")
    teacher_steps: int | None = option(None)
    distill_steps: int | None = option(None)
    octree_grid: int | None = option(None)
    octree_box_scale: float | None = option(None, "unbounded scenes: the octree covers the teacher's core cube times "
                                            "this (octree build --box-scale); bounded scenes ignore it")
    octree_epochs: int | None = option(None, "octree fine-tuning epochs (default: the preset's; 0 keeps the built "
                                       "tree)")
    octree_lr: float | None = option(None)
    bake_stride: int = option(2)
    teacher_config: str | None = option(None, "a teacher training config JSON (e.g. a run's config.json) instead of "
                                        "the preset")
    distill_config: str | None = option(None, "a distillation config JSON instead of the preset")
    stop_after: str | None = option(None, "stop after this stage (e.g. to test resuming)")

    def run(self) -> dict | None:
        from nerfbake.pipeline import PipelineConfig, run_pipeline
        from nerfbake.smerf.run import config_from_file as distill_config
        from nerfbake.teacher.run import config_from_file as teacher_config

        cfg = PipelineConfig(
            data=self.data, out=self.out, preset=self.preset, methods=methods(self.methods), k=self.k,
            eval_views=self.eval_views or None, teacher_steps=self.teacher_steps, distill_steps=self.distill_steps,
            octree_grid=self.octree_grid, octree_box_scale=self.octree_box_scale, octree_epochs=self.octree_epochs,
            octree_lr=self.octree_lr, bake_stride=self.bake_stride, downscale=self.downscale, normalize=self.normalize,
            teacher=teacher_config(self.teacher_config) if self.teacher_config else None,
            distill=distill_config(self.distill_config) if self.distill_config else None)
        return run_pipeline(cfg, stop_after=self.stop_after, log=log_line)

    def text(self, results: dict | None) -> None:
        if results:
            print_summary(Path(self.out), results)


@dataclass(kw_only=True)
class Demo(Command):
    """Built-in scene -> the whole pipeline with shortened CPU settings -> report and the commands to view each result."""
    name = "demo"
    help = "the whole pipeline on the built-in synthetic scene (CPU, ~10 minutes)"
    out: str = option("outputs/demo")
    width: int = option(160)
    views: int = option(48)
    spp: int = option(32)
    teacher_steps: int | None = option(None, "hash-teacher steps (default 1000)")
    octree_grid: int | None = option(None, "PlenOctree dense grid side (default 128)")
    distill_steps: int | None = option(None, "SMERF distillation steps (default 1200)")
    student_sparse: int | None = option(None, "SMERF sparse grid side S (default 64)")
    student_triplane: int | None = option(None, "SMERF triplane side T (default 256)")
    eval_views: int = option(6)
    methods: str = option("octree,smerf", METHODS)

    def run(self) -> dict:
        from nerfbake.data.formats import load_dataset
        from nerfbake.pipeline import run_demo

        out = Path(self.out)
        results = run_demo(out, self.width, self.views, self.spp, self.eval_views, methods(self.methods), log=log_line,
                           teacher_steps=self.teacher_steps, octree_grid=self.octree_grid,
                           distill_steps=self.distill_steps, student_sparse=self.student_sparse,
                           student_triplane=self.student_triplane)
        print_summary(out, results)
        return {"scene": load_dataset(out / "scene").info(), "methods": results["methods"],
                "report": str(out / "report.md")}

    def text(self, result: dict) -> str:
        return json.dumps(result, indent=2)


@dataclass(kw_only=True)
class Report(Command):
    name = "report"
    help = "write RUN/report.md (table, plots) from a pipeline run"
    run_folder: str = option(help="a pipeline run folder", positional=True, flag="run")

    def run(self) -> str:
        from nerfbake.pipeline import collect_results
        from nerfbake.report import write_report

        return str(write_report(self.run_folder, collect_results(self.run_folder)))


@dataclass(kw_only=True)
class Doctor(Command):
    name = "doctor"
    help = ("what this machine gives nerfbake: Python, torch build and device, Warp, Mitsuba's libLLVM, pycolmap, LPIPS "
            "weights, chromium, free disk")

    def run(self) -> list:
        from nerfbake.doctor import run_checks

        return run_checks()

    def text(self, checks: list) -> str:
        missing = [c.name for c in checks if c.required and not c.ok]
        return "\n".join([c.line() for c in checks]
                         + ["everything nerfbake needs is here" if not missing else f"missing: {', '.join(missing)}"])

    def exit_code(self, checks: list) -> int:
        return 1 if any(c.required and not c.ok for c in checks) else 0


@dataclass(kw_only=True)
class View(Command):
    name = "view"
    help = "serve the web viewer for a baked SMERF folder, a PlenOctree .npz or a splat .ply/.splat (gsplat.js)"
    scene: str = option(help="asset folder (holding sm_XXX/), tree .npz or splat .ply/.splat", positional=True)
    port: int = option(8000)
    host: str = option("127.0.0.1", "0.0.0.0 exposes the viewer to other devices on the network")
    benchmark: bool = option(False, "measure ms/frame at 512x512 and 1280x720 in headless chromium")
    frame_mult: int = option(1, "draws per animation frame while benchmarking")
    frames: int = option(6, "timed animation frames per view")
    warmup: int = option(2, "discarded animation frames per view")
    max_views: int | None = option(None, "benchmark only the first N views (default: every test view)")
    gpu: bool = option(False, "benchmark on the machine's GPU instead of SwiftShader, timed by the GPU "
                       "(EXT_disjoint_timer_query_webgl2) where offered")
    walkthrough: str | None = option(None, "with --benchmark: fly along a camera path (a test_frames.json, "
                                     "{\"frames\": [{position, forward}, ...]}, or 'test' for the scene's test cameras in "
                                     "order) across submodel boundaries at 512x512 and print per-frame times, frames "
                                     "drawn while loading, blank frames, the most submodels resident and the host cache "
                                     "size", metavar="PATH")
    json: bool = option(False, JSON)

    def run(self) -> dict | None:
        from nerfbake.viewer.browser import read_walkthrough, run_benchmark, run_walkthrough
        from nerfbake.viewer.server import ViewerServer, find_scene

        scene = find_scene(self.scene)
        if scene.kind == "splats" and (self.benchmark or self.walkthrough):
            raise ValueError("--benchmark and --walkthrough time our own renderers (SMERF folders and trees); a splat "
                             "file is drawn by gsplat.js: see benchmarks/splat_export.py for its pictures")
        if self.walkthrough and not self.benchmark:
            raise ValueError("--walkthrough flies the viewer headless: give it with --benchmark")
        if self.walkthrough:
            return run_walkthrough(scene, read_walkthrough(self.walkthrough, scene), software_gl=not self.gpu)
        if self.benchmark:
            return run_benchmark(scene, frame_mult=self.frame_mult, frames_per_view=self.frames, warmup=self.warmup,
                                 max_views=self.max_views, software_gl=not self.gpu)
        server = ViewerServer(scene, host=self.host, port=self.port)
        print(f"serving {scene.kind} scene {scene.name} at {server.url}  (Ctrl-C stops)", flush=True)
        if self.host not in ("127.0.0.1", "localhost"):
            print(f"reachable from other devices on this network at http://<this machine's address>:{server.port}/",
                  flush=True)
        try:
            server.httpd.serve_forever()
        finally:
            server.httpd.server_close()

    def text(self, r: dict | None) -> str | None:
        if r is None:
            return None
        if self.walkthrough:
            return (f"{r['frames']} frames: p50 {r['p50_ms']:.1f} ms, p95 {r['p95_ms']:.1f} ms, max {r['max_ms']:.1f} "
                    f"ms; {r['frames_while_loading']} drawn while a submodel loaded, {r['blank_frames']} blank; at most "
                    f"{r['max_resident']} submodels resident, host cache {r['max_host_cache']}; the last camera held "
                    f"{r['held_frames']} frames " + ("until its own submodel was drawn" if r["settled"] else
                                                      "and its own submodel never arrived"))
        return "\n".join(f"{s['width']}x{s['height']}: {s['mean_ms_per_frame']:.2f} ms/frame ({s['fps']:.1f} fps) on "
                         f"{s['renderer']}" for s in r["sizes"])
