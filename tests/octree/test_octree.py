"""PlenOctrees: the svox file layout, the renderer (kernel vs torch reference vs closed form), the analytic
backward (vs autograd and finite differences), compression, building from a teacher and fine-tuning."""
import json
import math
import zipfile
from dataclasses import replace

import numpy as np
import pytest
import torch

from nerfbake.cli import main
from nerfbake.kernels.octree import render_backward
from nerfbake.octree.build import BuildConfig, build_octree
from nerfbake.octree.compress import compress_tree, median_cut
from nerfbake.octree.io import OctreeFileError, load_tree, save_tree, volrend_problems
from nerfbake.octree.optimize import OptimizeConfig, optimize_tree
from nerfbake.octree.render import RenderOptions, render_reference, render_rays
from nerfbake.octree.tree import Octree, tree_from_cells
from tests.conftest import shared_data
from tests.helpers import devices


@pytest.fixture(scope="module")
def fixtures():
    return shared_data("octree_fixtures")


def random_tree(data_dim=76, seed=0, cells=300, depth=3):
    rng = np.random.default_rng(seed)
    t = tree_from_cells(rng.integers(0, 2 ** (depth + 1), (cells, 3)), depth, [-1, -1, -1], [1, 1, 1], data_dim)
    g = torch.Generator().manual_seed(seed)
    t.data.normal_(generator=g)
    t.data[..., -1] = t.data[..., -1].abs() * 0.6  # optical depth ~1 across the box: partly transparent
    return t


def random_env(height=6, seed=5):
    """A small environment map with every texel different (wrong texel or filtering shows in the comparisons)."""
    return torch.rand(height, 2 * height, 3, generator=torch.Generator().manual_seed(seed))


def random_rays(n, seed=0, radius=3.0):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g)
    o = o / o.norm(dim=-1, keepdim=True) * radius
    d = torch.rand(n, 3, generator=g) - 0.5 - o
    return o, d / d.norm(dim=-1, keepdim=True)


# --- file format -----------------------------------------------------------------------------------------------------

def test_reads_svox_files_as_svox_does(fixtures):
    q = json.loads((fixtures / "svox_queries.json").read_text())
    for name in ("good_svox_raw.npz", "good_svox_deflate.npz"):
        tree = load_tree(fixtures / name)
        assert (tree.data_format, tree.num_leaves, tree.depth_limit) == ("SH4", q["n_leaves"], 4)
        got = tree.query(torch.tensor(q["points"]))
        assert torch.equal(got, torch.tensor(q["values"], dtype=torch.float32))


def test_compressed_web_layout_decodes_to_the_raw_tree(fixtures):
    raw = load_tree(fixtures / "good_svox_raw.npz")
    comp = load_tree(fixtures / "good_compressed_numpy.npz")
    leaf = raw.child == 0
    alive = leaf & (raw.data[..., -1] > 0)
    assert torch.equal(comp.data[alive], raw.data[alive])


def test_our_writer_reproduces_svox_arrays_and_round_trips_bit_exactly(fixtures, tmp_path):
    tree = load_tree(fixtures / "good_svox_raw.npz")
    save_tree(tree, tmp_path / "a.npz")
    save_tree(load_tree(tmp_path / "a.npz"), tmp_path / "b.npz")
    svox, a, b = (np.load(p) for p in (fixtures / "good_svox_raw.npz", tmp_path / "a.npz", tmp_path / "b.npz"))
    assert sorted(a.files) == sorted(svox.files)
    for k in svox.files:
        assert a[k].dtype == svox[k].dtype and a[k].shape == svox[k].shape, k
        assert np.array_equal(a[k], svox[k]) and np.array_equal(a[k], b[k]), k
    assert volrend_problems(tmp_path / "a.npz") == []
    save_tree(tree, tmp_path / "c.npz", compress=True)
    assert volrend_problems(tmp_path / "c.npz") == []
    assert zipfile.ZipFile(tmp_path / "c.npz").infolist()[0].compress_type == zipfile.ZIP_DEFLATED


