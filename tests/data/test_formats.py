"""Readers against the real datasets in ../shared/data: counts, intrinsics and, above all, geometry."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from nerfbake.data.errors import DatasetError
from nerfbake.data.formats import detect_format, load_dataset
from nerfbake.data.formats.colmap_model import read_points3d_binary
from nerfbake.data.rays import camera_rays


def data_info(path, *extra):
    out = subprocess.run([sys.executable, "-m", "nerfbake", "data", "info", str(path), "--json", *extra],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def test_lego_info(lego):
    info = data_info(lego)
    assert info["format"] == "blender"
    assert info["splits"] == {"train": 100, "val": 100, "test": 200}
    assert (info["width"], info["height"]) == (400, 400)
    assert info["fx"] == pytest.approx(555.5555, abs=1e-3) and info["fy"] == pytest.approx(555.5555, abs=1e-3)
    assert (info["cx"], info["cy"]) == (200.0, 200.0)
    assert info["normalization"]["scale"] == 1.0 and info["bounds"] == [2.0, 6.0]
    half = data_info(lego, "--downscale", "2")
    assert (half["width"], half["fx"]) == (200, pytest.approx(277.7778, abs=1e-3))


def test_lego_images_are_composited_on_white_and_downscale(lego):
    ds = load_dataset(lego)
    img = ds.image(0)
    assert img.shape == (400, 400, 3) and img.dtype == np.float32
    assert np.allclose(img[0, 0], 1.0)  # background corner is white
    rgba = ds.image(0, keep_alpha=True)
    assert rgba.shape == (400, 400, 4) and rgba[0, 0, 3] == 0
    small = load_dataset(lego, downscale=4)
    s = small.image(0)
    assert s.shape == (100, 100, 3)
    # Area downscale: the mean colour is preserved.
    assert abs(s.mean() - img.mean()) < 2e-3


def lego_depth(ds, index):
    """NeRF-synthetic depth PNGs store 8·(1 − v/255) as distance along the ray (0 = background)."""
    frame = ds.frames[index]
    v = np.asarray(Image.open(str(frame.image_path).replace(".png", "_depth_0001.png")))[..., 0].astype(np.float64)
    return frame.camera, np.where(v > 0, 8.0 * (1.0 - v / 255.0), 0.0)


@pytest.mark.parametrize("a,b", [(0, 5), (40, 47)])
def test_lego_depth_maps_agree_in_world_space(lego, a, b):
    ds = load_dataset(lego)
    test = ds.split("test")
    cam_a, depth_a = lego_depth(ds, test[a])
    cam_b, depth_b = lego_depth(ds, test[b])
    rays = camera_rays(cam_a)
    mask = depth_a > 0
    pts = (rays["origins"][mask].double() + rays["directions"][mask].double() * torch_tensor(depth_a[mask])[:, None]).numpy()
    uv, _ = cam_b.project(pts)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam_b.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam_b.height)
    assert inside.mean() > 0.9
    uv, pts = uv[inside], pts[inside]
    d_b = depth_b[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    seen = d_b > 0
    assert seen.mean() > 0.9  # back-projected surface lands on the object in the other view
    dist = np.linalg.norm(pts[seen] - cam_b.origin, axis=1)
    rel = np.abs(d_b[seen] - dist) / dist
    assert np.median(rel) < 0.01  # the PNG's 8/255 quantisation is ~0.8% at 4 units


def torch_tensor(a):
    import torch

    return torch.from_numpy(a)


def test_fern_info(fern):
    info = data_info(fern)
    assert info["format"] == "llff"
    assert info["splits"] == {"train": 17, "test": 3}
    assert (info["width"], info["height"]) == (504, 378)
    hwf = np.load(fern / "poses_bounds.npy")[0, :15].reshape(3, 5)[:, 4]
    assert info["fx"] == pytest.approx(hwf[2] / 8) and info["downscale"] == 8
    ds = load_dataset(fern)
    names = sorted(f.name for f in ds.frames)
    assert [ds.frames[i].name for i in ds.split("test")] == [names[0], names[8], names[16]]


def test_fern_points_project_consistently_with_llff_poses(fern):
    """COLMAP's points, seen by image k, project inside image k, and their depth range is exactly the near/far
    that LLFF stored for that image (LLFF computes bounds from these points): poses and axes are right."""
    xyz, _, tracks = read_points3d_binary(fern / "sparse" / "0" / "points3D.bin")
    bounds = np.load(fern / "poses_bounds.npy")[:, 15:]
    ds = load_dataset(fern)  # normalised: map the points the same way
    pts = ds.normalization.apply_to_points(xyz)
    for k, frame in enumerate(ds.frames):  # sorted names; COLMAP ids follow that order
        vis = np.array([(k + 1) in t for t in tracks])
        uv, depth = frame.camera.project(pts[vis])
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < 504) & (uv[:, 1] >= 0) & (uv[:, 1] < 378) & (depth > 0)
        assert inside.mean() > 0.99, frame.name
        near, far = np.percentile(depth, 0.1), np.percentile(depth, 99.9)
        np.testing.assert_allclose([near, far], bounds[k] * ds.normalization.scale, rtol=1e-3)


def test_fox_info_and_distortion(fox):
    info = data_info(fox)
    assert info["format"] == "transforms"
    assert info["camera_model"] == "OPENCV" and info["num_images"] == 67
    assert info["splits"] == {"train": 58, "test": 9}
    assert set(info["distortion"]) == {"k1", "k2", "p1", "p2"}
    assert info["extras"]["aabb_scale"] == 4
    ds = load_dataset(fox, downscale=4)
    cam = ds.frames[0].camera
    assert (cam.width, cam.height) == (270, 480)
    assert ds.image(0).shape == (480, 270, 3)
    # Object-centric normalisation keeps every camera in [-1, 1]^3 and looks at the origin.
    origins = np.stack([f.camera.origin for f in ds.frames])
    assert np.abs(origins).max() <= 1 + 1e-9
    fwd = -np.stack([f.camera.c2w[:3, 2] for f in ds.frames])
    to_center = -origins / np.linalg.norm(origins, axis=1, keepdims=True)
    assert np.median((fwd * to_center).sum(1)) > math.cos(math.radians(25))


def test_detect_format(lego, fern, fox):
    assert [detect_format(p) for p in (lego, fern, fox)] == ["blender", "llff", "transforms"]


def test_ply_points_ascii_binary_and_truncated(tmp_path):
    from nerfbake.data.errors import DatasetError
    from nerfbake.data.formats.ply import read_ply_points

    pts = np.array([[0.5, -1.0, 2.0], [3.0, 4.5, -6.0]])
    head = "ply\nformat {}\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n"
    (tmp_path / "a.ply").write_text(head.format("ascii 1.0") + "".join(f"{x} {y} {z} 7\n" for x, y, z in pts))
    rec = np.zeros(2, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    rec["x"], rec["y"], rec["z"], rec["red"] = pts[:, 0], pts[:, 1], pts[:, 2], 7
    (tmp_path / "b.ply").write_bytes(head.format("binary_little_endian 1.0").encode() + rec.tobytes())
    for name in ("a.ply", "b.ply"):
        np.testing.assert_allclose(read_ply_points(tmp_path / name), pts)
    (tmp_path / "c.ply").write_bytes((tmp_path / "b.ply").read_bytes()[:-5])
    with pytest.raises(DatasetError, match="c.ply.*truncated"):
        read_ply_points(tmp_path / "c.ply")
    (tmp_path / "d.ply").write_text("not a ply")
    with pytest.raises(DatasetError, match="d.ply: not a PLY"):
        read_ply_points(tmp_path / "d.ply")


def ring_poses_bounds(n: int = 16, radius: float = 4.0) -> np.ndarray:
    """LLFF poses_bounds rows for cameras on a ring, all looking at the origin (a mip-NeRF 360 style capture)."""
    rows = []
    for k in range(n):
        a = 2 * math.pi * k / n
        centre = np.array([radius * math.cos(a), radius * math.sin(a), 0.5])
        back = centre / np.linalg.norm(centre)  # OpenGL +Z points away from what the camera looks at
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        pose = np.stack([-up, right, back, centre], axis=1)  # LLFF columns: [down, right, back | t]
        hwf = np.array([[6.0], [8.0], [7.0]])
        rows.append(np.concatenate([np.concatenate([pose, hwf], 1).reshape(-1), [1.0, 9.0]]))
    return np.stack(rows)


def test_scene_kind_is_decided_from_the_cameras(tmp_path, lego, fern):
    """Fern looks one way (forward-facing recentring); a 360 capture in poses_bounds.npy form is normalised as one;
    lego is a bounded object; each says why."""
    info = load_dataset(fern).info()
    assert info["scene_kind"] == "forward-facing" and info["normalization"]["method"] == "forward-facing"
    assert "look one way" in info["scene_kind_why"]
    root = tmp_path / "ring"
    (root / "images").mkdir(parents=True)
    np.save(root / "poses_bounds.npy", ring_poses_bounds())
    for k in range(16):
        Image.new("RGB", (8, 6), (k * 10, 0, 0)).save(root / "images" / f"{k:03d}.png")
    ds = load_dataset(root)
    assert ds.normalization.method == "object-centric" and "many directions" in ds.normalization.why
    assert ds.scene_kind()[0] == "unbounded-360"
    origins = np.stack([f.camera.origin for f in ds.frames])
    assert np.abs(origins).max() == pytest.approx(1.0) and np.linalg.norm(origins.mean(0)[:2]) < 1e-6
    assert load_dataset(root, normalize="forward-facing").normalization.method == "forward-facing"  # the override
    assert load_dataset(lego).scene_kind()[0] == "object-centric"


def test_normalize_overrides_the_scene_kind_and_says_so(fern, lego, capsys):
    """--normalize object-centric makes a forward-facing-looking capture a 360 one (the case of a 360 capture the
    cameras misjudge); forward-facing forces LLFF's recentring; Blender scenes refuse an override."""
    from nerfbake.cli import main

    ds = load_dataset(fern, normalize="object-centric")
    kind, why = ds.scene_kind()
    assert kind == "unbounded-360" and why.startswith("--normalize object-centric") and "look one way" in why
    assert ds.normalization.overridden and not load_dataset(fern).normalization.overridden
    assert main(["data", "info", str(fern), "--normalize", "object-centric", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["normalization"] | {"transform": None, "scale": None} == {
        "method": "object-centric", "why": "--normalize object-centric", "overridden": True, "transform": None, "scale": None}
    assert main(["data", "info", str(lego), "--normalize", "none"]) == 2
    assert "Blender-format scene keeps the frame" in capsys.readouterr().err
    with pytest.raises(DatasetError, match="unknown normalisation 'sideways'"):
        load_dataset(fern, normalize="sideways")


def test_depth_bounds_count_only_the_points_a_camera_sees(tmp_path):
    """A point beside the camera (in front of it, outside its image) must not pull the near bound to ~0."""
    from nerfbake.data.cameras import Camera
    from nerfbake.data.dataset import Frame, depth_bounds

    frame = Frame("a.png", tmp_path / "a.png", Camera(np.eye(4), 64, 48, 50.0, 50.0, 32.0, 24.0, "PINHOLE"))
    seen = np.stack([np.array([0.0, 0.0, -2.0 - 0.01 * k]) for k in range(100)])  # straight ahead, 2 to 3 away
    beside = np.array([[5.0, 0.0, -0.01]])  # depth 0.01, far outside the 64x48 image
    near, far = depth_bounds([frame], np.concatenate([seen, beside]))
    assert 2.0 <= near < 2.01 and far <= 3.0
    assert depth_bounds([frame], beside) is None
