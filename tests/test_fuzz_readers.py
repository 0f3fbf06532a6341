"""Property tests for every reader: a valid file with bytes flipped, cut short, grown or with its JSON values
replaced either loads or raises the project's error (:class:`NerfbakeError`, which names the file) -- no other
exception, no hang. NERFBAKE_FUZZ_EXAMPLES sets the examples per reader (CI: 200)."""
import gzip
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy.spatial.transform import Rotation

from nerfbake.data.formats import load_dataset
from nerfbake.data.formats.colmap_model import read_model
from nerfbake.data.formats.ply import read_ply_points
from nerfbake.errors import NerfbakeError
from nerfbake.octree.io import load_tree
from nerfbake.smerf.assets import SceneAssets, load_deferred_mlp, load_submodel, read_params
from tests.conftest import shared_data

EXAMPLES = int(os.environ.get("NERFBAKE_FUZZ_EXAMPLES", "200"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@st.composite
def corrupted(draw, data: bytes) -> bytes:
    """``data`` with a few bytes overwritten, then possibly cut short or grown with junk."""
    out = bytearray(data)
    for _ in range(draw(st.integers(0, 6))):
        if out:
            out[draw(st.integers(0, len(out) - 1))] = draw(st.integers(0, 255))
    cut = draw(st.one_of(st.none(), st.integers(0, len(out))))
    if cut is not None:
        del out[cut:]
    return bytes(out) + draw(st.binary(max_size=16))


JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers(-2**40, 2**40) | st.floats() | st.text(max_size=6),
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
                           max_leaves=6)


@st.composite
def json_mutated(draw, obj):
    """``obj`` with one value somewhere inside replaced (or a key dropped)."""
    def paths(o, prefix=()):
        yield prefix
        if isinstance(o, dict):
            for k, v in o.items():
                yield from paths(v, prefix + (k,))
        elif isinstance(o, list):
            for i, v in enumerate(o[:4]):
                yield from paths(v, prefix + (i,))
    target = draw(st.sampled_from(list(paths(obj))))
    obj = json.loads(json.dumps(obj))
    if not target:
        return draw(JSON_VALUES)
    parent = obj
    for k in target[:-1]:
        parent = parent[k]
    if isinstance(parent, dict) and draw(st.booleans()):
        del parent[target[-1]]
    else:
        parent[target[-1]] = draw(JSON_VALUES)
    return obj


def fuzz(strategy, check) -> None:
    """Run ``check`` on ``EXAMPLES`` inputs drawn from ``strategy`` (derandomized: CI sees the same ones)."""
    FUZZ(given(strategy)(check))()


def expect_loads_or_project_error(fn, *args):
    try:
        fn(*args)
    except NerfbakeError as exc:
        assert str(exc), "an error without a message"


@pytest.fixture(scope="module")
def work():
    with tempfile.TemporaryDirectory(prefix="nerfbake-fuzz-") as d:
        yield Path(d)


# ---- PlenOctree trees -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fixture", ["good_svox_raw.npz", "good_svox_deflate.npz", "good_compressed_numpy.npz"])
def test_tree_files(fixture, work):
    good = (shared_data("octree_fixtures") / fixture).read_bytes()
    path = work / fixture

    def check(data):
        path.write_bytes(data)
        expect_loads_or_project_error(load_tree, path)

    fuzz(corrupted(good), check)


# ---- SMERF assets -------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def smerf(work):
    root = work / "smerf"
    shutil.copytree(shared_data("smerf_tiny"), root)
    (root / "sm_000" / "scene_params.json.gz").unlink()  # one copy of the params, the one mutated
    return root / "sm_000"


def _with_file(path: Path, data: bytes, fn):
    original = path.read_bytes()
    path.write_bytes(data)
    try:
        expect_loads_or_project_error(fn)
    finally:
        path.write_bytes(original)


def test_smerf_scene_params(smerf):
    params = json.loads((smerf / "scene_params.json").read_text())

    def check(obj):
        _with_file(smerf / "scene_params.json", json.dumps(obj).encode(),
                   lambda: (load_submodel(smerf), SceneAssets.open(smerf.parent)))

    fuzz(json_mutated(params), check)


@pytest.mark.parametrize("name", ["sparse_grid_block_indices.raw.gz", "occupancy_grid_8_000.raw.gz",
                                  "distance_grid_8_000.raw.gz", "plane_rgb_0.raw.gz"])
def test_smerf_raw_gz(smerf, name):
    good = (smerf / name).read_bytes()

    def check(data):
        _with_file(smerf / name, data, lambda: load_submodel(smerf))

    fuzz(st.one_of(corrupted(good), corrupted(gzip.compress(gzip.decompress(good)[:57]))), check)


def test_smerf_deferred_mlp(smerf):
    good = (smerf / "deferred_mlp.json.gz").read_bytes()
    mlp = json.loads(gzip.decompress(good))
    small = {k: v for k, v in mlp.items()}

    def check(data):
        _with_file(smerf / "deferred_mlp.json.gz", data, lambda: load_deferred_mlp(smerf, read_params(smerf)))

    fuzz(st.one_of(corrupted(good), json_mutated(small).map(lambda o: gzip.compress(json.dumps(o).encode()))), check)


# ---- datasets -----------------------------------------------------------------------------------------------------

def _images(folder: Path, n=4):
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        Image.fromarray(np.full((6, 8, 3), 40 * i, np.uint8)).save(folder / f"{i}.png")


def _poses(n=4):
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([3 * np.cos(a), 3 * np.sin(a), 0.5])
        fwd = -eye / np.linalg.norm(eye)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([right, up, -fwd], 1)
        c2w[:3, 3] = eye
        out.append(c2w)
    return out


def test_transforms_json(work):
    root = work / "transforms"
    _images(root)
    meta = {"fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "k1": 0.01,
            "frames": [{"file_path": f"{i}.png", "transform_matrix": p.tolist()} for i, p in enumerate(_poses())]}

    def check(data):
        (root / "transforms.json").write_bytes(data)
        expect_loads_or_project_error(load_dataset, root)

    fuzz(st.one_of(json_mutated(meta).map(lambda o: json.dumps(o).encode()), corrupted(json.dumps(meta).encode())), check)


def test_poses_bounds_npy(work):
    root = work / "llff"
    _images(root / "images")
    rows = []
    for p in _poses():
        llff = np.concatenate([p[:3, 1:2], p[:3, 0:1], -p[:3, 2:3], p[:3, 3:4], np.array([[6], [8], [8.0]])], 1)
        rows.append(np.concatenate([llff.reshape(-1), [1.0, 6.0]]))
    path = root / "poses_bounds.npy"
    np.save(path, np.array(rows))
    good = path.read_bytes()

    def check(data):
        path.write_bytes(data)
        expect_loads_or_project_error(load_dataset, root)

    fuzz(corrupted(good), check)


@pytest.fixture(scope="module")
def colmap_models(work):
    """A small model in both forms, the binary one written by pycolmap from the text one."""
    import pycolmap

    text = work / "colmap_text" / "sparse" / "0"
    text.mkdir(parents=True)
    (text / "cameras.txt").write_text("# cameras\n1 SIMPLE_RADIAL 8 6 8 4 3 0.01\n2 PINHOLE 8 6 8 8 4 3\n")
    lines = ["# images"]
    for i, p in enumerate(_poses()):
        w2c = np.linalg.inv(p @ np.diag([1, -1, -1, 1.0]))
        x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        q = [w, x, y, z]
        lines += [" ".join(map(str, [i + 1, *q, *w2c[:3, 3], 1 + i % 2, f"{i}.png"])), "4 3 1" if i < 2 else ""]
    (text / "images.txt").write_text("\n".join(lines) + "\n")
    (text / "points3D.txt").write_text("1 0.1 0.2 0.3 200 100 50 0.5 1 0 2 0\n")
    _images(work / "colmap_text" / "images")
    binary = work / "colmap_bin" / "sparse" / "0"
    binary.mkdir(parents=True)
    pycolmap.Reconstruction(str(text)).write_binary(str(binary))
    _images(work / "colmap_bin" / "images")
    return text, binary


def test_colmap_reader_agrees_with_pycolmap(colmap_models):
    import pycolmap

    for sparse in colmap_models:
        ours, theirs = read_model(sparse), pycolmap.Reconstruction(str(sparse))
        assert sorted(ours.images) == sorted(theirs.images)
        for iid, im in theirs.images.items():
            m = im.cam_from_world().matrix() if callable(im.cam_from_world) else im.cam_from_world.matrix()
            np.testing.assert_allclose(ours.images[iid].world_to_camera()[:3], m, atol=1e-9)
            assert ours.images[iid].name == im.name and ours.images[iid].camera_id == im.camera_id
        for cid, cam in theirs.cameras.items():
            assert ours.cameras[cid].model == cam.model.name
            np.testing.assert_allclose(ours.cameras[cid].params, cam.params)
        np.testing.assert_allclose(ours.points, np.stack([p.xyz for p in theirs.points3D.values()]))
        assert load_dataset(sparse.parents[1]).info()["num_images"] == 4


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt",
                                  "points3D.txt"])
def test_colmap_files(colmap_models, name):
    sparse = colmap_models[0] if name.endswith(".txt") else colmap_models[1]
    good = (sparse / name).read_bytes()

    def check(data):
        _with_file(sparse / name, data, lambda: load_dataset(sparse.parents[1]))

    fuzz(corrupted(good), check)


@pytest.mark.parametrize("form", ["ascii", "binary_little_endian"])
def test_ply_points(work, form):
    pts = np.array([[0, 0, 0], [1, 2, 3], [-1, 0.5, 2]], np.float32)
    header = (f"ply\nformat {form} 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nend_header\n").encode()
    if form == "ascii":
        body = "".join(f"{x} {y} {z} 7\n" for x, y, z in pts).encode()
    else:
        body = b"".join(p.tobytes() + b"\x07" for p in pts)
    path = work / f"{form}.ply"
    good = header + body
    path.write_bytes(good)
    np.testing.assert_allclose(read_ply_points(path), pts)

    def check(data):
        path.write_bytes(data)
        expect_loads_or_project_error(read_ply_points, path)

    fuzz(corrupted(good), check)
