"""Bad input gets one clear line naming the file and the fix, never a traceback."""
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from nerfbake.data.errors import DatasetError
from nerfbake.data.formats import load_dataset


def tiny_blender(root, n=3, size=8):
    (root / "train").mkdir(parents=True)
    frames = []
    for i in range(n):
        Image.fromarray(np.full((size, size, 4), 128, np.uint8)).save(root / "train" / f"r_{i}.png")
        pose = np.eye(4)
        pose[2, 3] = 4 + i
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": pose.tolist()})
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return root


def cli(*args):
    return subprocess.run([sys.executable, "-m", "nerfbake", *map(str, args)], capture_output=True, text=True)


def assert_one_line_error(proc, *fragments):
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert "Traceback" not in proc.stderr
    for frag in fragments:
        assert frag in lines[0], lines[0]


def test_missing_image(tmp_path):
    root = tiny_blender(tmp_path / "scene")
    (root / "train" / "r_1.png").unlink()
    assert_one_line_error(cli("data", "info", root, "--json"), "r_1.png", "image file is missing")


def test_corrupt_image(tmp_path):
    root = tiny_blender(tmp_path / "scene")
    (root / "train" / "r_2.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    ds = load_dataset(root)  # headers of other images are fine; the bad one fails when read
    with pytest.raises(DatasetError, match=r"r_2\.png: (cannot decode|not a readable) image"):
        ds.image(2)
    (root / "train" / "r_0.png").write_bytes(b"garbage")
    assert_one_line_error(cli("data", "info", root, "--json"), "r_0.png", "not a readable image")


def test_transforms_without_frames(tmp_path):
    root = tiny_blender(tmp_path / "scene")
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    assert_one_line_error(cli("data", "info", root), "transforms_train.json", "no 'frames'")
    (root / "transforms_train.json").write_text("{ not json")
    assert_one_line_error(cli("data", "info", root), "transforms_train.json", "not valid JSON")


def test_bad_pose_matrix(tmp_path):
    root = tiny_blender(tmp_path / "scene")
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"][1]["transform_matrix"] = [[1, 0], [0, 1]]
    (root / "transforms_train.json").write_text(json.dumps(meta))
    assert_one_line_error(cli("data", "info", root), "frame 1", "4x4")


def test_llff_pose_image_count_mismatch(tmp_path, fern):
    root = tmp_path / "fern"
    shutil.copytree(fern / "images_8", root / "images_8")
    shutil.copy(fern / "poses_bounds.npy", root / "poses_bounds.npy")
    sorted((root / "images_8").iterdir())[-1].unlink()
    assert_one_line_error(cli("data", "info", root), "images_8", "19 images but poses_bounds.npy has 20 poses")


def test_transforms_unknown_camera_model(tmp_path):
    root = tmp_path / "ngp"
    (root / "images").mkdir(parents=True)
    Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(root / "images" / "a.jpg")
    meta = {"fl_x": 10, "w": 8, "h": 6, "camera_model": "EQUIRECTANGULAR",
            "frames": [{"file_path": "images/a.jpg", "transform_matrix": np.eye(4).tolist()}]}
    (root / "transforms.json").write_text(json.dumps(meta))
    assert_one_line_error(cli("data", "info", root), "transforms.json", "unknown camera_model 'EQUIRECTANGULAR'")


def test_transforms_per_frame_intrinsics_and_explicit_splits(tmp_path):
    root = tmp_path / "ns"
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(4):
        Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(root / "images" / f"{i}.png")
        fr = {"file_path": f"images/{i}.png", "transform_matrix": np.eye(4).tolist()}
        if i == 3:
            fr.update({"fl_x": 20.0, "fl_y": 21.0, "cx": 4.5, "cy": 3.5, "k1": 0.1})
        frames.append(fr)
    meta = {"fl_x": 10.0, "fl_y": 10.0, "cx": 4, "cy": 3, "w": 8, "h": 6, "frames": frames,
            "train_filenames": ["images/0.png", "images/1.png"], "test_filenames": ["images/3.png"]}
    (root / "transforms.json").write_text(json.dumps(meta))
    ds = load_dataset(root, normalize="none")
    assert ds.splits == {"train": [0, 1], "test": [3]}
    assert ds.frames[0].camera.fx == 10 and ds.frames[3].camera.fy == 21 and ds.frames[3].camera.model == "OPENCV"
    assert ds.frames[3].camera.distortion == {"k1": 0.1}


def test_not_a_dataset(tmp_path):
    assert_one_line_error(cli("data", "info", tmp_path), "no dataset found")
    assert_one_line_error(cli("data", "info", tmp_path / "nope"), "no such dataset directory")
