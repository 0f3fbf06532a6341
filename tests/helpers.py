"""Small configurations shared by several test modules."""
import pytest
import torch

from nerfbake.fields.hash_sh import HashSHConfig
from nerfbake.fields.nerf_sh import NeRFSHConfig
from nerfbake.smerf.run import DistillConfig
from nerfbake.smerf.student import StudentConfig
from nerfbake.teacher.models import HashTeacherConfig, NeRFSHTeacherConfig
from nerfbake.teacher.presets import TeacherTrainConfig


def tiny_config(field="hash", steps=6):
    return TeacherTrainConfig(
        field=field, preset="test", steps=steps, batch_rays=256, lr=1e-2, lr_final=1e-3, warmup_steps=2,
        checkpoint_every=3,
        hash=HashTeacherConfig(HashSHConfig(levels=4, log2_table=12, max_res=64, hidden=16, sh_degree=2),
                               grid_resolution=32, render_steps=128, grid_update_every=2),
        nerf_sh=NeRFSHTeacherConfig(NeRFSHConfig(num_freqs=4, depth=2, width=32, skip=1, sh_degree=2),
                                    coarse_samples=8, fine_samples=8, sparsity_points=64),
    )




# Kernel tests run on the CPU everywhere and also on CUDA where a GPU is present (the same kernels, built for it).
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
devices = pytest.mark.parametrize("device", DEVICES)


def tiny_distill_config(steps=60) -> DistillConfig:
    return DistillConfig(preset="test", steps=steps, batch_patches=64, checkpoint_every=20, val_every=0, warmup_steps=5,
                         empty_space_points=4096,
                         student=StudentConfig(sparse_resolution=32, triplane_resolution=128))


def run_nerfbake(args: list[str], processes: int = 1) -> None:
    """``nerfbake ARGS`` in a subprocess, under ``torchrun`` with that many CPU processes (gloo) when > 1."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {**os.environ, "NERFBAKE_THREADS": "1"}
    launcher = [sys.executable] if processes == 1 else [str(Path(sys.executable).with_name("torchrun")), "--standalone",
                                                        "--nproc_per_node", str(processes)]
    proc = subprocess.run([*launcher, "-m", "nerfbake", *args], env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]


def one_and_two_processes(args: list[str], one, two) -> None:
    """Run ``nerfbake ARGS --out ONE`` in one process and under ``torchrun`` with 2 CPU processes into TWO."""
    run_nerfbake([*args, "--out", str(one)])
    run_nerfbake([*args, "--out", str(two)], processes=2)
