"""A catalogue of broken inputs, one per row: each CLI command fails with exit 2 and one ``error:`` line that names the
broken file, never a traceback. Rows were found by running them (truncated gzip, missing asset_metadata, a zero
camera angle, ...) and by reading every reader for what it did not check."""
import gzip
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from nerfbake.cli import main
from tests.conftest import shared_data


def smerf_copy(tmp: Path) -> Path:
    assets = tmp / "assets"
    shutil.copytree(shared_data("smerf_tiny"), assets)
    return assets


def tree_copy(tmp: Path, name="good_svox_raw.npz") -> Path:
    tree = tmp / "tree.npz"
    shutil.copy(shared_data("octree_fixtures") / name, tree)
    return tree


def rewrite_npz(path: Path, change) -> Path:
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    np.savez(path.with_suffix(""), **arrays)
    return path


def transforms_scene(tmp: Path, **meta_changes) -> Path:
    root = tmp / "scene"
    root.mkdir()
    frames = []
    for i in range(3):
        Image.fromarray(np.full((8, 8, 3), 100, np.uint8)).save(root / f"{i}.png")
        pose = np.eye(4)
        pose[2, 3] = 3 + i
        frames.append({"file_path": f"{i}.png", "transform_matrix": pose.tolist()})
    meta = {"fl_x": 8.0, "fl_y": 8.0, "w": 8, "h": 8, "frames": frames, **meta_changes}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


# ---- the rows: (id, build(tmp) -> (argv, broken file)) -----------------------------------------------------------

def truncated_mlp(tmp):
    a = smerf_copy(tmp)
    f = a / "sm_000" / "deferred_mlp.json.gz"
    f.write_bytes(f.read_bytes()[:200])
    return ["smerf", "info", a], f


def truncated_params_gz(tmp):
    a = smerf_copy(tmp)
    (a / "sm_000" / "scene_params.json").unlink()
    f = a / "sm_000" / "scene_params.json.gz"
    f.write_bytes(f.read_bytes()[:100])
    return ["smerf", "info", a], f


def params_without_asset_metadata(tmp):
    a = smerf_copy(tmp)
    f = a / "sm_000" / "scene_params.json"
    p = json.loads(f.read_text())
    del p["asset_metadata"]
    f.write_text(json.dumps(p))
    (a / "sm_000" / "scene_params.json.gz").unlink()
    return ["smerf", "render", "--assets", a, "--out", tmp / "r", "--width", 8, "--height", 8], f


def params_not_an_object(tmp):
    a = smerf_copy(tmp)
    f = a / "sm_000" / "scene_params.json"
    f.write_text("[1, 2, 3]")
    return ["smerf", "info", a], f


def nan_in_deferred_mlp(tmp):
    a = smerf_copy(tmp)
    f = a / "sm_000" / "deferred_mlp.json.gz"
    mlp = json.loads(gzip.decompress(f.read_bytes()))
    mlp["ResampleDense_1/bias"]["data"][0] = float("nan")
    f.write_bytes(gzip.compress(json.dumps(mlp).encode()))
    return ["smerf", "info", a], f


def truncated_raw_gz(tmp):
    a = smerf_copy(tmp)
    f = a / "sm_000" / "plane_rgb_0.raw.gz"
    f.write_bytes(f.read_bytes()[:50])
    return ["smerf", "render", "--assets", a, "--out", tmp / "r", "--width", 8, "--height", 8], f


def corrupt_deflate_member(tmp):
    tree = tree_copy(tmp, "good_svox_deflate.npz")
    with zipfile.ZipFile(tree) as z:
        infos = {i.filename: i for i in z.infolist()}
    data = bytearray(tree.read_bytes())
    info = infos["data.npy"]
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 16
    data[start:start + 64] = bytes(64)  # zero a stretch of the DEFLATE stream
    tree.write_bytes(bytes(data))
    return ["octree", "info", tree], tree


def corrupt_npy_header(tmp):
    tree = tree_copy(tmp)
    data = bytearray(tree.read_bytes())
    at = data.find(b"{'descr'")
    data[at:at + 8] = b"{'descr("
    tree.write_bytes(bytes(data))
    return ["octree", "info", tree], tree


def data_dim_not_scalar(tmp):
    tree = rewrite_npz(tree_copy(tmp), lambda z: z.update(data_dim=np.array([4, 4])))
    return ["octree", "info", tree], tree


def child_of_wrong_dtype(tmp):
    tree = rewrite_npz(tree_copy(tmp), lambda z: z.update(child=z["child"].astype(np.float32)))
    return ["octree", "info", tree], tree


def missing_tree(tmp):
    return ["octree", "info", tmp / "nothing.npz"], tmp / "nothing.npz"


def zero_camera_angle(tmp):
    root = transforms_scene(tmp, camera_angle_x=0)
    meta = json.loads((root / "transforms.json").read_text())
    del meta["fl_x"], meta["fl_y"]
    (root / "transforms.json").write_text(json.dumps(meta))
    return ["data", "info", root], root / "transforms.json"