def independent_svox_tree(path):
    """A two-level SH1 tree written straight from the format rules (not with nerfbake's writer): the root's
    cell (1,1,1) is refined; every leaf of the refined node is red with sigma 4, the rest empty."""
    child = np.zeros((2, 2, 2, 2), np.int32)
    child[0, 1, 1, 1] = 1  # relative pointer: node 0 + 1
    data = np.zeros((2, 2, 2, 2, 4), np.float16)
    data[1, ..., 0] = 2.0 / 0.28209479177387814  # sigmoid(2) red
    data[1, ..., 1] = data[1, ..., 2] = -2.0 / 0.28209479177387814
    data[1, ..., 3] = 4.0
    parent_depth = np.array([[0, 0], [7, 1]], np.int32)
    np.savez(path, data_dim=np.int64(4), child=child, parent_depth=parent_depth, n_internal=np.int64(2),
             n_free=np.int64(0), invradius3=np.full(3, 0.25, np.float32), offset=np.full(3, 0.5, np.float32),
             depth_limit=np.int64(1), geom_resize_fact=np.float64(1.0), data=data, data_format=np.array("SH1"))


def test_independently_written_tree_loads_and_renders_the_closed_form(tmp_path):
    independent_svox_tree(tmp_path / "ind.npz")
    assert volrend_problems(tmp_path / "ind.npz") == []
    tree = load_tree(tmp_path / "ind.npz")  # world box [-2, 2]^3; the red block is [0, 2]^3
    assert tree.num_leaves == 15 and tree.data_format == "SH1"
    o = torch.tensor([[1.0, 1.0, -5.0], [-1.0, -1.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    out = render_rays(tree, o, d, RenderOptions(step_size=1e-6, stop_thresh=0.0))
    a = 1 - math.exp(-4.0 * 2.0)  # two world units through sigma 4
    s = 1 / (1 + math.exp(-2.0))
    expect = torch.tensor([[a * s + (1 - a), a * (1 - s) + (1 - a), a * (1 - s) + (1 - a)], [1.0, 1.0, 1.0]])
    assert torch.allclose(out["rgb"], expect, atol=1e-4)
    assert out["alpha"][0] == pytest.approx(a, abs=1e-5) and out["alpha"][1] == 0


def test_bad_files_give_clear_errors(fixtures, tmp_path):
    good = dict(np.load(fixtures / "good_svox_raw.npz"))
    (tmp_path / "trunc.npz").write_bytes((fixtures / "good_svox_raw.npz").read_bytes()[:5000])
    with pytest.raises(OctreeFileError, match="trunc.npz: not a readable .npz"):
        load_tree(tmp_path / "trunc.npz")
    np.savez(tmp_path / "foreign.npz", weights=np.zeros(3))
    with pytest.raises(OctreeFileError, match="missing key 'child'.*not a PlenOctree"):
        load_tree(tmp_path / "foreign.npz")
    np.savez(tmp_path / "f32.npz", **{**good, "data": good["data"].astype(np.float32)})
    with pytest.raises(OctreeFileError, match="half precision"):
        load_tree(tmp_path / "f32.npz")
    assert any("half precision" in p for p in volrend_problems(tmp_path / "f32.npz"))
    np.savez(tmp_path / "i64.npz", **{**good, "child": good["child"].astype(np.int64)})
    with pytest.raises(OctreeFileError, match="int32"):
        load_tree(tmp_path / "i64.npz")
    empty = {**good, "child": good["child"][:0], "parent_depth": good["parent_depth"][:0], "data": good["data"][:0]}
    np.savez(tmp_path / "empty.npz", **empty)
    with pytest.raises(OctreeFileError, match="empty.npz: the tree has no nodes"):
        load_tree(tmp_path / "empty.npz")
    cyclic = {**good, "child": np.array([[[[1, 1], [1, 1]], [[1, 1], [1, 1]]], [[[-1, -1], [-1, -1]], [[-1, -1], [-1, -1]]]], np.int32),
              "data": good["data"][:2]}
    np.savez(tmp_path / "cyclic.npz", **cyclic)
    with pytest.raises(OctreeFileError, match="cyclic.npz: a child pointer points outside"):
        load_tree(tmp_path / "cyclic.npz")
    np.savez(tmp_path / "fmt.npz", **{**good, "data_format": np.array("SH16")})
    with pytest.raises(OctreeFileError, match="SH16 does not match data_dim 13"):
        load_tree(tmp_path / "fmt.npz")
    with pytest.raises(OctreeFileError, match="no such tree"):
        load_tree(tmp_path / "missing.npz")
    tree = load_tree(fixtures / "good_svox_raw.npz")
    with pytest.raises(ValueError, match=r"outside the 4 basis functions"):
        render_rays(tree, torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), RenderOptions(basis_max=9))
    assert main(["octree", "info", str(tmp_path / "trunc.npz")]) == 2


# --- rendering -------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("opts", [
    RenderOptions(), RenderOptions.training(), RenderOptions(basis_min=1, basis_max=9, background=(0.2, 0.5, 0.0)),
    RenderOptions(bbox_min=(0.3, 0.0, 0.2), bbox_max=(0.8, 0.7, 1.0), step_size=1e-3),
], ids=["volrend-defaults", "training", "sh-range", "slicing"])
@pytest.mark.parametrize("env", [False, True], ids=["background", "env-map"])
@devices
def test_kernel_matches_torch_reference(opts, env, device):
    tree = random_tree(76)  # SH25: every basis function the kernel has
    if env:
        tree.env_map = random_env()
    o, d = random_rays(3000)
    a = {k: v.cpu() for k, v in render_rays(tree.to(device), o.to(device), d.to(device), opts).items()}
    b = render_reference(tree, o, d, opts)
    assert (a["rgb"] - b["rgb"]).abs().max() < 1e-4
    assert (a["alpha"] - b["alpha"]).abs().max() < 1e-4
    assert ((a["depth"] - b["depth"]).abs() / b["depth"].clamp_min(1)).max() < 1e-4
    assert 0.05 < float(b["alpha"].mean()) < 0.95  # the rays see the tree, and not all of it is opaque


