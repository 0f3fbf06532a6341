import json
import subprocess
import sys

import numpy as np
import pytest

from nerfbake.cli import main
from nerfbake.data import images


def test_demo_synthesises_runs_the_pipeline_and_writes_the_report(tmp_path):
    """The demo's own plumbing on a 4-view scene (the SMERF stages need more steps than this test affords: a
    60-step teacher leaves the student nothing to bake; tests/test_pipeline.py runs them with tiny configs)."""
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "nerfbake", "demo", "--out", str(out), "--width", "48",
                           "--views", "4", "--spp", "4", "--teacher-steps", "60", "--eval-views", "1", "--octree-grid", "32",
                           "--methods", "octree"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout[proc.stdout.index('{\n  "scene"'): proc.stdout.rindex("}") + 1])
    assert res["scene"]["format"] == "blender" and res["scene"]["splits"]["train"] == 4
    assert (out / "scene" / "transforms_test.json").is_file()
    rows = {r["method"]: r for r in res["methods"]}
    assert set(rows) == {"teacher (hash)", "PlenOctree raw", "PlenOctree optimized", "PlenOctree compressed"}
    assert all(r["num_views"] == 1 and r["psnr"] > 5 for r in rows.values())
    assert rows["PlenOctree compressed"]["disk_bytes"] < rows["PlenOctree raw"]["disk_bytes"]
    assert (out / "report.md").is_file() and "nerfbake view" in proc.stderr


def test_downscaled_images_are_cached_on_disk(tmp_path, monkeypatch, lego):
    monkeypatch.setenv("NERFBAKE_CACHE", str(tmp_path / "cache"))
    path = lego / "test" / "r_3.png"
    a = images.load_image_uint8(path, (100, 100))
    cached = list((tmp_path / "cache" / "images").glob("*.npy"))
    assert len(cached) == 1
    np.testing.assert_array_equal(np.load(cached[0]), a)
    monkeypatch.setattr(images, "_MEMORY_CACHE", images.ImageCache())  # a fresh process: served from disk
    np.testing.assert_array_equal(images.load_image_uint8(path, (100, 100)), a)


def test_every_command_keeps_its_recorded_flags(capsys):
    """Flags are contracts other tools call. The parser's commands and flags must equal tests/cli_flags.json, and
    each command's ``--help`` must list them; after a deliberate change re-record with
    ``python -m tests.cli_flags > tests/cli_flags.json``."""
    from pathlib import Path

    from nerfbake.cli import build_parser
    from tests.cli_flags import command_flags

    recorded = json.loads((Path(__file__).parent / "cli_flags.json").read_text())
    now = command_flags(build_parser())
    assert sorted(now) == sorted(recorded), "commands added or removed"
    for command, flags in recorded.items():
        assert now[command] == flags, f"{command}: flags changed ({sorted(set(flags) ^ set(now[command]))})"
        argv = [] if command == "nerfbake" else command.split()
        with pytest.raises(SystemExit) as exc:
            main([*argv, "--help"])
        assert exc.value.code == 0
        text = capsys.readouterr().out
        missing = [f for f in flags if f not in text]
        assert missing == [], f"`nerfbake {command} --help` does not list {missing}"


def test_a_command_runs_from_python_as_from_the_command_line(fern, capsys):
    """The command dataclasses are the CLI: the same options give the same result without a command line."""
    from nerfbake.commands import DataInfo

    assert main(["data", "info", str(fern), "--json", "--downscale", "2"]) == 0
    assert json.loads(capsys.readouterr().out) == DataInfo(path=str(fern), downscale=2.0).run()


def test_preset_override_flags_come_from_the_stage_configs(capsys):
    """``--grid`` is BuildConfig.grid: its help is the field's, and a flag not given leaves the preset's value."""
    from dataclasses import fields

    from nerfbake.cli import build_parser, command_from
    from nerfbake.octree.build import BuildConfig

    with pytest.raises(SystemExit):
        main(["octree", "build", "--help"])
    grid_help = next(f for f in fields(BuildConfig) if f.name == "grid").metadata["help"]
    assert " ".join(grid_help.split()) in " ".join(capsys.readouterr().out.split())
    argv = ["octree", "build", "--teacher", "t", "--out", "o.npz", "--grid", "64", "--no-autoscale"]
    assert command_from(build_parser(argv).parse_args(argv)).overrides == {"grid": 64, "autoscale": False}