def nan_in_a_camera(tmp):
    root = transforms_scene(tmp)
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][1]["transform_matrix"][0][3] = "NaN"
    (root / "transforms.json").write_text(json.dumps(meta).replace('"NaN"', "NaN"))
    return ["data", "info", root], root / "transforms.json"


def nan_in_ply_points(tmp):
    root = transforms_scene(tmp, ply_file_path="points.ply")
    pts = np.array([[0, 0, 0], [np.nan, 1, 2], [1, 1, 1]], np.float32)
    header = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n" \
             b"property float z\nend_header\n"
    (root / "points.ply").write_bytes(header + pts.tobytes())
    return ["data", "info", root], root / "points.ply"


def image_that_is_not_an_image(tmp):
    root = transforms_scene(tmp)
    (root / "0.png").write_bytes(b"GIF89a but not really")
    meta = json.loads((root / "transforms.json").read_text())
    del meta["w"], meta["h"]  # so the image header must be read
    (root / "transforms.json").write_text(json.dumps(meta))
    return ["data", "info", root], root / "0.png"


def empty_folder_as_dataset(tmp):
    (tmp / "empty").mkdir()
    return ["data", "info", tmp / "empty"], tmp / "empty"


def run_folder_of_the_wrong_kind(tmp):
    run = tmp / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"kind": "smerf-student"}))
    return ["teacher", "eval", "--run", run], run / "config.json"


def student_folder_that_is_a_teacher(tmp):
    run = tmp / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"train": {}, "box": {}}))
    return ["bake", "--student", run, "--out", tmp / "out"], run / "config.json"


def student_folder(tmp) -> Path:
    """A student folder whose config.json is valid (a tiny student), so that what fails is its checkpoint."""
    from nerfbake.smerf.run import DistillConfig
    from nerfbake.smerf.partition import Partition
    from nerfbake.smerf.student import StudentConfig
    from nerfbake.train.loop import to_jsonable

    run = tmp / "run"
    run.mkdir()
    cfg = DistillConfig(student=StudentConfig(sparse_resolution=8, triplane_resolution=16))
    part = Partition.from_cameras(np.array([[0.0, 0, 0], [1, 1, 1]]), 1)
    (run / "config.json").write_text(json.dumps({"kind": "smerf-student", "distill": to_jsonable(cfg),
                                                 "partition": part.to_json()}))
    return run


def corrupt_checkpoint(tmp):
    run = student_folder(tmp)
    (run / "student.pt").write_bytes(b"PK\x03\x04 truncated")
    return ["bake", "--student", run, "--out", tmp / "out"], run / "student.pt"


class _RunsCode:
    def __reduce__(self):
        return (print, ("this ran while loading a checkpoint",))


def checkpoint_with_pickled_code(tmp):
    import torch

    run = student_folder(tmp)
    torch.save({"model": {}, "payload": _RunsCode()}, run / "student.pt")
    return ["bake", "--student", run, "--out", tmp / "out"], run / "student.pt"


def synth_into_a_full_folder(tmp):
    existing = tmp / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    return ["synth", "--scene", "objects", "--out", existing, "--views", 1, "--width", 8, "--height", 8], existing


def tree_onto_an_existing_file(tmp):
    existing = tmp / "existing.npz"
    existing.write_bytes(b"mine")
    return ["octree", "build", "--teacher", tmp / "no_teacher", "--out", existing], existing


ROWS = [truncated_mlp, truncated_params_gz, params_without_asset_metadata, params_not_an_object, nan_in_deferred_mlp,
        truncated_raw_gz, corrupt_deflate_member, corrupt_npy_header, data_dim_not_scalar, child_of_wrong_dtype,
        missing_tree, zero_camera_angle, nan_in_a_camera, nan_in_ply_points, image_that_is_not_an_image,
        empty_folder_as_dataset, run_folder_of_the_wrong_kind, student_folder_that_is_a_teacher, corrupt_checkpoint,
        checkpoint_with_pickled_code, synth_into_a_full_folder, tree_onto_an_existing_file]


@pytest.mark.parametrize("row", ROWS, ids=[r.__name__ for r in ROWS])
def test_bad_input_is_one_line_naming_the_file(row, tmp_path, capsys):
    argv, broken = row(tmp_path)
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "this ran while loading" not in out
    lines = [line for line in err.splitlines() if line.startswith("error")]  # progress bars may share stderr
    assert code == 2, err
    assert len(lines) == 1 and "Traceback" not in err, err
    assert str(broken) in lines[0] or broken.name in lines[0], lines[0]
    assert "bug in nerfbake" not in lines[0], lines[0]
    assert not (tmp_path / "out").exists() and not (tmp_path / "r").exists(), "a half-written output"
    existing = tmp_path / "existing"
    if existing.is_dir():
        assert [p.name for p in existing.iterdir()] == ["keep.txt"], "an existing output was touched"


def test_debug_shows_the_traceback(tmp_path):
    argv, _ = missing_tree(tmp_path)
    with pytest.raises(Exception, match="no such tree"):
        main(["--debug", *map(str, argv)])
