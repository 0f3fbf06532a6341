"""The baked-asset reader and the Python/Warp re-implementation of the official SMERF viewer's ray marcher,
checked against the official viewer's own picture of the shared one-submodel scene."""
import gzip
import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest

from nerfbake.cli import main
from nerfbake.smerf.assets import AssetError, SceneAssets, load_submodel
from nerfbake.smerf.baked_render import ViewerCamera, read_test_frames, render_baked, submodel_for_position
from tests.conftest import shared_data
from tests.helpers import devices


@pytest.fixture(scope="module")
def tiny_assets():
    return shared_data("smerf_tiny")


def blob_masks(img: np.ndarray) -> dict[str, np.ndarray]:
    """Pixels of the orange sphere and the green and blue cubes."""
    r, g, b = (img[..., c].astype(float) for c in range(3))
    return {"orange": (r > 120) & (g > 50) & (b < 80) & (r > g + 40), "green": (g > 120) & (r < 80) & (b < 120),
            "blue": (b > 120) & (r < 100) & (g < 100)}


def test_reads_the_official_layout(tiny_assets):
    sm = load_submodel(tiny_assets / "sm_000")
    p = sm.params
    assert sm.block_indices.shape == (32, 32, 32, 3)
    assert sm.atlas_rgb.shape == (p["atlas_width"], p["atlas_height"], p["atlas_depth"], 3)
    assert sm.atlas_density.shape[-1] == 2 and sm.plane_features.shape == (3, 256, 256, 4)
    assert sm.occupancy[8].shape == (32, 32, 32) and sm.distance[8].shape == (32, 32, 32)
    live = sm.block_indices[..., 0] < 255
    assert 0 < live.sum() <= p["atlas_width"] // 9 * p["atlas_height"] // 9 * p["atlas_depth"] // 9
    # the distance grid never lets the marcher jump over an occupied cell
    assert (sm.distance[8][sm.occupancy[8] > 0] == 0).all() and (sm.occupancy[8] > 0).any()


@devices
def test_baked_renderer_matches_the_official_viewer(tiny_assets, tmp_path, device):
    official = iio.imread(tiny_assets / "official_viewer_render.png")[..., :3]
    h, w = official.shape[:2]
    scene = SceneAssets.open(tiny_assets)
    cam = ViewerCamera.perspective([0, 0, 0], np.diag([-1.0, 1.0, -1.0]), 40.0, w, h)
    ours = np.round(render_baked(scene, cam, device=device) * 255).astype(np.uint8)
    iio.imwrite(tmp_path / "ours.png", ours)
    # The official picture was accumulated progressively at half resolution (downscale 2) and is 12-24 % darker
    # with a top-to-bottom gradient, so geometry and hue are compared, not absolute brightness.
    ours_m, off_m = blob_masks(ours), blob_masks(official)
    for name in ours_m:
        a, b = ours_m[name], off_m[name]
        assert np.abs(np.argwhere(a).mean(0) - np.argwhere(b).mean(0)).max() < 2.0, name  # centroid, px
        assert (a & b).sum() / (a | b).sum() > 0.9, name  # overlap (IoU)
        ca, cb = ours[a & b].mean(0), official[a & b].astype(float).mean(0)
        assert ca @ cb / np.linalg.norm(ca) / np.linalg.norm(cb) > 0.999, name  # same hue
    background = ~np.any(list(ours_m.values()), 0) & ~np.any(list(off_m.values()), 0)
    assert ours[background].mean() < 3 and official[background].mean() < 3  # black (MLP output ~0) elsewhere


def test_test_frames_and_submodel_choice(tiny_assets):
    cams = read_test_frames(tiny_assets / "sm_000" / "test_frames.json", 80, 50)
    assert len(cams) == 1 and np.allclose(cams[0].rotation, np.diag([-1, 1, -1]))
    params = json.loads((tiny_assets / "sm_000" / "scene_params.json").read_text())
    assert submodel_for_position(params, np.array([0.3, -0.2, 0.1])) == 0
    k2 = {**params, "num_local_submodels": 2, "submodel_voxel_size": 1.0, "sm_to_params": [0, -1, -1, -1, -1, -1, -1, 1]}
    # training-frame (+,+,+) octant = viewer (-x, +z, +y)
    assert submodel_for_position(k2, np.array([-0.5, 0.5, 0.5])) == 1
    assert submodel_for_position(k2, np.array([0.5, -0.5, -0.5])) == 0