@pytest.mark.parametrize("env", [False, True], ids=["background", "env-map"])
@devices
def test_backward_matches_autograd_and_finite_differences(env, device):
    tree = random_tree(28, seed=1)
    tree.env_map = random_env() if env else None
    o, d = random_rays(2000, seed=1)
    opts = RenderOptions.training(background=(0.3, 0.6, 0.9))
    g = torch.randn(o.shape[0], 3, generator=torch.Generator().manual_seed(2))
    on = tree.to(device), o.to(device), d.to(device)
    rgb = render_rays(*on, opts)["rgb"]
    kernel = render_backward(*on, opts, rgb, g.to(device)).reshape(-1, 28).cpu()
    data64 = tree.data.double().requires_grad_()
    t64 = Octree(tree.child, data64, tree.offset, tree.invradius, tree.depth_limit, tree.env_map)
    (render_reference(t64, o.double(), d.double(), opts)["rgb"] * g.double()).sum().backward()
    auto = data64.grad.reshape(-1, 28)
    assert (kernel.double() - auto).abs().max() < 1e-4 * auto.abs().max()

    def loss(data):
        return float((render_reference(Octree(tree.child, data, tree.offset, tree.invradius, tree.depth_limit, tree.env_map),
                                       o.double(), d.double(), opts)["rgb"] * g.double()).sum())

    for col in (0, 5, 27):  # an SH coefficient of R, of G (degree 1), and sigma
        slot = int(auto[:, col].abs().argmax())
        eps = 1e-4
        hi, lo = data64.detach().clone(), data64.detach().clone()
        hi.view(-1, 28)[slot, col] += eps
        lo.view(-1, 28)[slot, col] -= eps
        fd = (loss(hi) - loss(lo)) / (2 * eps)
        assert kernel[slot, col].item() == pytest.approx(fd, rel=1e-3)


