"""Shared fixtures: the ../shared data folder (skip with a reason when a user's clone lacks it)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest
import torch

SHARED = Path(os.environ.get("NERFBAKE_SHARED", Path(__file__).resolve().parents[2] / "shared"))
DATA = SHARED / "data"

# Keep the downscale cache of test runs out of the user's home.
os.environ.setdefault("NERFBAKE_CACHE", tempfile.mkdtemp(prefix="nerfbake-test-cache-"))


@pytest.fixture(autouse=True)
def ieee_subnormals_after_each_test():
    """A trainer flushes subnormal floats to zero for the rest of its process (``kernels.flush_denormals``), and a
    test process runs many trainers; hypothesis refuses to draw floats while the main thread flushes them. Each
    test starts with IEEE subnormals on the main thread, as a fresh process does."""
    yield
    torch.set_flush_denormal(False)


def shared_data(name: str) -> Path:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"needs ../shared/data/{name} (present in CI, absent in a user's clone)")
    return path


@pytest.fixture(scope="session")
def lego() -> Path:
    return shared_data("lego_400")


@pytest.fixture(scope="session")
def fern() -> Path:
    return shared_data("fern")


@pytest.fixture(scope="session")
def fox() -> Path:
    return shared_data("fox")


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 32x32 Mitsuba scene (6 training views): enough for teachers and trees to learn something in seconds."""
    from nerfbake.data.synth import SynthConfig, render_dataset

    return render_dataset(SynthConfig("objects", 32, 32, views=6, spp=4, seed=0), tmp_path_factory.mktemp("tiny") / "scene")


@pytest.fixture(scope="session")
def tiny_teacher(tiny_scene, tmp_path_factory) -> Path:
    """A hash teacher trained 150 steps on ``tiny_scene`` (shared by the octree and SMERF tests)."""
    from dataclasses import replace

    from nerfbake.teacher.train import train_teacher
    from tests.helpers import tiny_config

    cfg = replace(tiny_config(steps=150), checkpoint_every=1000, val_every=10_000)
    return train_teacher(tiny_scene, tmp_path_factory.mktemp("teacher") / "run", cfg)


@pytest.fixture(scope="session")
def tiny_tree(tiny_teacher, tmp_path_factory) -> Path:
    """A PlenOctree (32^3 grid) built from ``tiny_teacher``."""
    from nerfbake.octree.build import BuildConfig, build_octree

    out = tmp_path_factory.mktemp("tree") / "tree.npz"
    build_octree(tiny_teacher, out, BuildConfig(grid=32, samples_per_leaf=8, autoscale_grid=16, weight_thresh=0.01))
    return out


@pytest.fixture(scope="session")
def tiny_student(tiny_teacher, tmp_path_factory) -> Path:
    from nerfbake.smerf.distill import distill
    from tests.helpers import tiny_distill_config

    return distill(tiny_teacher, tmp_path_factory.mktemp("student") / "s", tiny_distill_config())


@pytest.fixture(scope="session")
def tiny_assets_dir(tiny_student, tmp_path_factory) -> Path:
    """``tiny_student`` baked into the official viewer's asset layout."""
    from nerfbake.smerf.bake import bake_student

    out = tmp_path_factory.mktemp("assets") / "baked"
    bake_student(tiny_student, out, stride=1)
    return out


@pytest.fixture(scope="session")
def rooms_teacher(tmp_path_factory) -> Path:
    """A tiny hash teacher on the two-room synthetic scene (cameras spread over a K = 2 partition)."""
    from dataclasses import replace

    from nerfbake.data.synth import SynthConfig, render_dataset
    from nerfbake.teacher.train import train_teacher
    from tests.helpers import tiny_config

    scene = render_dataset(SynthConfig("rooms", 32, 32, views=12, spp=4, seed=0), tmp_path_factory.mktemp("rooms") / "scene")
    cfg = replace(tiny_config(steps=80), checkpoint_every=1000, val_every=10_000)
    return train_teacher(scene, tmp_path_factory.mktemp("rooms_teacher") / "run", cfg)


@pytest.fixture(scope="session")
def rooms_k3(rooms_teacher, tmp_path_factory) -> tuple[Path, Path]:
    """(student, baked assets) of a K = 3 distillation of ``rooms_teacher``: four alive submodels (at K = 2 the
    partition gives each room one, too few to test streaming and eviction), 5 steps for each of them."""
    from dataclasses import replace

    from nerfbake.smerf.bake import bake_student
    from nerfbake.smerf.distill import distill
    from tests.helpers import tiny_distill_config

    root = tmp_path_factory.mktemp("rooms_k3")
    student = distill(rooms_teacher, root / "student", replace(tiny_distill_config(steps=5), k=3,
                                                                steps_per_submodel=True))
    bake_student(student, root / "assets")
    return student, root / "assets"
