"""Commands that make and inspect datasets: ``data info``, ``metrics``, ``synth``, ``process``."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from nerfbake.commands.spec import JSON, NORMALIZATIONS, NORMALIZE_HELP, OVERWRITE, Command, option


@dataclass(kw_only=True)
class DataInfo(Command):
    name = "data info"
    help = "summarise a dataset (format auto-detected)"
    path: str = option(positional=True)
    json: bool = option(False, JSON)
    downscale: float = option(1.0, "image downscale factor (intrinsics scale with it)")
    format: str | None = option(None, "skip auto-detection", choices=("blender", "llff", "colmap", "transforms"))
    normalize: str = option("auto", NORMALIZE_HELP, choices=NORMALIZATIONS)

    def run(self) -> dict:
        from nerfbake.data.formats import load_dataset

        return load_dataset(self.path, format=self.format, downscale=self.downscale, normalize=self.normalize).info()

    def text(self, info: dict) -> None:
        from rich.table import Table

        from nerfbake.progress import console

        table = Table(title=f"{info['root']} ({info['format']})", show_header=False)
        for k, v in info.items():
            if k not in ("root", "normalization", "extras"):
                table.add_row(k, str(v))
        table.add_row("normalization", f"{info['normalization']['method']}, scale {info['normalization']['scale']:.4g}")
        console.print(table)


@dataclass(kw_only=True)
class Metrics(Command):
    name = "metrics"
    help = "PSNR, SSIM, LPIPS (alex, vgg) between two images (RGBA on white)"
    image_a: str = option(help="reference image", positional=True)
    image_b: str = option(help="image to score", positional=True)
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.eval.metrics import compare_image_files

        return compare_image_files(self.image_a, self.image_b)

    def text(self, result: dict) -> str:
        return "\n".join(f"{k:10s} {v:.5f}" for k, v in result.items())


@dataclass(kw_only=True)
class Synth(Command):
    name = "synth"
    help = "render a synthetic Blender-format dataset with Mitsuba 3"
    scene: str = option("objects", "the scene (--list shows them)")
    out: str | None = option(None, "dataset folder to write")
    overwrite: bool = option(False, OVERWRITE)
    width: int = option(200)
    height: int = option(200)
    views: int = option(60, "training views (val and test get a quarter each, at least 4)")
    spp: int = option(64, "samples per pixel")
    seed: int = option(0)
    list: bool = option(False, "list the scenes")

    def run(self) -> str:
        from nerfbake.data.synth import SCENES, SynthConfig, render_dataset
        from nerfbake.progress import progress_bar

        if self.list:
            return "\n".join(f"{name:10s} {desc}" for name, desc in SCENES.items())
        if not self.out:
            raise ValueError("synth needs --out DIR (or --list)")
        cfg = SynthConfig(scene=self.scene, width=self.width, height=self.height, views=self.views, spp=self.spp,
                          seed=self.seed)
        held = cfg.held_out_views
        with progress_bar(f"synth {cfg.scene}", cfg.views + 2 * held, unit="views") as advance:
            out = render_dataset(cfg, Path(self.out), progress=lambda done, total: advance(), overwrite=self.overwrite)
        return f"wrote {out} ({cfg.views} train / {held} val / {held} test views, {cfg.width}x{cfg.height})"


@dataclass(kw_only=True)
class Process(Command):
    """Photos or a video -> a posed dataset (pycolmap SfM on the CPU): COLMAP layout + transforms.json."""
    name = "process"
    help = "your own photos or video -> a posed dataset (structure from motion, CPU)"
    images: str | None = option(None, "folder of photos (EXIF orientation honoured; unreadable files are skipped)",
                                group="source")
    video: str | None = option(None, "video file: the sharpest frame of each evenly spaced window is kept", group="source")
    out: str = option(help="dataset folder to create (images/, sparse/0/, transforms.json)")
    overwrite: bool = option(False, OVERWRITE)
    fps: float | None = option(None, "video: frames kept per second of video (default: --max-images in all)")
    max_images: int | None = option(None, "use at most N images, evenly spread (video default 100; folder: all)")
    camera_model: str = option("SIMPLE_RADIAL", "COLMAP camera model, one per video or per EXIF camera",
                               choices=("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"))
    matcher: str | None = option(None, "default: sequential for video, exhaustive for a folder",
                                 choices=("exhaustive", "sequential"))
    downscales: str = option("2,4,8", "also write images_F/ for these factors ('none' for none)")

    def run(self) -> str:
        from nerfbake.data.process import ProcessConfig, parse_downscales, process, summary_lines

        cfg = ProcessConfig(out=Path(self.out), images=Path(self.images) if self.images else None,
                            video=Path(self.video) if self.video else None, fps=self.fps, max_images=self.max_images,
                            camera_model=self.camera_model, matcher=self.matcher,
                            downscales=parse_downscales(self.downscales), overwrite=self.overwrite)
        return "\n".join(summary_lines(process(cfg, log=lambda line: print(line, file=sys.stderr))))