def test_environment_map_lookup_follows_its_convention():
    """Texel centres return their texel; between columns the lookup is bilinear and wraps around in longitude,
    as a WebGL texture with LINEAR filtering and REPEAT in s; directions map to rows from +z down to -z."""
    from nerfbake.render.envmap import equirect_coords, equirect_directions, sample_equirect

    env = random_env(8)
    dirs = equirect_directions(8, 16)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(8, 16))
    assert torch.allclose(sample_equirect(env, dirs.reshape(-1, 3)), env.reshape(-1, 3), atol=1e-5)
    assert float(dirs[0, 0, 2]) > 0.98 and float(dirs[-1, 0, 2]) < -0.98
    # half way between the last column and the first (longitude +-pi): their mean
    th = math.pi * 2.5 / 8  # row 2's centre
    seam = torch.tensor([[-math.sin(th), 0.0, math.cos(th)]])
    assert torch.allclose(sample_equirect(env, seam)[0], 0.5 * (env[2, 0] + env[2, -1]), atol=1e-5)
    s, t = equirect_coords(torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
    assert s.tolist() == pytest.approx([0.5, 0.5]) and t.tolist() == pytest.approx([0.5, 1.0])


def test_environment_map_survives_save_compress_and_load(tmp_path):
    tree = random_tree(28, seed=3, cells=2000, depth=4)
    tree.env_map = random_env(4)
    save_tree(tree, tmp_path / "raw.npz")
    compress_tree(tmp_path / "raw.npz", tmp_path / "c.npz", band_bits=(16,))
    for name in ("raw.npz", "c.npz"):
        z = np.load(tmp_path / name)
        assert z["env_map"].dtype == np.uint8 and z["env_map"].shape == (4, 8, 3)
        assert volrend_problems(tmp_path / name) == []  # volrend and svox read the keys they know and ignore it
        back = load_tree(tmp_path / name)
        assert (back.env_map - tree.env_map).abs().max() <= 0.5 / 255 + 1e-6
    np.savez(tmp_path / "bad.npz", **{**dict(np.load(tmp_path / "raw.npz")), "env_map": np.zeros((4, 8), np.uint8)})
    with pytest.raises(OctreeFileError, match="bad.npz.*env_map"):
        load_tree(tmp_path / "bad.npz")


def test_densities_beyond_half_precision_saturate_instead_of_becoming_inf(tmp_path):
    """volrend stores leaves in float16 (max 65504); a teacher's density can be larger. Saved trees saturate and
    load back (an inf would make every later stage refuse the file); NaN is refused before anything is written."""
    tree = random_tree(28, seed=6)
    leaf = int(torch.nonzero(tree.child.reshape(-1) == 0)[0])
    tree.data.view(-1, 28)[leaf, -1] = 1e6
    save_tree(tree, tmp_path / "big.npz")
    back = load_tree(tmp_path / "big.npz")
    assert float(back.data.view(-1, 28)[leaf, -1]) == 65504.0 and volrend_problems(tmp_path / "big.npz") == []
    compress_tree(tmp_path / "big.npz", tmp_path / "big_c.npz")
    assert torch.isfinite(load_tree(tmp_path / "big_c.npz").data).all()
    tree.data.view(-1, 28)[leaf, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        save_tree(tree, tmp_path / "nan.npz")
    assert not (tmp_path / "nan.npz").exists()


def test_tree_from_cells_has_exactly_those_leaves():
    rng = np.random.default_rng(3)
    cells = np.unique(rng.integers(0, 32, (500, 3)), axis=0)
    tree = tree_from_cells(cells, 4, [0, 0, 0], [1, 1, 1], 4)
    leaves = tree.leaves()
    fine = (leaves["depth"] == 4)
    assert int(fine.sum()) >= len(cells)
    centres = torch.from_numpy((cells + 0.5) / 32)
    slots = tree.lookup(centres)
    assert len(set(slots.tolist())) == len(cells)
    assert set(slots.tolist()) <= set(leaves["index"][fine].tolist())
    pd = tree.parent_depth()
    kids = np.nonzero(tree.child.numpy().reshape(-1))[0]
    assert np.array_equal(np.sort(pd[1:, 0]), np.sort(kids)) and pd[:, 1].max() == 4


# --- compression -----------------------------------------------------------------------------------------------------

def test_median_cut_codebook():
    x = np.random.default_rng(0).normal(size=(5000, 3)).astype(np.float32)
    book, idx = median_cut(x, 8)
    assert book.shape == (256, 3) and idx.max() < 256
    rmse8 = np.sqrt(np.mean((book[idx] - x) ** 2))
    book4, idx4 = median_cut(x, 4)
    assert rmse8 < 0.35 and rmse8 < 0.6 * np.sqrt(np.mean((book4[idx4] - x) ** 2))  # unit-variance input
    for k in range(256):  # each entry is the mean of its members
        members = x[idx == k]
        if len(members):
            assert np.allclose(book[k], members.mean(0), atol=1e-5)
    few = x[:7]
    book, idx = median_cut(few, 4)
    assert np.allclose(book[idx], few, atol=1e-6)
    clustered = np.concatenate([x[:100] * 1e-4, x[100:200] + 5])  # one tight cluster, one wide one
    book, idx = median_cut(clustered, 8, min_extent=1e-2)
    assert len(np.unique(idx[:100])) == 1 and len(np.unique(idx[100:])) > 50
    assert np.abs(book[idx[:100]] - clustered[:100]).max() < 1e-2


def test_compress_follows_the_web_layout(tmp_path):
    tree = random_tree(49, seed=4, cells=3000, depth=4)
    save_tree(tree, tmp_path / "raw.npz")
    info = compress_tree(tmp_path / "raw.npz", tmp_path / "c.npz", bits=16, retain=1, sigma_thresh=2.0, band_bits=(16,))
    z = np.load(tmp_path / "c.npz")
    assert sorted(z.files) == sorted(["data_dim", "child", "invradius3", "offset", "data_format", "quant_colors",
                                      "quant_map", "sigma", "data_retained", "compression"])
    assert z["quant_colors"].shape == (15, 65536, 3) and z["quant_map"].dtype == np.uint16
    assert z["data_retained"].shape == (1, tree.num_nodes, 2, 2, 2, 3)
    assert volrend_problems(tmp_path / "c.npz") == []
    back = load_tree(tmp_path / "c.npz")
    alive = (tree.child == 0) & (tree.data[..., -1] > 2.0)
    # fewer surviving leaves than codebook entries: quantisation is exact up to float16
    assert torch.allclose(back.data[alive], tree.data[alive], atol=2e-2)
    assert (back.data[~alive][..., -1] == 0).all()
    assert info["leaves_kept"] == int(alive.sum())
    # fewer entries for higher SH bands: still volrend's 65536-entry layout, indices stay inside each band's budget
    banded = compress_tree(tmp_path / "raw.npz", tmp_path / "banded.npz", band_bits=(16, 8, 6, 4))
    assert banded["band_bits"] == [16] + [8] * 3 + [6] * 5 + [4] * 7
    zb = np.load(tmp_path / "banded.npz")
    assert volrend_problems(tmp_path / "banded.npz") == [] and zb["quant_colors"].shape == (16, 65536, 3)
    for j, b in enumerate(banded["band_bits"]):
        assert zb["quant_map"][j].max() < 2 ** b and not zb["quant_colors"][j, 2 ** b:].any()
    uniform = compress_tree(tmp_path / "raw.npz", tmp_path / "uniform.npz", band_bits=(16,))
    assert banded["file_bytes"] < uniform["file_bytes"]
    coarse = load_tree(tmp_path / "banded.npz")
    assert torch.allclose(coarse.data[alive][:, [0, 16, 32, 48]], tree.data[alive][:, [0, 16, 32, 48]], atol=2e-2)
    compress_tree(tmp_path / "raw.npz", tmp_path / "c8.npz", bits=8)
    assert any("65536" in p for p in volrend_problems(tmp_path / "c8.npz"))
    compress_tree(tmp_path / "raw.npz", tmp_path / "sh4.npz", sh_degree=1, band_bits=(16,))
    low = load_tree(tmp_path / "sh4.npz")
    assert low.data_format == "SH4" and volrend_problems(tmp_path / "sh4.npz") == []
    keep = [c * 16 + k for c in range(3) for k in range(4)] + [48]
    assert torch.allclose(low.data[alive], tree.data[alive][:, keep], atol=2e-2)
    with pytest.raises(ValueError, match="outside 0..3"):
        compress_tree(tmp_path / "raw.npz", tmp_path / "x.npz", sh_degree=4)


# --- build and fine-tune from a teacher --------------------------------------------------------------------------------

def test_build_optimize_compress_eval_on_a_tiny_scene(tiny_scene, tiny_teacher, tmp_path):
    from nerfbake.octree.optimize import image_step
    from nerfbake.teacher.evaluate import render_camera as teacher_render
    from nerfbake.data.formats import load_dataset
    from nerfbake.octree.render import render_camera

    cfg = BuildConfig(grid=32, samples_per_leaf=8, autoscale_grid=16, weight_thresh=0.01)
    summary = build_octree(tiny_teacher, tmp_path / "tree.npz", cfg)
    assert summary["kept_voxels"] > 50 and summary["num_leaves"] >= summary["kept_voxels"]
    with pytest.raises(ValueError, match="box-scale.*contracted"):  # a bounded teacher has nothing beyond its box
        build_octree(tiny_teacher, tmp_path / "wide.npz", replace(cfg, box_scale=2.0))
    assert not (tmp_path / "wide.npz").exists()
    tree = load_tree(tmp_path / "tree.npz")
    assert tree.depth_limit == 4 and tree.sh_degree == 2
    ds = load_dataset(tiny_scene)
    from nerfbake.teacher.run import load_teacher
    teacher, *_ = load_teacher(tiny_teacher)
    cam = ds.frames[ds.split("test")[0]].camera
    a = render_camera(tree, cam)["rgb"]
    b = teacher_render(teacher, cam)["rgb"]
    assert -10 * np.log10(np.mean((a - b) ** 2)) > 20  # the tree renders what the teacher renders

    # one SGD step on one image lowers that image's error
    i = ds.split("train")[0]
    target = torch.from_numpy(ds.image(i)[..., :3].reshape(-1, 3).copy())
    opts = RenderOptions.training()
    before = image_step(tree, ds.frames[i].camera, target, opts, lr=1e5)
    after = image_step(tree, ds.frames[i].camera, target, opts, lr=0.0)
    assert after < before

    res = optimize_tree(tmp_path / "tree.npz", tiny_scene, tmp_path / "opt.npz",
                        OptimizeConfig(epochs=2, lr=1e5, val_every=1, val_views=2))
    assert res["best_val_psnr"] >= res["history"][0]["val_psnr"]
    assert load_tree(tmp_path / "opt.npz").num_leaves == tree.num_leaves
    res = optimize_tree(tmp_path / "tree.npz", tiny_scene, tmp_path / "kept.npz", OptimizeConfig(epochs=0, val_views=2))
    assert res["best_epoch"] == 0 and len(res["history"]) == 1  # 0 epochs: the built tree, unchanged
    assert torch.equal(load_tree(tmp_path / "kept.npz").data, load_tree(tmp_path / "tree.npz").data)

    assert main(["octree", "compress", "--tree", str(tmp_path / "opt.npz"), "--out", str(tmp_path / "c.npz"),
                 "--retain", "1", "--sigma-thresh", "0.5"]) == 0
    assert main(["octree", "eval", "--tree", str(tmp_path / "c.npz"), "--data", str(tiny_scene), "--max-views", "2",
                 "--repeats", "1", "--json"]) == 0


def test_octree_eval_and_info_print_the_contract_keys(fixtures, tiny_scene, tmp_path, capsys):
    tree = tmp_path / "t.npz"
    tree.write_bytes((fixtures / "good_svox_raw.npz").read_bytes())
    assert main(["octree", "info", str(tree), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["num_leaves"] == 3256 and info["volrend_problems"] == [] and info["env_map"] is None
    assert main(["octree", "eval", "--tree", str(tree), "--data", str(tiny_scene), "--max-views", "2",
                 "--repeats", "1", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    for k in ("psnr", "ssim", "lpips_vgg", "ms_per_frame", "fps", "num_leaves", "file_bytes", "device"):
        assert k in res, k
    poses = {"w": 24, "h": 16, "camera_angle_x": 0.8,
             "frames": [{"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]}]}
    (tmp_path / "poses.json").write_text(json.dumps(poses))
    assert main(["octree", "render", "--tree", str(tree), "--pose-file", str(tmp_path / "poses.json"),
                 "--out", str(tmp_path / "r"), "--sh-range", "0,1", "--depth"]) == 0
    assert (tmp_path / "r" / "0000.png").is_file() and np.load(tmp_path / "r" / "0000_depth.npy").shape == (16, 24)


def test_an_unbounded_360_teacher_builds_a_tree_over_its_core_and_a_forward_facing_one_is_refused(tmp_path, fox, fern):
    """Real captures: the octree route covers the uncontracted core of a 360 capture (the cube its cameras stand in);
    a forward-facing capture has no box to cover and gets a clear refusal naming SMERF."""
    from nerfbake.teacher.train import train_teacher
    from tests.helpers import tiny_config

    cfg = replace(tiny_config(steps=20), checkpoint_every=1000, val_every=10_000, batch_rays=128)
    cfg.hash.proposal = replace(cfg.hash.proposal, proposal_samples=16, final_samples=8, levels=3, log2_table=10)
    fox_cfg = replace(cfg, downscale=16)
    fox_run = train_teacher(fox, tmp_path / "fox", fox_cfg)
    summary = build_octree(fox_run, tmp_path / "fox.npz", BuildConfig(grid=32, samples_per_leaf=2, autoscale_grid=16,
                                                                      weight_thresh=0.01, env_map_height=6))
    assert "core" in summary["region"] and "environment map" in summary["region"] and summary["num_leaves"] > 0
    assert min(summary["box_min"]) >= -1 and max(summary["box_max"]) <= 1
    # --box-scale: the tree reaches into the room beyond the core (fitted to what the views see there)
    wide = build_octree(fox_run, tmp_path / "fox_wide.npz", BuildConfig(grid=32, samples_per_leaf=2, autoscale_grid=16,
                                                                         weight_thresh=0.01, env_map_height=6,
                                                                         box_scale=2.0))
    assert wide["region"].startswith("2 x") and min(wide["box_min"]) >= -2 and max(wide["box_max"]) <= 2
    assert min(wide["box_min"]) < -1 or max(wide["box_max"]) > 1
    # beyond the box, the environment map: each texel is the teacher's colour along its direction from the cameras'
    # mean position, from where that ray leaves the box on
    from nerfbake.data.formats import load_dataset
    from nerfbake.render.envmap import equirect_directions
    from nerfbake.teacher.sampling import ray_box
    from nerfbake.teacher.run import load_teacher

    assert summary["env_map"] == [6, 12]
    tree = load_tree(tmp_path / "fox.npz")
    teacher = load_teacher(fox_run)[0]
    centre = torch.tensor(np.mean([c.c2w[:3, 3] for c in load_dataset(fox, downscale=16).cameras("train")], 0)).float()
    d = equirect_directions(6, 12)[[1, 4], [3, 10]]
    o = centre.expand_as(d)
    _, t_far = ray_box(o, d, torch.tensor(summary["box_min"]).float(), torch.tensor(summary["box_max"]).float())
    expect = teacher.render_rays(o + t_far[:, None] * d, d, torch.ones(3))["rgb"].detach()
    assert (tree.env_map[[1, 4], [3, 10]] - expect).abs().max() <= 0.5 / 255 + 1e-4
    # fox has train and test only: fine-tuning picks its best epoch on training views, never on the test views
    res = optimize_tree(tmp_path / "fox.npz", fox, tmp_path / "fox_opt.npz", OptimizeConfig(epochs=1, downscale=16, val_views=2))
    assert res["val_split"] == "train" and (tmp_path / "fox_opt.npz").is_file()
    fern_run = train_teacher(fern, tmp_path / "fern", replace(cfg, steps=2))
    with pytest.raises(ValueError, match="forward-facing.*SMERF"):
        build_octree(fern_run, tmp_path / "fern.npz", BuildConfig(grid=32, samples_per_leaf=2, autoscale_grid=16))
    # --normalize object-centric: the user says fern is a 360 capture; the teacher records it, and the octree build
    # reads the photos the same way (a 360 scene: the core and its environment map)
    fern360 = train_teacher(fern, tmp_path / "fern360", replace(cfg, steps=2, normalize="object-centric"))
    meta = json.loads((fern360 / "config.json").read_text())
    assert meta["train"]["normalize"] == "object-centric" and meta["dataset"]["scene_kind"] == "unbounded-360"
    # read as a 360 capture, fern's whole core cube lies within the teacher's near bound of its cameras (its photos
    # show nothing that close): no tree to build, and the error says why
    with pytest.raises(ValueError, match="near bound.*use SMERF"):
        build_octree(fern360, tmp_path / "fern360.npz", BuildConfig(grid=32, samples_per_leaf=2, autoscale_grid=16,
                                                                    weight_thresh=0.0, env_map_height=4))
