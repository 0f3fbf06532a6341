"""The resumable pipeline on a tiny scene: every method evaluated, a report written, an interrupted distillation
resumed, and the report's numbers equal to the per-stage evaluations."""
import json
import os
from dataclasses import replace

from nerfbake.cli import main
from nerfbake.pipeline import PipelineConfig, distill_config, run_pipeline
from tests.helpers import tiny_config, tiny_distill_config


def tiny_pipeline(scene, out, **kw) -> PipelineConfig:
    kw = {"eval_views": 2, **kw}
    return PipelineConfig(data=str(scene), out=str(out), teacher=replace(tiny_config(steps=40), checkpoint_every=1000),
                          distill=replace(tiny_distill_config(steps=30), checkpoint_every=5), octree_grid=32,
                          octree_epochs=1, octree_lr=1e5, bake_stride=1, **kw)


def test_pipeline_resumes_an_interrupted_distillation_and_reports_every_method(tiny_scene, tmp_path, capsys):
    from nerfbake.smerf.distill import distill

    run = tmp_path / "run"
    cfg = tiny_pipeline(tiny_scene, run)
    assert run_pipeline(cfg, stop_after="octree_eval") == {}
    assert not (run / "stages" / "distill.json").exists()
    # "Ctrl-C" in the middle of distillation: a checkpoint at step 10 of 30, the run not complete
    distill(run / "teacher", run / "smerf" / "student", distill_config(cfg), stop_at=10)
    assert not json.loads((run / "smerf" / "student" / "config.json").read_text())["complete"]
    log = []
    results = run_pipeline(cfg, log=log.append)
    assert any("teacher: done before" in line for line in log) and any("octree_eval: done before" in line for line in log)
    assert json.loads((run / "smerf" / "student" / "config.json").read_text())["complete"]
    methods = [r["method"] for r in results["methods"]]
    assert methods == ["teacher (hash)", "PlenOctree raw", "PlenOctree optimized", "PlenOctree compressed",
                       "SMERF student", "SMERF baked"]
    for r in results["methods"]:
        assert r["psnr"] > 10 and r["ms_per_frame"] > 0 and r["disk_bytes"] > 0 and r["memory_bytes"] > 0
    # the report's numbers are the per-stage evaluation outputs
    assets_eval = json.loads((run / "smerf" / "assets_eval" / "results_test.json").read_text())
    assert results["methods"][-1]["psnr"] == assets_eval["psnr"]
    teacher_eval = json.loads((run / "teacher" / "eval" / "results_test.json").read_text())
    assert results["methods"][0]["psnr"] == teacher_eval["psnr"]
    report = (run / "report.md").read_text()
    assert "| SMERF baked |" in report and "nerfbake view" in report
    for png in ("quality_vs_time.png", "quality_vs_disk.png", "strip.png", "training.png"):
        assert (run / "report" / png).stat().st_size > 1000, png
    # `nerfbake report` rewrites it from the stage records alone
    (run / "report.md").unlink()
    assert main(["report", str(run)]) == 0 and (run / "report.md").is_file()
    assert main(["report", str(tmp_path)]) == 2  # not a pipeline run: a clear error
    assert "not a `nerfbake pipeline` run" in capsys.readouterr().err


def test_a_changed_setting_reruns_its_stage_and_everything_downstream_and_says_why(tiny_scene, tmp_path):
    import pytest

    from nerfbake.errors import NerfbakeError

    run = tmp_path / "run"
    run_pipeline(tiny_pipeline(tiny_scene, run, methods=("octree",)), stop_after="teacher_eval")
    teacher_ckpt = (run / "teacher" / "checkpoint.pt").stat().st_mtime_ns
    log = []
    run_pipeline(tiny_pipeline(tiny_scene, run, methods=("octree",), eval_views=3), stop_after="teacher_eval", log=log.append)
    assert any("teacher: done before" in line for line in log), log
    assert any("teacher_eval: runs again: eval_views 2 -> 3" in line for line in log), log
    assert json.loads((run / "stages" / "teacher_eval.json").read_text())["result"]["num_views"] == 3
    assert (run / "teacher" / "checkpoint.pt").stat().st_mtime_ns == teacher_ckpt
    log = []  # the same dataset named another way (relative, with a trailing "/.") is the same teacher
    renamed = os.path.relpath(tiny_scene) + "/."
    run_pipeline(replace(tiny_pipeline(tiny_scene, run, methods=("octree",), eval_views=3), data=renamed),
                 stop_after="teacher_eval", log=log.append)
    assert any("teacher: done before" in line for line in log) and any("teacher_eval: done before" in line for line in log), log
    log = []
    run_pipeline(tiny_pipeline(tiny_scene, run, methods=("octree",), eval_views=3, teacher_steps=20),
                 stop_after="teacher_eval", log=log.append)
    assert any("teacher: runs again: teacher_steps None -> 20" in line for line in log), log
    assert any("teacher_eval: runs again: teacher ran again" in line for line in log), log
    assert json.loads((run / "teacher" / "config.json").read_text())["steps_done"] == 20  # trained afresh, not resumed
    with pytest.raises(NerfbakeError, match="no such stage.*teacher_eval"):
        run_pipeline(tiny_pipeline(tiny_scene, run), stop_after="octree_evaluate")
    with pytest.raises(ValueError, match="unknown method"):
        run_pipeline(tiny_pipeline(tiny_scene, tmp_path / "x", methods=("nerf",)))


