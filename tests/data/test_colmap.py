"""COLMAP models written by pycolmap (binary) and by hand in the classic text layout, from lego's known cameras."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nerfbake.data.cameras import opencv_to_opengl
from nerfbake.data.errors import DatasetError
from nerfbake.data.formats import load_dataset


def lego_views(lego, count=9):
    ds = load_dataset(lego)
    return [ds.frames[i] for i in ds.split("test")[:count]]


def link_images(frames, root):
    (root / "images").mkdir(parents=True)
    for f in frames:
        (root / "images" / f.image_path.name).symlink_to(f.image_path)


def w2c_opencv(c2w_gl):
    return np.linalg.inv(opencv_to_opengl(c2w_gl))


def write_text_model(frames, sparse, camera_line="1 PINHOLE 400 400 555.5555 555.5555 200 200"):
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"# classic COLMAP text model\n{camera_line}\n")
    lines = []
    for i, f in enumerate(frames, start=1):
        w2c = w2c_opencv(f.camera.c2w)
        qx, qy, qz, qw = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        t = w2c[:3, 3]
        lines += [f"{i} {qw} {qx} {qy} {qz} {t[0]} {t[1]} {t[2]} 1 {f.image_path.name}", ""]
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    (sparse / "points3D.txt").write_text("")


def assert_same_cameras(ds, frames):
    by_name = {f.name: f for f in ds.frames}
    for f in frames:
        got = by_name[f.image_path.name].camera
        np.testing.assert_allclose(got.c2w, f.camera.c2w, atol=1e-6)
        assert got.fx == pytest.approx(555.5555, abs=1e-3) and got.cx == 200


def test_classic_text_model(lego, tmp_path):
    frames = lego_views(lego)
    link_images(frames, tmp_path)
    write_text_model(frames, tmp_path / "sparse" / "0")
    ds = load_dataset(tmp_path, normalize="none")
    assert ds.format == "colmap" and len(ds) == 9
    assert ds.splits["test"] == [0, 8]
    assert_same_cameras(ds, frames)
    assert ds.image(0).shape == (400, 400, 3)  # opaque format: alpha dropped


def test_binary_model_written_by_pycolmap(lego, tmp_path):
    import pycolmap

    frames = lego_views(lego)
    link_images(frames, tmp_path)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="OPENCV", width=400, height=400, params=[555.5555, 555.5555, 200, 200, 0.01, -0.002, 0.0003, 0.0001])
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    for i, f in enumerate(frames, start=1):
        im = pycolmap.Image(name=f.image_path.name, camera_id=1, image_id=i)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(w2c_opencv(f.camera.c2w)[:3]))
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(tmp_path / "sparse" / "0"))
    ds = load_dataset(tmp_path, normalize="none")
    assert_same_cameras(ds, frames)
    cam0 = ds.frames[0].camera
    assert cam0.model == "OPENCV" and cam0.distortion == pytest.approx({"k1": 0.01, "k2": -0.002, "p1": 0.0003, "p2": 0.0001})
    # Default normalisation: cameras inside [-1, 1]^3, recorded so points map back.
    norm_ds = load_dataset(tmp_path)
    origins = np.stack([f.camera.origin for f in norm_ds.frames])
    assert np.abs(origins).max() == pytest.approx(1.0)
    back = norm_ds.normalization.invert_points(origins)
    np.testing.assert_allclose(back, np.stack([f.camera.origin for f in ds.frames]), atol=1e-9)


def test_unknown_camera_model_is_named(lego, tmp_path):
    frames = lego_views(lego, 2)
    link_images(frames, tmp_path)
    write_text_model(frames, tmp_path / "sparse" / "0", camera_line="1 FOV 400 400 555 555 200 200 0.5")
    with pytest.raises(DatasetError, match=r"cameras? 1 uses the FOV model.*supported: SIMPLE_PINHOLE"):
        load_dataset(tmp_path)


def test_missing_image_is_named(lego, tmp_path):
    frames = lego_views(lego, 3)
    link_images(frames[:2], tmp_path)
    write_text_model(frames, tmp_path / "sparse" / "0")
    with pytest.raises(DatasetError, match=frames[2].image_path.name + ": image file is missing"):
        load_dataset(tmp_path)
