"""Outputs appear whole or not at all, with the modes the umask gives, and cleanups never touch a live writer's work."""
import json
import os
import stat
import subprocess
import sys

import numpy as np
import pytest

from nerfbake import atomic
from nerfbake.octree.io import write_npz
from nerfbake.train.loop import RunLog, save_checkpoint, trim_log


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_files_get_the_umask_modes_not_tempfiles_0600(tmp_path):
    old = os.umask(0o022)
    try:
        atomic.write_json(tmp_path / "a.json", {"x": 1})
        write_npz(tmp_path / "t.npz", {"a": np.zeros(3)}, compress=True)
        save_checkpoint(tmp_path / "c.pt", {"step": 1})
        with atomic.atomic_folder(tmp_path / "out") as tmp:
            (tmp / "f").write_text("x")
    finally:
        os.umask(old)
    assert atomic.FILE_MODE == 0o666 & ~atomic.UMASK
    for f in ("a.json", "t.npz", "c.pt"):
        assert mode(tmp_path / f) == atomic.FILE_MODE, f
    assert mode(tmp_path / "out") == atomic.DIR_MODE
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "c.pt", "out", "t.npz"]  # no temporaries left


def test_a_failed_write_leaves_the_old_output_and_no_temporaries(tmp_path):
    atomic.write_text(tmp_path / "r.json", "old")
    with pytest.raises(RuntimeError):
        with atomic.atomic_file(tmp_path / "r.json") as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert (tmp_path / "r.json").read_text() == "old"
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic.atomic_folder(tmp_path / "out", overwrite=True) as tmp:
            (tmp / "new").write_text("half")
            raise RuntimeError("killed")
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["keep"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "r.json"]


def test_a_folder_is_refused_unless_overwrite_then_swapped_whole(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old").write_text("x")
    with pytest.raises(atomic.OutputExistsError, match="--overwrite"):
        with atomic.atomic_folder(out):
            pass
    with atomic.atomic_folder(out, overwrite=True) as tmp:
        (tmp / "new").write_text("y")
        assert (out / "old").exists()  # the old output stays until the new one is complete
    assert [p.name for p in out.iterdir()] == ["new"]
    atomic.check_output_folder(tmp_path / "empty_or_missing", overwrite=False)


def test_stale_temporaries_of_dead_processes_go_live_ones_stay(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        (tmp_path / f".out.tmp-{dead_pid}-abc123").mkdir()
        (tmp_path / f".out.tmp-{live.pid}-def456").mkdir()  # a concurrent writer at work
        (tmp_path / ".other.tmp-1-aaaaaa").mkdir()  # another output's: not ours to judge
        atomic.remove_stale_temps(tmp_path / "out")
        assert sorted(p.name for p in tmp_path.iterdir()) == [".other.tmp-1-aaaaaa", f".out.tmp-{live.pid}-def456"]
    finally:
        live.kill()


def test_a_resumed_log_holds_each_step_once(tmp_path):
    log = tmp_path / "metrics.jsonl"
    lines = [json.dumps({"step": s, "loss": 1.0}) for s in (25, 50, 75, 100)]
    log.write_text("\n".join(lines) + "\n" + '{"step": 125, "lo')  # killed mid-write after the step-50 checkpoint
    run = RunLog(tmp_path, start_step=50)
    run.train({"step": 75, "loss": 0.5})
    run.close()
    steps = [json.loads(line)["step"] for line in log.read_text().splitlines()]
    assert steps == [25, 50, 75]
    trim_log(log, 0)
    assert log.read_text() == ""
