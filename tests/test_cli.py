import json
import subprocess
import sys

import numpy as np

from nerfbake.data import images


def test_demo_synthesises_and_summarises(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "nerfbake", "demo", "--out", str(out), "--width", "48",
                           "--views", "4", "--spp", "4", "--teacher-steps", "60", "--eval-views", "1", "--octree-grid", "32"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout[proc.stdout.index("{"): proc.stdout.rindex("}") + 1])
    assert res["scene"]["format"] == "blender" and res["scene"]["splits"]["train"] == 4
    assert res["teacher"]["num_views"] == 1 and res["teacher"]["psnr"] > 5
    assert (out / "scene" / "transforms_test.json").is_file()
    assert set(res["octree"]) == {"raw", "optimized", "compressed"} and res["octree"]["optimized"]["psnr"] > 5
    assert res["octree"]["compressed"]["file_bytes"] < res["octree"]["raw"]["file_bytes"]


def test_downscaled_images_are_cached_on_disk(tmp_path, monkeypatch, lego):
    monkeypatch.setenv("NERFBAKE_CACHE", str(tmp_path / "cache"))
    path = lego / "test" / "r_3.png"
    a = images.load_image_uint8(path, (100, 100))
    cached = list((tmp_path / "cache" / "images").glob("*.npy"))
    assert len(cached) == 1
    np.testing.assert_array_equal(np.load(cached[0]), a)
    monkeypatch.setattr(images, "_MEMORY_CACHE", images.ImageCache())  # a fresh process: served from disk
    np.testing.assert_array_equal(images.load_image_uint8(path, (100, 100)), a)
