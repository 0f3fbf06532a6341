"""A SMERF student folder as an artifact: its config (with the presets), its layout (``config.json`` beside
``student.pt``) and its loader. Baking, evaluation and the seam check read students through this module, not
through the trainer (``smerf/distill.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field
import json
from pathlib import Path

from nerfbake.errors import RunFolderError, read_folder_config, reading
from nerfbake.smerf.partition import Partition
from nerfbake.smerf.student import Student, StudentConfig
from nerfbake.train.loop import RUN_CONFIG, load_checkpoint

CHECKPOINT = "student.pt"
CONFIG = RUN_CONFIG


@dataclass
class DistillConfig:
    """Everything distillation depends on: K, steps and batch, learning rates, loss weights and schedules, culling,
    and the student's own sizes (``student``)."""
    preset: str = "cpu-small"
    k: int = dc_field(default=1, metadata={"help": "submodels per axis (default 1)"})
    steps: int = dc_field(default=5000, metadata={"help": "distillation steps (default: the preset's)"})
    steps_per_submodel: bool = dc_field(default=False, metadata={
        "help": "run --steps for every alive submodel (K > 1), as the paper gives each its whole budget; by default "
                "the submodels share them"})
    batch_patches: int = dc_field(default=512, metadata={"help": "3x3 patches per step (512: 4608 rays)"})
    lr_grid: float = 5e-2
    lr_grid_final: float = 2e-3
    lr_mlp: float = 5e-3
    lr_mlp_final: float = 5e-4
    warmup_steps: int = 100
    rgb_mult: float = 1.0
    dssim_mult: float = 1.5
    mse_warmup: float = 0.15  # fraction of the run with an MSE colour loss first (see distill's docstring)
    geometry_mult: tuple[float, float] = (0.015, 0.001)  # linear over the run
    opacity_mult: float = 1.0  # per-ray |opacity_student - opacity_teacher| (see the module docstring)
    mlp_tv_mult: float = 0.1
    empty_space_mult: float = 1.0
    empty_space_points: int = 1 << 15
    consistency_mult: float = 1.0  # K > 1 only
    jitter_origin: float = 0.03  # Gaussian sigma, partition-cube units (per ray)
    jitter_direction: float = 0.03  # per patch
    reassign_fraction: float = 0.2
    downscale: float | None = dc_field(default=None, metadata={
        "help": "image downscale of the training photos (default: the teacher's)"})
    warm_start: bool = True  # start the sparse density from the teacher's (distill.warm_start_density)
    core_quantile: float = 0.1  # K = 1: the share of the training views' surfaces kept in the core (Partition)
    core_fill_quantile: float = 0.0  # K = 1: the share of them grown to fill the core, for an object (Partition)
    cull_alpha: tuple[float, float] = (5e-4, 5e-3)
    cull_window: tuple[float, float] = (0.4, 0.8)  # fractions of the run over which culling ramps up
    quantize: bool = True
    seed: int = 0
    checkpoint_every: int = 500
    val_every: int = 500
    tensorboard: bool = False
    student: StudentConfig = dc_field(default_factory=StudentConfig)

    def total_steps(self, num_alive: int) -> int:
        """Steps the run takes: ``steps``, or ``steps`` per alive submodel. Shared steps give each of N submodels 1/N
        of the rays; on the two-room scene at K = 2 that left each room's submodel fitting its training rays worse
        than K = 1's one submodel fits both."""
        return self.steps * (num_alive if self.steps_per_submodel else 1)

    def cull_threshold(self, step: int) -> float:
        a, b = (int(f * self.steps) for f in self.cull_window)
        if step < a:
            return 0.0
        frac = min(1.0, (step - a) / max(1, b - a))
        lo, hi = self.cull_alpha
        return lo ** (1 - frac) * hi ** frac

    def geometry_weight(self, step: int) -> float:
        frac = min(1.0, step / max(1, self.steps))
        return self.geometry_mult[0] + (self.geometry_mult[1] - self.geometry_mult[0]) * frac


def distill_preset(name: str, k: int = 1) -> DistillConfig:
    """``cpu-small`` (S = 256 at K = 1, 128 above, 6500 steps) or ``paper`` (SMERF's 50k steps at S = 512, T =
    2048)."""
    if name == "cpu-small":
        # S = 256 at K = 1 (the authors' 12 GB-GPU config pairs it with T = 1024) and 6500 steps. lego_400, 25 test
        # views, teacher 32.33 dB: S = 128 / 5000 steps (21 min on 2 cores) gave a student of 30.64; S = 256 / 5000
        # (27 min) 31.18, baked 30.79; S = 256 / 6500 (34 min) 31.47, baked 31.03. Training holds ~2.2 GB per alive
        # submodel at S = 256 (weights, gradients, Adam's two moments), so K > 1, whose submodels each cover less
        # space, stays at S = 128. The core grown to fill an object (core_fill_quantile 0.98; it never shrinks the
        # core, so rooms and real captures keep theirs): lego, one MLP, teacher 32.43, student 31.48 -> 31.83, baked
        # 31.42 -> 31.82, at the cost of finer viewer steps through the object (546 against 518 ms a frame in the
        # Python viewer-exact renderer).
        sparse = 256 if k == 1 else 128
        return DistillConfig(preset=name, k=k, steps=6500, core_fill_quantile=0.98,
                             student=StudentConfig(sparse_resolution=sparse))
    if name == "paper":  # SMERF's 50k steps of 65k rays at R = 2048 / L = 512 (explicit grids need ~17 GB per submodel)
        return DistillConfig(preset=name, k=k, steps=50_000, batch_patches=7282, checkpoint_every=5000, val_every=5000,
                             cull_window=(0.4, 0.8),
                             student=StudentConfig(sparse_resolution=512, triplane_resolution=2048, mlp_grid=5))
    raise ValueError(f"unknown preset {name!r}; choose cpu-small or paper")


def config_from_dict(d: dict) -> DistillConfig:
    """The config recorded in a student's ``config.json`` (lists back to tuples)."""
    d = dict(d)
    d.setdefault("warm_start", False)  # students distilled before the option started cold
    student = StudentConfig(**d.pop("student"))
    for key in ("geometry_mult", "cull_alpha", "cull_window"):
        d[key] = tuple(d[key])
    return DistillConfig(**d, student=student)


def config_from_file(path: str | Path):
    """The distillation config in a JSON file: a run's ``config.json`` (its ``"distill"`` entry) or a bare config."""
    with reading(path, RunFolderError, "pass a run's config.json or a distillation config written as JSON"):
        d = json.loads(Path(path).read_text())
        return config_from_dict(d.get("distill", d))


def load_student(path: str | Path) -> tuple[Student, DistillConfig, dict]:
    """(student, config, folder metadata) from a student folder, with clear errors."""
    path = Path(path)
    meta = read_folder_config(path, CONFIG, "student folder", "nerfbake distill", lambda m: m.get("kind") == "smerf-student")
    with reading(path / CONFIG, RunFolderError, "pass the folder written by nerfbake distill, or distill again"):
        cfg = config_from_dict(meta["distill"])
        student = Student(cfg.student, Partition.from_json(meta["partition"]), cfg.seed)
    state = load_checkpoint(path / CHECKPOINT)
    with reading(path / CHECKPOINT, RunFolderError, "its config.json and checkpoint do not match; distill again"):
        student.load_state_dict(state["model"])
    return student.eval(), cfg, meta
