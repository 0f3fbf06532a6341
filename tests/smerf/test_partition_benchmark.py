"""benchmarks/smerf_partition.py's paired K-against-K figures (the numbers issue 22's house verdict rests on)."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "smerf_partition.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("smerf_partition", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_paired_differences_over_all_views_and_where_the_teacher_renders(bench):
    teacher = {"a": 30.0, "b": 12.0, "c": 28.0, "d": 26.0}
    by_k = {1: {"a": 29.0, "b": 11.0, "c": 27.0, "d": 25.0},
            2: {"a": 29.5, "b": 6.0, "c": 27.5, "d": 25.2},
            3: {"a": 30.0, "b": 7.0, "c": 27.0, "d": 25.9}}
    out = bench.paired_differences(by_k, teacher, floor=25.0)
    step = np.array([0.5, -5.0, 0.5, 0.2])  # K = 2 - K = 1 on a, b, c, d
    assert out["2-1"]["all"] == {"mean_db": round(step.mean(), 3), "views": 4,
                                 "standard_error_db": round(step.std(ddof=1) / 2, 3)}
    ok = step[[0, 2, 3]]  # b is the teacher's failure: left out of teacher_ok
    assert out["2-1"]["teacher_ok"]["views"] == 3
    assert out["2-1"]["teacher_ok"]["mean_db"] == pytest.approx(ok.mean(), abs=1e-3)
    assert out["2-1"]["all"]["mean_db"] < 0 < out["2-1"]["teacher_ok"]["mean_db"]
    assert set(out) == {"teacher_ok_psnr_by_k", "2-1", "3-2"}
    assert out["teacher_ok_psnr_by_k"] == pytest.approx([27.0, 27.4, 27.6333], abs=1e-3)
    assert out["3-2"]["teacher_ok"]["mean_db"] == pytest.approx(np.mean([0.5, -0.5, 0.7]), abs=1e-3)


def test_paired_differences_with_no_view_over_the_floor(bench):
    out = bench.paired_differences({1: {"a": 10.0}, 2: {"a": 11.0}}, {"a": 12.0}, floor=25.0)
    assert out["teacher_ok_psnr_by_k"] == [None, None]
    assert out["2-1"]["teacher_ok"] == {"mean_db": None, "standard_error_db": None, "views": 0}
    assert out["2-1"]["all"]["standard_error_db"] is None  # one view: no spread
    assert out["2-1"]["all"]["mean_db"] == 1.0


def test_a_stopped_run_of_the_same_values_is_resumed_and_any_other_redone(bench, tmp_path):
    run = tmp_path / "teacher"
    assert bench.run_state(run, "train", "checkpoint.pt", steps=2000) is None  # nothing there
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"train": {"steps": 2000, "lr": 0.01}, "complete": False}))
    assert bench.run_state(run, "train", "checkpoint.pt", steps=2000) is None  # stopped before its first checkpoint
    (run / "checkpoint.pt").write_bytes(b"")
    assert bench.run_state(run, "train", "checkpoint.pt", steps=2000) == "stopped"
    assert bench.run_state(run, "train", "checkpoint.pt", steps=4000) is None  # other values: redone
    assert bench.run_state(run, "distill", "checkpoint.pt", steps=2000) is None  # another kind of run
    (run / "config.json").write_text(json.dumps({"train": {"steps": 2000, "lr": 0.01}, "complete": True}))
    assert bench.run_state(run, "train", "checkpoint.pt", steps=2000) == "finished"
