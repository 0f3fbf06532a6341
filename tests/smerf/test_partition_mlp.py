"""SMERF's camera partition (eq. 6), the deferred-MLP lattice (eq. 7; checked against the viewer-equivalent
interpolation used by the baked renderer) and the simulated 8-bit quantisation."""
import numpy as np
import pytest
import torch

from nerfbake.smerf.assets import VIEWER_FROM_TRAIN
from nerfbake.smerf.baked_render import deferred_mlp_weights
from nerfbake.smerf.deferred_mlp import GridMLP, unique_rows
from nerfbake.smerf.partition import Partition, PartitionError
from nerfbake.smerf.run import distill_preset
from nerfbake.smerf.seams import boundary_cameras
from nerfbake.smerf.student import Student, StudentConfig, mlp_lattice_size


def test_baking_cameras_are_those_within_one_and_a_half_cells_of_the_centre():
    """SMERF appendix C.2: a submodel's occupancy grid is built from the cameras within 1.5 cell widths of its centre,
    its own cameras always among them."""
    cams = np.array([[x, 0.0, 0.0] for x in np.linspace(-1, 1, 21)] + [[-1.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    part = Partition.from_cameras(cams, k=2)
    for p in range(part.num_alive):
        own = part.assign(cams) == p
        centre = part.cell_centre(part.params_to_sm[p])
        dist = np.linalg.norm(part.normalize(cams) - centre, axis=1) / (2 / part.k)  # in cell widths
        near = part.baking_cameras(cams, p)
        np.testing.assert_array_equal(near, own | (dist <= 1.5))
        assert near.sum() > own.sum()  # neighbours' cameras join in
        np.testing.assert_array_equal(part.baking_cameras(cams, p, radius=0.0), own)


def test_partition_assigns_cameras_by_cell_and_inf_norm():
    rng = np.random.default_rng(0)
    # cameras in two rooms, diagonal from each other: only the cells they occupy come alive, one per room (their
    # heights span less than a cell, so the cube is placed to hold them in one layer: see the next test)
    cams = np.concatenate([rng.uniform([-4, -1, -1], [-2, 1, 1], (30, 3)), rng.uniform([2, 3, -1], [4, 5, 1], (30, 3))])
    part = Partition.from_cameras(cams, k=2)
    assert np.abs(part.normalize(cams)).max() <= 0.95 + 1e-9
    assert part.num_alive == 2 and part.submodel_scale == pytest.approx(1.6)
    home = part.assign(cams)
    assert len(set(home[:30]) & set(home[30:])) == 0  # the rooms get different submodels
    for i, p in zip(part.assign(cams), part.normalize(cams)):  # home cell = the cell holding the camera
        assert part.params_to_sm[i] == part.cell_index(p)
    assert Partition.from_cameras(cams, k=1).submodel_scale == pytest.approx(2.5)
    # a point in a dead cell goes to the inf-norm nearest alive centre
    dead = [s for s, p in enumerate(part.sm_to_params) if p < 0]
    assert len(dead) == 6
    for sm in dead:
        c = part.cell_centre(sm)
        world = c / part.scale + part.centre
        got = part.assign(world[None])[0]
        dists = [np.abs(c - part.cell_centre(s)).max() for s in part.params_to_sm]
        assert dists[got] == min(dists)
    with pytest.raises(PartitionError, match="outside the partition cube"):
        part.assign(np.array([[40.0, 0, 0]]), strict=True)
    with pytest.raises(PartitionError, match="no training cameras"):
        Partition.from_cameras(np.zeros((0, 3)), k=2)
    assert Partition.from_json(part.to_json()).sm_to_params == part.sm_to_params
    for p in range(part.num_alive):
        assert p not in part.neighbours(p)


@pytest.mark.parametrize("k", [2, 3, 4])
def test_cell_boundaries_run_through_the_cameras_only_along_axes_they_span(k):
    """A walk at eye height through a row of rooms: along x the cameras fill the cube (centred, as before); along y
    and z they span less than K cells, so the cube is placed to hold them in the fewest whole layers, centred in
    them. Centred on their box instead, the two-room scene's 80 cameras came alive in 8 cells at K = 2 (3 to 18
    cameras each) rather than 2 of 40."""
    rng = np.random.default_rng(4)
    cams = np.stack([rng.uniform(-6, 6, 200), rng.uniform(-0.9, 0.9, 200), rng.uniform(1.4, 1.8, 200)], 1)
    part = Partition.from_cameras(cams, k)
    cube = part.normalize(cams)
    assert np.abs(cube).max() <= 0.95 + 1e-9  # every camera inside the cube, the longest axis as before
    assert cube[:, 0].min() == pytest.approx(-0.95) and cube[:, 0].max() == pytest.approx(0.95)
    width = 2 / k
    for axis in (1, 2):
        layers = np.floor((cube[:, axis] + 1) / width)
        span = np.ptp(cube[:, axis])
        assert len(np.unique(layers)) == int(span // width) + 1  # the fewest layers that hold them
        lo, hi = layers.min() * width - 1, (layers.max() + 1) * width - 1
        assert (cube[:, axis].min() - lo) == pytest.approx(hi - cube[:, axis].max())  # centred in those layers
    assert part.num_alive == k * (int(np.ptp(cube[:, 1]) // width) + 1)
    # K = 1 keeps the object-centred cube
    assert np.allclose(Partition.from_cameras(cams, 1).centre, 0)


def test_partition_cube_grows_until_a_share_of_the_surfaces_lies_in_the_core():
    # a forward-facing capture: cameras within 0.4 of the origin, surfaces 1.3 to 6 in front of them
    cams = np.random.default_rng(2).uniform([-0.4, -0.13, -0.05], [0.4, 0.13, 0.05], (20, 3))
    surfaces = np.linspace(1.3, 6.0, 101)
    by_cameras = Partition.from_cameras(cams, k=1)
    assert by_cameras.submodel_scale * by_cameras.scale * 1.3 > 5  # every surface deep in the contracted shell
    part = Partition.from_cameras(cams, k=1, surface_distances=surfaces, core_quantile=0.2)
    in_core = part.submodel_scale * part.scale * surfaces <= 1 + 1e-9
    assert in_core.mean() == pytest.approx(0.2, abs=0.011)
    assert np.abs(part.normalize(cams)).max() < 0.95  # the cameras still lie in the cube
    # an object scene, cameras all around at 4: its surfaces already lie in the core; the cameras size the cube
    ring = np.stack([4 * np.cos(np.linspace(0, 6, 30)), 4 * np.sin(np.linspace(0, 6, 30)), np.ones(30)], 1)
    assert Partition.from_cameras(ring, 1, surface_distances=np.full(50, 0.6)).scale == Partition.from_cameras(ring, 1).scale
    # a room: cameras spread through it, its nearer surfaces within the cameras' span: the cameras size the cube
    spread = np.random.default_rng(3).uniform(-1.5, 1.5, (40, 3))
    walls = np.linspace(0.74, 2.5, 60)
    assert Partition.from_cameras(spread, 1, surface_distances=walls).scale == Partition.from_cameras(spread, 1).scale
    # K > 1 is cut by the cameras alone
    assert Partition.from_cameras(cams, 2, surface_distances=surfaces).scale == Partition.from_cameras(cams, 2).scale


def test_an_object_ringed_by_cameras_is_scaled_up_to_fill_the_core():
    """``fill_quantile``: an object whose surfaces all lie well inside the K = 1 core gets a larger submodel scale, so
    that share of them reaches the core's face; a scene reaching past the core, K > 1, and an explicit factor keep
    theirs, and the growth stops at MAX_FILL times the authors' 2.5."""
    from nerfbake.smerf.partition import MAX_FILL

    ring = np.stack([4 * np.cos(np.linspace(0, 6, 30)), 4 * np.sin(np.linspace(0, 6, 30)), np.ones(30)], 1)
    object_surfaces = np.linspace(0.2, 1.0, 101)
    authors = Partition.from_cameras(ring, 1, surface_distances=object_surfaces)
    assert authors.scale_factor == 2.5 and authors.submodel_scale * authors.scale * 1.0 < 0.7  # a core 30 % empty
    part = Partition.from_cameras(ring, 1, surface_distances=object_surfaces, fill_quantile=0.9)
    assert part.scale == authors.scale and part.sm_to_params == authors.sm_to_params  # the cube is the cameras' still
    reach = part.submodel_scale * part.scale * object_surfaces
    assert np.quantile(reach, 0.9) == pytest.approx(0.95) and part.scale_factor > 3.5
    tiny = Partition.from_cameras(ring, 1, surface_distances=object_surfaces * 0.01, fill_quantile=0.9)
    assert tiny.scale_factor == pytest.approx(MAX_FILL * 2.5)
    walls = np.linspace(0.5, 6.0, 60)  # surfaces beyond the core already: nothing to fill
    assert Partition.from_cameras(ring, 1, surface_distances=walls, fill_quantile=0.9).scale_factor == 2.5
    assert Partition.from_cameras(ring, 2, surface_distances=object_surfaces, fill_quantile=0.9).scale_factor == 0.8
    assert Partition.from_cameras(ring, 1, scale_factor=2.5, surface_distances=object_surfaces,
                                  fill_quantile=0.9).scale_factor == 2.5


def test_boundary_cameras_are_the_ones_nearest_a_face_shared_with_an_alive_neighbour():
    rng = np.random.default_rng(1)
    # two rooms along x, every camera at one y and z: with K = 2 only the two cells split at x = 0 come alive
    x = np.concatenate([rng.uniform(-4, -0.8, 20), rng.uniform(0.8, 4, 20)])
    cams = np.stack([x, np.full(40, 0.25), np.full(40, 0.25)], 1)
    part = Partition.from_cameras(cams, k=2)
    assert part.num_alive == 2
    probes = np.array([[-0.1, 0.25, 0.25], [2.5, 0.25, 0.25], [40.0, 0.25, 0.25]])  # by the face, deep in B, outside
    pairs = boundary_cameras(part, probes, 5)
    assert [q["camera"] for q in pairs] == [0, 1]  # nearest first; the one outside the cube is skipped
    q = pairs[0]
    assert {q["home"], q["neighbour"]} == {0, 1} and q["home"] == part.assign(probes[:1])[0]
    cube_x = part.normalize(probes)[:, 0]
    assert q["gap_cell_widths"] == pytest.approx(abs(cube_x[0]))  # cells are 1 wide in the cube at K = 2
    assert pairs[1]["gap_cell_widths"] == pytest.approx(abs(cube_x[1]))


def test_grid_mlp_interpolation_matches_the_viewer():
    g = torch.Generator().manual_seed(0)
    mlp = GridMLP(1, generator=g)
    with torch.no_grad():
        for p in list(mlp.kernels) + list(mlp.biases):
            p.add_(torch.randn(p.shape, generator=g) * 0.3)  # make every lattice node different
    exported = {k: np.asarray(v["data"], np.float32).reshape(v["shape"]) for k, v in mlp.export().items()}
    params = {"num_submodels": 1, "num_local_submodels": 1, "submodel_voxel_size": 2.0, "params_to_sm": [0]}
    for viewer_pos in np.random.default_rng(1).uniform(-1.2, 1.2, (5, 3)):
        ref = deferred_mlp_weights(exported, params, 0, viewer_pos)
        train_pos = torch.tensor(VIEWER_FROM_TRAIN @ viewer_pos, dtype=torch.float32)[None]
        ours = mlp.weights_at(torch.zeros(1, dtype=torch.long), train_pos)
        for (k, b), (rk, rb) in zip(ours, ref):
            assert np.allclose(k[0].detach().numpy(), rk, atol=1e-5) and np.allclose(b[0].detach().numpy(), rb, atol=1e-5)


def test_one_deferred_mlp_per_submodel_the_authors_lattice_in_the_paper_preset_and_the_viewer_reads_either():
    rooms = np.concatenate([np.random.default_rng(0).uniform([-4, -1, -1], [-2, 1, 1], (30, 3)),
                            np.random.default_rng(1).uniform([2, 3, -1], [4, 5, 1], (30, 3))])
    k1, k2 = Partition.from_cameras(rooms, k=1), Partition.from_cameras(rooms, k=2)
    assert Student(StudentConfig(sparse_resolution=4, triplane_resolution=8), k1).mlp.grid == 1
    assert Student(StudentConfig(sparse_resolution=4, triplane_resolution=8), k2).mlp.grid == 1
    # students recorded before one MLP at every K (mlp_grid None) load with the lattice they were trained with
    assert Student(StudentConfig(sparse_resolution=4, triplane_resolution=8, mlp_grid=None), k2).mlp.grid == 5
    assert mlp_lattice_size(StudentConfig(mlp_grid=None), 1) == 1
    assert mlp_lattice_size(StudentConfig(mlp_grid=3), 1) == 3 and mlp_lattice_size(StudentConfig(mlp_grid=1), 2) == 1
    assert distill_preset("paper").student.mlp_grid == 5  # the authors' lattice at every K in the GPU preset
    # P = 1: the viewer's corner clamping gives the one MLP at every camera position, inside the cell or not
    mlp = GridMLP(1, grid=1, generator=torch.Generator().manual_seed(0))
    exported = {k: np.asarray(v["data"], np.float32).reshape(v["shape"]) for k, v in mlp.export().items()}
    assert exported["ResampleDense_0/kernel"].shape[1:4] == (1, 1, 1)
    assert float(mlp.tv_loss()) == 0.0  # no neighbours: no TV (not the NaN mean of nothing)
    params = {"num_submodels": 1, "num_local_submodels": 1, "submodel_voxel_size": 2.0, "params_to_sm": [0]}
    for viewer_pos in np.random.default_rng(2).uniform(-1.5, 1.5, (4, 3)):
        for i, (k, b) in enumerate(deferred_mlp_weights(exported, params, 0, viewer_pos)):
            assert np.allclose(k, exported[f"ResampleDense_{i}/kernel"][0, 0, 0, 0], atol=1e-6)
            assert np.allclose(b, exported[f"ResampleDense_{i}/bias"][0, 0, 0, 0], atol=1e-6)


def test_grid_mlp_trains_and_its_tv_is_zero_when_constant():
    mlp = GridMLP(2, in_dim=5, generator=torch.Generator().manual_seed(0))
    assert float(mlp.tv_loss().detach()) == 0.0
    x = torch.rand(64, 5)
    pos = torch.rand(64, 3) * 2 - 1
    idx = torch.randint(0, 2, (64,))
    target = torch.rand(64, 3)
    opt = torch.optim.Adam(mlp.parameters(), lr=1e-2)
    first = None
    for _ in range(50):
        loss = ((mlp(x, idx, pos) - target) ** 2).mean() + 0.1 * mlp.tv_loss()
        first = first if first is not None else float(loss.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.5 * first and float(mlp.tv_loss().detach()) > 0


def test_simulated_quantisation_is_the_bake_round_trip_with_straight_through_gradients():
    from nerfbake.render.quantize import RANGE_DENSITY, RANGE_FEATURES, from_bytes, simulate, to_bytes

    x = (torch.rand(1000, dtype=torch.float64) - 0.5) * 40
    for rng in (RANGE_FEATURES, RANGE_DENSITY):
        baked = from_bytes(to_bytes(x, rng), rng)
        xs = x.clone().requires_grad_()
        sim = simulate(xs, rng)
        assert np.allclose(sim.detach().numpy(), baked, atol=1e-9)
        assert np.abs(baked - x.clamp(*rng).numpy()).max() <= (rng[1] - rng[0]) / 255 / 2 + 1e-9
        sim.sum().backward()
        assert torch.equal(xs.grad, torch.ones_like(xs))


def test_grid_mlp_forward_equals_per_ray_interpolated_layers():
    g = torch.Generator().manual_seed(2)
    mlp = GridMLP(3, in_dim=7, generator=g)
    with torch.no_grad():
        for p in list(mlp.kernels) + list(mlp.biases):
            p.add_(torch.randn(p.shape, generator=g) * 0.3)
    # Rays share cameras, as in training: 6 camera positions, each seen from several submodels.
    cams = torch.rand(6, 3, generator=g) * 2.4 - 1.2
    x, pos = torch.rand(40, 7, generator=g), cams[torch.randint(0, 6, (40,), generator=g)]
    idx = torch.randint(0, 3, (40,), generator=g)
    h = x
    layers = mlp.weights_at(idx, pos)
    for i, (k, b) in enumerate(layers):
        h = torch.einsum("ri,rio->ro", h, k) + b
        h = torch.nn.functional.elu(h) if i < 2 else torch.sigmoid(h)
    assert torch.allclose(mlp(x, idx, pos), h, atol=1e-5)


def test_unique_rows_groups_equal_rows_as_torch_unique_does():
    g = torch.Generator().manual_seed(3)
    rows = torch.randn(7, 4, generator=g)
    key = rows[torch.randint(0, 7, (300,), generator=g)]
    uniq, inv = unique_rows(key)
    ref, _ = torch.unique(key, dim=0, return_inverse=True)
    assert uniq.shape == ref.shape == (7, 4)
    assert torch.equal(uniq[inv], key)
    assert sorted(map(tuple, uniq.tolist())) == sorted(map(tuple, ref.tolist()))


def test_deferred_mlp_json_reads_back_the_weights_at_the_precision_asked():
    import gzip
    import json

    from nerfbake.smerf.deferred_mlp import deferred_mlp_text

    export = GridMLP(3, width=16, grid=5, generator=torch.Generator().manual_seed(0)).export()
    for precision in (np.float32, np.float16):
        back = json.loads(deferred_mlp_text(export, precision))
        assert list(back) == list(export)
        for name, entry in export.items():
            assert back[name]["shape"] == entry["shape"]
            # the shortest digits that read back as the same value at that precision
            np.testing.assert_array_equal(np.float32(back[name]["data"]).astype(precision),
                                          np.float32(entry["data"]).astype(precision))
    # the shortest digits, not a widened double's 17: the gzip file is markedly smaller, and half again at float16
    size = {p: len(gzip.compress(deferred_mlp_text(export, p).encode())) for p in (np.float32, np.float16)}
    assert size[np.float32] < 0.75 * len(gzip.compress(json.dumps(export).encode()))
    assert size[np.float16] < 0.65 * size[np.float32]
    big = {"w": {"shape": [2], "data": [1e5, 0.1234567]}}  # past float16's range: that array stays float32
    assert np.float32(json.loads(deferred_mlp_text(big))["w"]["data"]).tolist() == np.float32([1e5, 0.1234567]).tolist()
    export["ResampleDense_0/bias"]["data"][0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        deferred_mlp_text(export)
