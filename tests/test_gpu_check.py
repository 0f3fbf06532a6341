"""benchmarks/gpu_check.sh: without CUDA every part is reported skipped (exit 0); its time box stops a trainer the way
Ctrl-C does, so what was learnt in the time is kept."""
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import gpu_check  # noqa: E402


@pytest.mark.skipif(torch.cuda.is_available(), reason="on a GPU machine the script runs its ten minutes of GPU work")
def test_without_cuda_every_part_is_skipped_with_the_reason(tmp_path):
    r = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_check.sh"), "--out", str(tmp_path / "gc")],
                       capture_output=True, text=True, env={"PYTHON": sys.executable, "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    parts = ("kernel_tests", "hash_teacher", "nerf_sh_paper", "octree_render", "viewer_gpu")
    assert summary["cuda"] is False
    assert all(summary[p]["status"] == "skipped" and "no CUDA" in summary[p]["reason"] for p in parts)
    assert "no CUDA device" in r.stderr and not (tmp_path / "gc").exists()


def test_the_time_box_interrupts_like_ctrl_c(tmp_path):
    child = textwrap.dedent("""
        import signal, sys, time
        signal.signal(signal.SIGINT, lambda *a: (print('{"stopped": true}'), sys.exit(0)))
        print("training", file=sys.stderr, flush=True)
        time.sleep(60)
    """)
    r = gpu_check.run_timeboxed([sys.executable, "-c", child], tmp_path / "log", budget_s=1.5)
    assert r["interrupted"] and r["returncode"] == 0 and r["seconds"] < 30
    assert gpu_check.last_json("progress {not json\n" + r["stdout"]) == {"stopped": True}
    assert "training" in (tmp_path / "log").read_text()


def test_psnr_curve_reads_a_run_log(tmp_path):
    lines = [json.dumps({"step": 25 * i, "psnr": 10 + i, "time": 100.0 + i}) for i in range(1, 40)]
    (tmp_path / "metrics.jsonl").write_text("\n".join(lines + ['{"step": 1000, "val_psnr": 3}']) + "\n")
    curve = gpu_check.psnr_curve(tmp_path, points=5)
    assert curve[0] == [25, 11, 0.0] and curve[-1] == [975, 49, 38.0] and 5 <= len(curve) <= 7