def test_broken_asset_directories(tiny_assets, tmp_path):
    broken = tmp_path / "scene"
    shutil.copytree(tiny_assets, broken)
    target = broken / "sm_000" / "sparse_grid_rgb_003.raw.gz"
    target.chmod(0o644)
    target.write_bytes(gzip.compress(gzip.decompress(target.read_bytes())[:100]))
    with pytest.raises(AssetError, match="sparse_grid_rgb_003.raw.gz: 100 bytes"):
        load_submodel(broken / "sm_000")
    (broken / "sm_000" / "plane_rgb_1.raw.gz").chmod(0o644)
    (broken / "sm_000" / "plane_rgb_1.raw.gz").unlink()
    with pytest.raises(AssetError, match="plane_rgb_1.raw.gz: missing"):
        load_submodel(broken / "sm_000")
    with pytest.raises(AssetError, match="not a SMERF asset directory"):
        SceneAssets.open(tmp_path / "nothing")
    assert main(["smerf", "info", str(tmp_path / "nothing")]) == 2


def test_smerf_info_and_render_commands(tiny_assets, tmp_path, capsys):
    assert main(["smerf", "info", str(tiny_assets), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["num_submodels"] == 1 and info["disk_bytes"] > 0 and info["submodels"][0]["triplane_resolution"] == 256
    assert info["format_problems"] == []
    assert main(["smerf", "render", "--assets", str(tiny_assets), "--out", str(tmp_path / "r"), "--width", "80",
                 "--height", "50"]) == 0
    img = iio.imread(tmp_path / "r" / "0000.png")
    assert img.shape == (50, 80, 3) and img.max() > 100


def test_format_rules_accept_the_official_export_and_name_each_violation(tiny_assets, tmp_path):
    from nerfbake.smerf.validate import asset_problems

    assert asset_problems(tiny_assets) == []
    broken = tmp_path / "scene"
    shutil.copytree(tiny_assets, broken)
    sm = broken / "sm_000"
    for f in sm.iterdir():
        f.chmod(0o644)
    params = json.loads((sm / "scene_params.json").read_text())
    params["triplane_voxel_size"] = 0.01
    del params["exposure_range"]
    (sm / "scene_params.json").write_text(json.dumps(params))
    (sm / "distance_grid_16_000.raw.gz").unlink()
    idx = gzip.decompress((sm / "sparse_grid_block_indices.raw.gz").read_bytes())
    arr = np.frombuffer(idx, np.uint8).copy()
    live = np.nonzero(arr.reshape(-1, 3)[:, 0] < 255)[0][0]
    arr.reshape(-1, 3)[live] = [200, 0, 0]  # outside a 288x9x9 atlas
    (sm / "sparse_grid_block_indices.raw.gz").write_bytes(gzip.compress(arr.tobytes()))
    problems = "\n".join(asset_problems(broken))
    assert "missing keys exposure_range" in problems
    assert "triplane_voxel_size = 0.01, expected 0.015625" in problems
    assert "distance_grid_16_000.raw.gz: missing" in problems
    assert "points outside the 288x9x9 atlas" in problems


def test_our_distance_grids_are_the_authors_and_an_overshooting_one_is_named(tiny_assets, tmp_path):
    """The byte is the Chebyshev distance to an occupied cell minus 1: the viewer jumps that many whole cells from
    anywhere inside a cell. Storing the distance itself (nerfbake before session 35) let rays jump through thin
    surfaces; the official export's grids are the reference."""
    from nerfbake.smerf.validate import asset_problems, distance_grid

    sm = load_submodel(tiny_assets / "sm_000")
    for f, occupancy in sm.occupancy.items():
        assert (distance_grid(occupancy > 0) == sm.distance[f]).all(), f"factor {f}"
    assert asset_problems(tiny_assets) == []
    broken = tmp_path / "scene"
    shutil.copytree(tiny_assets, broken)
    folder = broken / "sm_000"
    read = lambda name: np.frombuffer(gzip.decompress((folder / name).read_bytes()), np.uint8)  # noqa: E731
    occupied, official = read("occupancy_grid_8_000.raw.gz") > 0, read("distance_grid_8_000.raw.gz")
    target = folder / "distance_grid_8_000.raw.gz"
    target.chmod(0o644)
    target.write_bytes(gzip.compress(np.where(occupied, 0, official + 1).astype(np.uint8).tobytes()))  # the old rule
    assert "distance_grid_8 lets the viewer jump into occupied cells" in "\n".join(asset_problems(broken))
    far = np.flatnonzero(official > 0)[0]  # one byte too large away from any surface is named too
    overshoot = official.copy()
    overshoot[far] += 1
    target.write_bytes(gzip.compress(overshoot.tobytes()))
    assert "distance_grid_8 lets the viewer jump into occupied cells" in "\n".join(asset_problems(broken))
    target.write_bytes(gzip.compress(np.minimum(official, 1).tobytes()))  # smaller jumps are slower, not wrong
    assert asset_problems(broken) == []
    empty = folder / "occupancy_grid_8_000.raw.gz"  # nothing occupied: no byte can jump into anything
    empty.chmod(0o644)
    empty.write_bytes(gzip.compress(np.zeros_like(official).tobytes()))
    target.write_bytes(gzip.compress(np.full_like(official, 255).tobytes()))
    assert not any("distance_grid_8" in problem for problem in asset_problems(broken))
