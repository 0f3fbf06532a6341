"""``distill``, ``bake`` and ``smerf info | eval | render``."""
from __future__ import annotations

from dataclasses import dataclass, replace

from nerfbake.commands.spec import JSON, OVERWRITE, PRESETS, Command, config_overrides, option
from nerfbake.commands.teacher import scores_line


@dataclass(kw_only=True)
class Distill(Command):
    name = "distill"
    help = "distil a teacher into SMERF submodels (K^3 camera partition)"
    teacher: str = option(help="a teacher run folder")
    out: str = option(help="the student folder to write")
    preset: str = option("cpu-small", choices=PRESETS)
    config: str | None = option(None, "a student's config.json (or a bare distillation config) instead of --preset")
    overrides: dict = config_overrides("nerfbake.smerf.run:DistillConfig", "k", "steps", "steps_per_submodel",
                                       "batch_patches", "downscale")
    resume: bool = option(False, "continue from OUT's checkpoint")
    tensorboard: bool = option(False, "also write TensorBoard scalars to OUT/tensorboard")

    def run(self) -> None:
        from nerfbake.smerf.distill import distill
        from nerfbake.smerf.run import config_from_file, distill_preset

        cfg = config_from_file(self.config) if self.config else distill_preset(self.preset, self.overrides.get("k", 1))
        cfg = replace(cfg, **self.overrides, tensorboard=cfg.tensorboard or self.tensorboard)
        distill(self.teacher, self.out, cfg, resume=self.resume)


@dataclass(kw_only=True)
class Bake(Command):
    name = "bake"
    help = "bake a student into the SMERF web viewer's asset format"
    student: str = option(help="a folder written by nerfbake distill")
    out: str = option(help="the asset folder to write (sm_XXX/ per submodel)")
    ray_stride: int = option(2, "use every n-th pixel row/column for the alive voxels")
    camera_radius: float = option(1.5, "a submodel's alive voxels come from the training cameras within this many "
                                  "cell widths of its centre (SMERF's 1.5; 0: its own cameras only)")
    overwrite: bool = option(False, OVERWRITE)

    def run(self) -> dict:
        from nerfbake.smerf.bake import bake_student

        return bake_student(self.student, self.out, stride=self.ray_stride, overwrite=self.overwrite,
                            camera_radius=self.camera_radius)

    def text(self, s: dict) -> str:
        return (f"baked {s['num_submodels']} submodel(s) into {self.out} in {s['seconds']:.0f} s "
                f"(render with: nerfbake smerf render --assets {self.out} --out DIR)")


@dataclass(kw_only=True)
class SmerfInfo(Command):
    name = "smerf info"
    help = "summarise a baked asset directory (ours or the official export)"
    assets: str = option(help="folder holding sm_XXX/ (or one sm_XXX folder)", positional=True)
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.smerf.evaluate import asset_summary

        return asset_summary(self.assets)

    def text(self, info: dict) -> str:
        return "\n".join([f"{info['assets']}: {info['num_submodels']} submodel(s) on a {info['grid']}^3 grid, "
                          f"{info['disk_bytes'] / 1e6:.2f} MB on disk (largest submodel "
                          f"{info['peak_submodel_bytes'] / 1e6:.2f} MB)"]
                         + [f"format problem: {msg}" for msg in info["format_problems"]])


@dataclass(kw_only=True)
class SmerfEval(Command):
    name = "smerf eval"
    help = "PSNR/SSIM/LPIPS of a student or of baked assets on a held-out split"
    student: str | None = option(None, "a folder written by nerfbake distill", group="which")
    assets: str | None = option(None, "a folder written by nerfbake bake", group="which")
    data: str | None = option(None, "dataset (default: the one the student was distilled on)")
    split: str = option("test")
    max_views: int | None = option(None)
    downscale: float | None = option(None, "image downscale (default: the one the student was distilled at)")
    no_images: bool = option(False, "score without writing the renders")
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.smerf.evaluate import evaluate_assets, evaluate_student

        evaluate, folder = (evaluate_student, self.student) if self.student else (evaluate_assets, self.assets)
        return evaluate(folder, self.data, self.split, self.max_views, write_images=not self.no_images,
                        downscale=self.downscale)

    def text(self, r: dict) -> str:
        return (f"{r['method']} {r['split']}: {scores_line(r)}  {r['ms_per_frame']:.0f} ms/frame  "
                f"{r['disk_bytes'] / 1e6:.1f} MB")


@dataclass(kw_only=True)
class SmerfRender(Command):
    name = "smerf render"
    help = "render test_frames.json views as the official viewer's shader does"
    assets: str = option()
    out: str = option()
    overwrite: bool = option(False, OVERWRITE)
    frames: str | None = option(None, "a test_frames.json (default: the first submodel's)")
    width: int = option(800)
    height: int = option(500)
    step_mult: int = option(1, "the viewer's stepMult, a whole number >= 1 (2 halves the step)")

    def run(self) -> str:
        from nerfbake.smerf.baked_render import render_frames_to_folder

        written = render_frames_to_folder(self.assets, self.out, self.frames, self.width, self.height, self.step_mult,
                                          self.overwrite)
        return f"wrote {len(written)} images to {self.out}"
