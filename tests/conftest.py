"""Shared fixtures: the ../shared data folder (skip with a reason when a user's clone lacks it)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

SHARED = Path(os.environ.get("NERFBAKE_SHARED", Path(__file__).resolve().parents[2] / "shared"))
DATA = SHARED / "data"

# Keep the downscale cache of test runs out of the user's home.
os.environ.setdefault("NERFBAKE_CACHE", tempfile.mkdtemp(prefix="nerfbake-test-cache-"))


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
