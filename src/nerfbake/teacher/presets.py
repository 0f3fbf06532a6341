"""Training presets. ``cpu-small`` finishes on a 2-core CPU in minutes (tests, demo); ``paper`` is the
paper-scale GPU preset (PlenOctrees' NeRF-SH: 64+128 samples, 1024-ray batches; hash teacher: 2^22-entry
tables, 65k-ray batches, 200k steps as in Zip-NeRF/SMERF)."""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field

from nerfbake.data.normalization import NORMALIZATIONS, NORMALIZE_HELP
from nerfbake.fields.hash_sh import HashSHConfig
from nerfbake.fields.nerf_sh import NeRFSHConfig
from nerfbake.teacher.models import HashTeacherConfig, NeRFSHTeacherConfig


@dataclass
class TeacherTrainConfig:
    field: str = "hash"
    preset: str = "cpu-small"
    steps: int = dc_field(default=3000, metadata={"help": "training steps (default: the preset's)"})
    batch_rays: int = dc_field(default=4096, metadata={"help": "rays per step"})
    lr: float = 1e-2
    lr_final: float = 3e-4  # log-linear schedule only
    lr_schedule: str = "log-linear"  # or "step": constant, x0.33 at 50/75/90% of the steps
    warmup_steps: int = 100
    weight_decay: float = 1e-6
    seed: int = 0
    downscale: float = dc_field(default=1.0, metadata={"help": "image downscale of the training photos"})
    # the scene normalisation (data/normalization NORMALIZATIONS); auto decides from the cameras
    normalize: str = dc_field(default="auto", metadata={"choices": NORMALIZATIONS, "help": NORMALIZE_HELP})
    # Per-image exposure / white-balance corrections (teacher/appearance.py): "affine", "auto" (affine for photographs,
    # none for RGBA renders) or "none". Off by default: scored at the mean appearance, held-out views lost 0.64 dB
    # with them on the phone clip (600 steps: 22.13 vs 22.77) and 0.04 dB on fern.
    appearance: str = dc_field(default="none", metadata={"choices": ("auto", "affine", "none"), "help": (
        "per-image exposure/white-balance corrections (default none; auto: affine for photographs, none for RGBA "
        "renders); held-out views are scored at the mean appearance")})
    # Each training ray's prediction is composited on a random colour (RGBA targets on the same one): the field must
    # be opaque wherever the photos are. False: white.
    random_background: bool = True
    checkpoint_every: int = 500
    val_every: int = 1000
    val_rays: int = 4096
    tensorboard: bool = False  # also write scalars as TensorBoard events to RUN/tensorboard
    hash: HashTeacherConfig = dc_field(default_factory=HashTeacherConfig)
    nerf_sh: NeRFSHTeacherConfig = dc_field(default_factory=NeRFSHTeacherConfig)

    @property
    def model_config(self):
        return self.hash if self.field == "hash" else self.nerf_sh


def preset(field_kind: str, name: str) -> TeacherTrainConfig:
    if field_kind not in ("hash", "nerf-sh"):
        raise ValueError(f"unknown teacher field {field_kind!r}; choose hash or nerf-sh")
    if name == "cpu-small":
        if field_kind == "hash":
            # Checkpoints (~200 MB with Adam's moments) and full validation renders every 1000/2000 steps: together
            # ~20 s of a 20-minute budget at 500/1000.
            # Unbounded scenes: MLPs in bfloat16 on CPUs that have it (bonsai, 800 steps: 23.42 dB held-out against
            # 23.39 in float32, 298 s against 334). Fewer samples than 64 proposal + 32 final lose: 32 + 16 runs at
            # twice the rays/s but, with the stratified draw, scored 23.62 dB on bonsai after 1440 steps against 24.07
            # for 64 + 32 after 800 in the same time (before that draw: 18.08 at 800 steps, 16.23 at 6000).
            return TeacherTrainConfig(field="hash", preset=name, steps=9000, batch_rays=4096, lr=1e-2, lr_schedule="step",
                                      checkpoint_every=1000, val_every=2000,
                                      hash=HashTeacherConfig(HashSHConfig(levels=16, log2_table=19, max_res=1024, sh_degree=3),
                                                             unbounded_mlp_dtype="bfloat16"))
        return TeacherTrainConfig(field="nerf-sh", preset=name, steps=2000, batch_rays=512, lr=5e-4, lr_final=5e-5,
                                  warmup_steps=0, weight_decay=0.0,
                                  nerf_sh=NeRFSHTeacherConfig(NeRFSHConfig(num_freqs=8, depth=4, width=128, skip=2),
                                                              coarse_samples=32, fine_samples=32, sparsity_points=2048))
    if name == "paper":
        if field_kind == "hash":
            return TeacherTrainConfig(field="hash", preset=name, steps=200_000, batch_rays=65536, lr=1e-2, lr_final=1e-3,
                                      checkpoint_every=5000, val_every=10000,
                                      hash=HashTeacherConfig(HashSHConfig(levels=20, log2_table=22, max_res=8192, sh_degree=3),
                                                             grid_resolution=256, render_steps=1024))
        # Density through softplus(x - 1), not PlenOctrees' ReLU: Adam's first updates move every weight by the full
        # rate in the sign of its gradient, and at 8 x 256 that drove the ReLU density below zero everywhere within
        # 3-5 steps, for good (the H100's 12.6-13.3 dB stall). lego_400 at 1/4 size, 256 rays of 32 + 64 samples,
        # this preset's learning-rate schedule, training PSNR at step 300 (one run each): ReLU 13.2 (dead at step 5);
        # ReLU + 500 warm-up steps 19.95; softplus 21.19; softplus + warm-up 19.84; the 4 x 128 cpu-small field
        # 19.81. Held-out, `benchmarks/nerf_sh_convergence.py --steps 400`: 17.11 dB against cpu-small's 16.21.
        return TeacherTrainConfig(field="nerf-sh", preset=name, steps=2_000_000, batch_rays=1024, lr=5e-4, lr_final=5e-6,
                                  warmup_steps=0, weight_decay=0.0, checkpoint_every=10000, val_every=50000,
                                  nerf_sh=NeRFSHTeacherConfig(NeRFSHConfig(density_activation="softplus"),
                                                              coarse_samples=64, fine_samples=128))
    raise ValueError(f"unknown preset {name!r}; choose cpu-small or paper")