def test_two_process_pipeline_equals_one(tiny_scene, tmp_path):
    """`torchrun --nproc_per_node 2 -m nerfbake pipeline ...` (gloo, data-parallel training stages, the rest on
    rank 0) gives the figures the 1-process run gives."""
    from nerfbake.train.loop import write_json_atomic
    from tests.helpers import one_and_two_processes

    write_json_atomic(tmp_path / "teacher.json", replace(tiny_config(steps=6), checkpoint_every=1000))
    write_json_atomic(tmp_path / "distill.json", tiny_distill_config(steps=4))
    args = ["pipeline", "--data", str(tiny_scene), "--teacher-config", str(tmp_path / "teacher.json"),
            "--distill-config", str(tmp_path / "distill.json"), "--eval-views", "1", "--octree-grid", "16",
            "--octree-epochs", "1", "--octree-lr", "1e5", "--bake-stride", "1"]
    one_and_two_processes(args, tmp_path / "one", tmp_path / "two")
    assert json.loads((tmp_path / "two" / "smerf" / "assets" / "bake.json").read_text())["ranks"] == 2
    a, b = (json.loads((tmp_path / r / "results.json").read_text())["methods"] for r in ("one", "two"))
    assert [r["method"] for r in a] == [r["method"] for r in b] and len(a) == 6
    for ra, rb in zip(a, b):
        assert abs(ra["psnr"] - rb["psnr"]) < 0.05, (ra["method"], ra["psnr"], rb["psnr"])


def test_photos_over_the_working_size_are_downscaled_and_why_is_said(fox, fern):
    from nerfbake.pipeline import resolve_downscale

    factor, why = resolve_downscale(PipelineConfig(data=str(fox), out="unused"))
    assert factor == 4 and "1080x1920" in why and "270x480" in why  # 1920 / 2 = 960 is still over 800
    assert resolve_downscale(PipelineConfig(data=str(fox), out="unused", preset="paper"))[0] == 2
    assert resolve_downscale(PipelineConfig(data=str(fern), out="unused"))[0] == 8  # images_8 already fits
    assert resolve_downscale(PipelineConfig(data=str(fox), out="unused", downscale=1))[0] == 1


def test_a_setting_added_later_leaves_earlier_fingerprints_as_they_were():
    """A run recorded before --normalize existed resumes without redoing its teacher when --normalize is not given,
    and giving it runs the teacher again."""
    from nerfbake.pipeline import STAGES, fingerprints

    settings = vars(PipelineConfig(data=".", out="unused"))
    before = [replace(s, keys=tuple(k for k in s.keys if k != "normalize")) for s in STAGES]  # the older stage table
    assert fingerprints(STAGES, settings) == fingerprints(before, settings)
    assert fingerprints(STAGES, {**settings, "normalize": "none"})["teacher"] != fingerprints(before, settings)["teacher"]
    # the same for --octree-box-scale, which only the octree build (and what follows it) reads
    before = [replace(s, keys=tuple(k for k in s.keys if k != "octree_box_scale")) for s in STAGES]
    assert fingerprints(STAGES, settings) == fingerprints(before, settings)
    wide = fingerprints(STAGES, {**settings, "octree_box_scale": 2.5})
    old = fingerprints(before, settings)
    assert wide["octree_build"] != old["octree_build"] and wide["teacher"] == old["teacher"]


def test_a_method_that_cannot_run_on_a_scene_is_skipped_with_a_reason(tiny_scene, tmp_path):
    from nerfbake.pipeline import STAGES, skip_reason
    from nerfbake.train.loop import write_json_atomic

    octree = next(s for s in STAGES if s.name == "octree_build")
    smerf = next(s for s in STAGES if s.name == "distill")
    for kind, contracted, near, skipped in [("forward-facing", True, 0.1, "forward-facing"),
                                            ("unbounded-360", True, 0.1, None), ("object-centric", False, 2.0, None),
                                            ("unbounded-360", True, 100.0, "near bound")]:
        box = {"box_min": [-1.0] * 3, "box_max": [1.0] * 3, "near": near, "contracted": contracted}
        write_json_atomic(tmp_path / "teacher" / "config.json",
                          {"box": box, "dataset": {"scene_kind": kind}, "data": str(tiny_scene),
                           "train": {"downscale": 1.0, "normalize": "auto"}})
        reason = skip_reason(octree, tmp_path)
        assert (reason is not None) == bool(skipped) and skip_reason(smerf, tmp_path) is None
        if skipped:
            assert skipped in reason and "SMERF" in reason


def test_a_pipeline_killed_at_random_moments_resumes_to_the_uninterrupted_results(tiny_scene, tmp_path):
    """SIGKILL (no chance to clean up) at three random moments, then a run to the end: the same figures as a run
    never interrupted, and no temporary files left behind."""
    import os
    import random
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    code = ("import sys; from pathlib import Path; from tests.test_pipeline import tiny_pipeline; "
            "from nerfbake.pipeline import run_pipeline; "
            "run_pipeline(tiny_pipeline(Path(sys.argv[1]), Path(sys.argv[2])), log=lambda line: None)")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}

    def start(out):
        return subprocess.Popen([sys.executable, "-c", code, str(tiny_scene), str(out)], cwd=root, env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    t = time.perf_counter()
    whole = start(tmp_path / "whole")
    assert whole.wait() == 0, whole.stderr.read()
    seconds = time.perf_counter() - t
    rng = random.Random(0)
    killed = tmp_path / "killed"
    for _ in range(3):
        proc = start(killed)
        time.sleep(rng.uniform(0.1, 0.9) * seconds)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    proc = start(killed)
    assert proc.wait() == 0, proc.stderr.read()

    def figures(run):
        rows = json.loads((run / "results.json").read_text())["methods"]
        return {r["method"]: (round(r["psnr"], 4), round(r["ssim"], 5), r["num_views"]) for r in rows}

    assert figures(killed) == figures(tmp_path / "whole")
    leftovers = [p for p in killed.rglob(".*") if ".tmp-" in p.name or ".old-" in p.name]
    assert not leftovers, leftovers
