"""``teacher train | eval | render``."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from nerfbake.commands.spec import JSON, OVERWRITE, PRESETS, Command, config_overrides, option


@dataclass(kw_only=True)
class TeacherTrain(Command):
    name = "teacher train"
    help = "train a teacher (presets: cpu-small = 2-core CPU in minutes; paper = GPU scale)"
    data: str = option(help="a dataset folder (any format nerfbake data info reads)")
    out: str = option(help="the run folder to write")
    field: str = option("hash", "hash: hash-grid SH field, fast (default); nerf-sh: the PlenOctrees NeRF-SH MLP",
                        choices=("hash", "nerf-sh"))
    preset: str = option("cpu-small", choices=PRESETS)
    overrides: dict = config_overrides("nerfbake.teacher.presets:TeacherTrainConfig", "steps", "batch_rays", "downscale",
                                       "normalize", "appearance")
    seed: int = option(0)
    resume: bool = option(False, "continue from RUN/checkpoint.pt")
    config: str | None = option(None, "training config JSON (e.g. another run's config.json) instead of a preset")
    tensorboard: bool = option(False, "also write TensorBoard scalars to RUN/tensorboard")

    def run(self) -> None:
        from nerfbake.teacher.presets import preset
        from nerfbake.teacher.run import config_from_file
        from nerfbake.teacher.train import train_teacher

        cfg = config_from_file(self.config) if self.config else preset(self.field, self.preset)
        cfg = replace(cfg, **self.overrides, seed=self.seed, tensorboard=cfg.tensorboard or self.tensorboard)
        train_teacher(self.data, self.out, cfg, resume=self.resume)


def scores_line(result: dict) -> str:
    """``PSNR .. SSIM .. LPIPS-net ..``: the start of every evaluation's one-line summary."""
    return (f"PSNR {result['psnr']:.2f}  SSIM {result['ssim']:.4f}  "
            f"LPIPS-{result['lpips_net']} {result['lpips_' + result['lpips_net']]:.4f}")


@dataclass(kw_only=True)
class TeacherEval(Command):
    name = "teacher eval"
    help = "render a split and print PSNR/SSIM/LPIPS"
    run_folder: str = option(help="a teacher run folder", flag="--run")
    split: str = option("test")
    max_views: int | None = option(None)
    json: bool = option(False, JSON)
    no_images: bool = option(False, "score without writing the renders")
    appearance_fit: str = option("none", "half: fit an affine colour map on each held-out photo's left half, score its "
                                 "right half (NeRF-W's protocol for photos with their own exposure)",
                                 choices=("none", "half"))

    def run(self) -> dict:
        from nerfbake.teacher.evaluate import evaluate_teacher

        return evaluate_teacher(Path(self.run_folder), self.split, self.max_views, write_images=not self.no_images,
                                appearance_fit=self.appearance_fit)

    def text(self, r: dict) -> str:
        return f"{r['split']}: {scores_line(r)}  ({r['num_views']} views, {r['seconds_per_view']:.2f} s/view)"


@dataclass(kw_only=True)
class TeacherRender(Command):
    name = "teacher render"
    help = "render camera poses from a transforms-style JSON"
    run_folder: str = option(help="a teacher run folder", flag="--run")
    pose_file: str = option()
    out: str = option()
    overwrite: bool = option(False, OVERWRITE)

    def run(self) -> str:
        from nerfbake.teacher.evaluate import render_poses

        written = render_poses(Path(self.run_folder), Path(self.pose_file), Path(self.out), overwrite=self.overwrite)
        return f"wrote {len(written)} images to {self.out}"
