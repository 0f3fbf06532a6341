"""Splat export: the files are read by an independent parser (plyfile) and hold what the tree holds."""
import json
import math

import numpy as np
import pytest
import torch

from nerfbake.cli import main
from nerfbake.octree.io import load_tree
from nerfbake.render.sh import sh_basis
from nerfbake.splats.from_tree import SPREAD, gaussians_from_tree, refit_sh
from nerfbake.splats.gaussians import Gaussians
from nerfbake.splats.io import ply_properties, read_ply

plyfile = pytest.importorskip("plyfile", reason="plyfile is the independent reader (pip install plyfile)")


def gs_sh_color(sh: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The 3DGS reference code's colour (its eval_sh to degree 1 and its +0.5, clamp), written from its formulas:
    SH_C0 = 0.28209479177387814, SH_C1 = 0.4886025119029199, degree 1 = C1 * (-y, z, -x)."""
    x, y, z = d
    c = 0.28209479177387814 * sh[:, 0]
    if sh.shape[1] > 1:
        c = c - 0.4886025119029199 * y * sh[:, 1] + 0.4886025119029199 * z * sh[:, 2] - 0.4886025119029199 * x * sh[:, 3]
    return np.maximum(c + 0.5, 0.0)


def test_refit_matches_the_plenoctree_colour_under_3dgs_rules():
    gen = torch.Generator().manual_seed(0)
    k = torch.randn(50, 3, 4, generator=gen, dtype=torch.float64) * 0.8  # mild colours: sigmoid is near its line
    fitted = refit_sh(k, 1, 1).double().numpy()
    for d in np.random.default_rng(1).normal(size=(20, 3)):
        d = d / np.linalg.norm(d)
        want = torch.sigmoid((k * sh_basis(1, torch.tensor(d))).sum(-1)).numpy()  # PlenOctree: sigmoid(SH . k)
        got = np.stack([gs_sh_color(fitted[:, c], d) for c in range(3)], 1)
        # a linear fit of a sigmoid: close everywhere, closest where the colour is mid-range
        assert np.abs(got - want).mean() < 0.005 and np.abs(got - want).max() < 0.05


def test_ply_has_the_reference_layout_and_the_trees_leaves(tiny_tree, tmp_path, capsys):
    out = tmp_path / "scene.ply"
    assert main(["export", "--tree", str(tiny_tree), "--out", str(out), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    ply = plyfile.PlyData.read(str(out))
    vertex = ply["vertex"]
    names = [p.name for p in vertex.properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    tree = load_tree(tiny_tree)
    rest = 3 * ((tree.sh_degree + 1) ** 2 - 1)  # the tree's degree (2 here: 24 f_rest; degree 3 has 45)
    assert names == ply_properties(tree.sh_degree) and len([n for n in names if n.startswith("f_rest_")]) == rest
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert all(p.val_dtype in ("f4", "float32") for p in vertex.properties) and ply.byte_order in ("<", "=")
    assert len(vertex.data) == record["num_splats"] > 0 and json.loads((tmp_path / "scene.ply.json").read_text()) == record

    leaves = tree.leaves()
    data = tree.data.reshape(-1, tree.data_dim)[leaves["index"]].double()
    side = leaves["size"][:, None] / tree.invradius.double()[None]
    alpha = 1 - torch.exp(-data[:, -1].clamp_min(0) * side.mean(1))
    keep = alpha >= 1 / 255
    centres = tree.tree_to_world((leaves["corner"] + leaves["size"][:, None] / 2)[keep].float()).numpy()
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], 1)
    np.testing.assert_allclose(xyz, centres, atol=1e-6)
    opacity = 1 / (1 + np.exp(-vertex["opacity"].astype(np.float64)))
    np.testing.assert_allclose(opacity, alpha[keep].numpy(), atol=1e-4)
    np.testing.assert_allclose(np.exp(vertex["scale_0"].astype(np.float64)), SPREAD * side[keep, 0].numpy(), rtol=1e-5)
    assert (vertex["rot_0"] == 1).all() and (vertex["rot_1"] == 0).all() and (vertex["nx"] == 0).all()
    # view-averaged colour: the mean of sigmoid(SH . k) over the sphere is what f_dc's colour must come close to
    dirs = torch.nn.functional.normalize(torch.randn(256, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=-1)
    k = data[keep, :-1].reshape(-1, 3, tree.num_basis)
    mean_colour = torch.sigmoid(k @ sh_basis(tree.sh_degree, dirs).T).mean(-1).numpy()
    dc = np.stack([vertex[f"f_dc_{c}"] for c in range(3)], 1) * 0.28209479177387814 + 0.5
    assert np.abs(dc - mean_colour).mean() < 0.02
    again = read_ply(out)  # our own reader agrees with plyfile
    np.testing.assert_array_equal(again.means.astype(np.float32), xyz)


def test_splat_file_is_32_bytes_a_splat(tiny_tree, tmp_path):
    out = tmp_path / "scene.splat"
    assert main(["export", "--tree", str(tiny_tree), "--out", str(out), "--format", "splat", "--max-splats", "50"]) == 0
    raw = np.frombuffer(out.read_bytes(), dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4),
                                                  ("rot", "u1", 4)])
    assert out.stat().st_size == 32 * 50 and len(raw) == 50
    assert (raw["rot"][:, 0] == 255).all() and (raw["rot"][:, 1:] == 128).all()  # identity quaternion
    importance = raw["scale"].prod(1) * raw["rgba"][:, 3]
    assert (np.diff(importance.astype(np.float64)) <= 1e-3 * importance.max()).all()  # most visible first
    assert json.loads((tmp_path / "scene.splat.json").read_text())["sh_degree"] == 0


def test_bad_input_gives_one_clear_error_and_no_file(tiny_tree, tiny_teacher, tmp_path, capsys):
    not_a_teacher = tmp_path / "folder"
    not_a_teacher.mkdir()
    (not_a_teacher / "config.json").write_text(json.dumps({"kind": "smerf-student"}))
    out = tmp_path / "x.ply"
    assert main(["export", "--teacher", str(not_a_teacher), "--out", str(out)]) == 2
    assert "teacher" in capsys.readouterr().err and not out.exists()
    assert main(["export", "--tree", str(tmp_path / "none.npz"), "--out", str(out)]) == 2
    assert "none.npz" in capsys.readouterr().err and not out.exists()
    assert main(["export", "--tree", str(tiny_tree), "--out", str(tmp_path)]) == 2  # a folder, not a file
    assert "is a folder" in capsys.readouterr().err
    assert main(["export", "--tree", str(tiny_tree), "--out", str(out), "--sh-degree", "4"]) == 2
    assert "0..3" in capsys.readouterr().err and not out.exists()
    empty = tmp_path / "empty.npz"  # every leaf transparent
    tree = load_tree(tiny_tree)
    tree.data[..., -1] = 0
    from nerfbake.octree.io import save_tree
    save_tree(tree, empty)
    assert main(["export", "--tree", str(empty), "--out", str(out)]) == 2
    assert "no leaf is opaque enough" in capsys.readouterr().err and not out.exists()
    assert not list(tmp_path.glob("x.ply*"))


def test_gaussians_check_their_shapes():
    with pytest.raises(ValueError, match="sh has shape"):
        Gaussians(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 4)), np.zeros(2), np.zeros((2, 3, 5)))
    assert math.isclose(gaussians_from_tree.__defaults__[0] or 0, 0)  # sh_degree default: the tree's (None)


def test_degree_three_ply_orders_f_rest_channel_by_channel(tmp_path):
    """The reference writes features_rest transposed to (N, 3, 15) and flattened: f_rest_0..14 are red's
    coefficients 1..15, 15..29 green's, 30..44 blue's."""
    from nerfbake.splats.io import write_splats

    rng = np.random.default_rng(0)
    g = Gaussians(rng.normal(size=(7, 3)), rng.normal(size=(7, 3)), rng.normal(size=(7, 4)), rng.normal(size=7),
                  rng.normal(size=(7, 3, 16)))
    write_splats(g, tmp_path / "g.ply", "ply")
    v = plyfile.PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    assert len(v.properties) == 62
    for c in range(3):
        np.testing.assert_allclose(v[f"f_dc_{c}"], g.sh[:, c, 0], rtol=1e-6)
        for j in range(15):
            np.testing.assert_allclose(v[f"f_rest_{c * 15 + j}"], g.sh[:, c, 1 + j], rtol=1e-6)
    np.testing.assert_allclose(np.stack([v[f"rot_{i}"] for i in range(4)], 1), g.quats, rtol=1e-6)
    np.testing.assert_allclose(v["opacity"], g.opacity_logits, rtol=1e-6)


def test_environment_map_becomes_a_shell_of_splats_seen_in_the_right_directions(tiny_tree, tmp_path, capsys):
    """A tree's environment map (colour by direction beyond its box) turned into splats: seen from the box's centre,
    each direction shows the map's colour there; and the export writes the shell after the leaves."""
    from nerfbake.data.cameras import Camera
    from nerfbake.octree.io import save_tree
    from nerfbake.render.envmap import equirect_directions
    from nerfbake.splats.from_tree import environment_shell
    from nerfbake.splats.rasterize import render_gaussians

    tree = load_tree(tiny_tree)
    tree.env_map = (0.5 + 0.4 * equirect_directions(32, 64)).float()  # a smooth map: colour = 0.5 + 0.4 d
    shell = environment_shell(tree, sh_degree=1)
    assert len(shell) == 32 * 64 and shell.sh.shape == (32 * 64, 3, 4) and np.all(shell.sh[:, :, 1:] == 0)
    centre = tree.tree_to_world(torch.full((1, 3), 0.5, dtype=torch.float64)).numpy()[0]
    for view in ([1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.3, 0.5, 0.81], [0.0, 0.0, -1.0]):
        v = np.asarray(view) / np.linalg.norm(view)
        helper = np.array([0.0, 1.0, 0.0]) if abs(v[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        right = np.cross(v, helper)
        right /= np.linalg.norm(right)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([right, np.cross(right, v), -v], 1)
        c2w[:3, 3] = centre
        img = render_gaussians(shell, Camera(c2w, 9, 9, 20.0, 20.0, 4.5, 4.5), (0.0, 0.0, 0.0)).numpy()
        np.testing.assert_allclose(img[4, 4], 0.5 + 0.4 * v, atol=0.04, err_msg=str(view))
    path = save_tree(tree, tmp_path / "env.npz")
    assert main(["export", "--tree", str(path), "--out", str(tmp_path / "s.ply"), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["environment_splats"] == 32 * 64
    assert record["num_splats"] == len(gaussians_from_tree(tree)) + 32 * 64
