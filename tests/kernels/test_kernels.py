"""Warp kernels against slow torch references on the same inputs."""
import platform

import pytest
import torch

from nerfbake.kernels import parallel_map
from nerfbake.kernels.hashgrid import hash_encode, hash_encode_reference
from nerfbake.kernels.march import march_rays
from nerfbake.render.packed import packed_composite, packed_median_depth, packed_weights
from nerfbake.render.quadrature import composite, weights_from_density
from nerfbake.train.loop import DataParallel
from tests.helpers import devices


def grid_setup(levels=6, log2_table=10, rows=None):
    rows = rows or 2**log2_table
    res = torch.tensor([4, 7, 11, 19, 33, 60][:levels], dtype=torch.int32)
    dense = ((res.long() + 1) ** 3 <= rows).int()
    table = torch.randn(levels, rows, 2, generator=torch.Generator().manual_seed(0))
    return res, dense, table


@pytest.mark.parametrize("rows", [1024, 1000], ids=["2^k-rows", "other-rows"])  # masked or modulo hash
@devices
def test_hash_encoding_matches_reference_and_has_both_kinds_of_level(rows, device):
    res, dense, table = grid_setup(rows=rows)
    assert dense.any() and not dense.all()
    x = torch.rand(3000, 3, generator=torch.Generator().manual_seed(1))
    x[:10] = torch.tensor([0.0, 1.0, 0.999999])  # the box's faces
    kernel = hash_encode(x.to(device), table.to(device), res.to(device), dense.to(device)).cpu()
    torch.testing.assert_close(kernel, hash_encode_reference(x, table, res, dense))


@devices
def test_hash_encoding_gradient_matches_reference(device):
    res, dense, table = grid_setup()
    x = torch.rand(2000, 3, generator=torch.Generator().manual_seed(2))
    g = torch.randn(2000, 12, generator=torch.Generator().manual_seed(3))
    t1 = table.clone().to(device).requires_grad_()
    t2 = table.clone().requires_grad_()
    (hash_encode(x.to(device), t1, res.to(device), dense.to(device)) * g.to(device)).sum().backward()
    (hash_encode_reference(x, t2, res, dense) * g).sum().backward()
    torch.testing.assert_close(t1.grad.cpu(), t2.grad, atol=1e-5, rtol=1e-5)


def test_hash_encoding_gradient_by_finite_differences():
    res, dense, table = grid_setup(3, 8)
    table = table.double().float()
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(4))
    t = table.clone().requires_grad_()
    hash_encode(x, t, res, dense).sum().backward()
    # The encoding is linear in the table: the finite difference of one entry equals its gradient.
    nz = torch.nonzero(t.grad.abs() > 1e-3)[:5]
    for lvl, row, f in nz.tolist():
        eps = 1e-2
        tp, tm = table.clone(), table.clone()
        tp[lvl, row, f] += eps
        tm[lvl, row, f] -= eps
        fd = (hash_encode(x, tp, res, dense).sum() - hash_encode(x, tm, res, dense).sum()) / (2 * eps)
        assert abs(float(fd) - float(t.grad[lvl, row, f])) < 1e-3


@devices
def test_marching_matches_a_dense_reference(device):
    g = torch.Generator().manual_seed(5)
    grid = torch.rand(16, 16, 16, generator=g) > 0.7
    box_min, box_max = torch.tensor([-1.0, -1, -1]), torch.tensor([1.0, 1, 1])
    n = 300
    origins = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0, 0, 3.0])
    dirs = torch.nn.functional.normalize(torch.tensor([0, 0, -1.0]) + 0.3 * torch.randn(n, 3, generator=g), dim=-1)
    t_near, t_far = torch.full((n,), 1.0), torch.full((n,), 5.0)
    dt = 0.05
    offset = torch.rand(n, generator=g)
    on = [v.to(device) for v in (origins, dirs, t_near, t_far, grid, box_min, box_max)]
    ray_idx, t0, t1 = (v.cpu() for v in march_rays(*on, dt, offset.to(device)))
    # Reference: every step's midpoint, kept when its cell is occupied.
    steps = torch.arange(0, 200).float()
    t = t_near[:, None] + offset[:, None] * dt + steps * dt
    valid = t < t_far[:, None]
    mid = origins[:, None] + (t + dt / 2)[..., None] * dirs[:, None]
    ijk = ((mid - box_min) / (box_max - box_min) * 16).floor().long()
    inside = ((ijk >= 0) & (ijk < 16)).all(-1)
    occ = torch.zeros_like(inside)
    occ[inside] = grid[ijk[inside][:, 0], ijk[inside][:, 1], ijk[inside][:, 2]]
    keep = occ & valid
    ref_idx = torch.arange(n)[:, None].expand_as(keep)[keep]
    assert torch.equal(ray_idx, ref_idx)
    torch.testing.assert_close(t0, t[keep], atol=1e-4, rtol=0)
    torch.testing.assert_close(t1, torch.minimum(t + dt, t_far[:, None])[keep], atol=1e-4, rtol=0)


def test_packed_compositing_equals_dense_quadrature():
    g = torch.Generator().manual_seed(6)
    r, s = 50, 20
    t = torch.sort(torch.rand(r, s + 1, generator=g) * 4 + 2, dim=-1).values
    sigma = torch.rand(r, s, generator=g) * 3
    rgb = torch.rand(r, s, 3, generator=g)
    w, _ = weights_from_density(sigma, t)
    dense = composite(w, rgb, background=0.5, t=t)
    ray_idx = torch.arange(r).repeat_interleave(s)
    pw, _ = packed_weights(sigma.reshape(-1), t[:, :-1].reshape(-1), t[:, 1:].reshape(-1), ray_idx, r)
    packed = packed_composite(pw, rgb.reshape(-1, 3), t[:, :-1].reshape(-1), t[:, 1:].reshape(-1), ray_idx, r, 0.5)
    torch.testing.assert_close(pw.view(r, s), w, atol=1e-6, rtol=1e-5)
    for k in ("rgb", "acc", "depth"):
        torch.testing.assert_close(packed[k], dense[k], atol=1e-5, rtol=1e-5)
    # the median depth: the first interval at which a ray's running weight reaches half its total
    median = packed_median_depth(pw, t[:, :-1].reshape(-1), t[:, 1:].reshape(-1), ray_idx, r)
    first = (torch.cumsum(w.double(), -1) >= 0.5 * w.double().sum(-1, keepdim=True)).double().argmax(-1)
    torch.testing.assert_close(median, (0.5 * (t[:, :-1] + t[:, 1:])).gather(1, first[:, None])[:, 0])
    no_weight = packed_median_depth(torch.zeros(3), torch.zeros(3), torch.ones(3), torch.tensor([0, 0, 2]), 3)
    assert torch.isinf(no_weight).all()  # rays with no weight (1) or no samples have no depth


@devices
def test_contracted_marching_matches_a_step_by_step_reference(device):
    """Unbounded scenes: the grid spans contracted space and steps grow as r^2 beyond the unit cube."""
    from nerfbake.teacher.sampling import OccupancyGrid

    g = torch.Generator().manual_seed(7)
    grid = OccupancyGrid([-1.0] * 3, [1.0] * 3, resolution=16, dt=0.05, contracted=True)
    grid.occupied.copy_(torch.rand(16, 16, 16, generator=g) > 0.5)
    n = 40
    origins = 0.8 * (2 * torch.rand(n, 3, generator=g) - 1)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    t_near, t_far = torch.full((n,), 0.05), torch.full((n,), 200.0)
    offset = torch.rand(n, generator=g)
    dt = 0.05
    on = [v.to(device) for v in (origins, dirs, t_near, t_far, grid.occupied, grid.grid_min, grid.grid_max)]
    ray_idx, t0, t1 = (v.cpu() for v in march_rays(*on, dt, offset.to(device), contract_centre=grid.centre.to(device),
                                                     contract_half=grid.half.to(device)))
    steps = 0
    for r in range(n):
        o, d = origins[r].double(), dirs[r].double()
        stretch = lambda t: max(1.0, float((o + t * d).abs().max()) ** 2)  # noqa: E731
        t = float(t_near[r]) + float(offset[r]) * dt * stretch(float(t_near[r]))
        want = []
        while t < float(t_far[r]):
            h = dt * stretch(t)
            if bool(grid.occupied_at((o + (t + 0.5 * h) * d).float()[None])[0]):
                want.append(t)
            t += h
        got = t0[ray_idx == r]
        assert got.numel() == len(want), r
        torch.testing.assert_close(got.double(), torch.tensor(want, dtype=torch.float64), rtol=1e-4, atol=1e-4)
        steps += len(want)
    assert steps > 100  # rays really crossed occupied cells, far ones too
    assert float(t1.max()) > 20  # steps reach far beyond the unit cube


def test_packed_distortion_loss_equals_the_dense_form():
    from nerfbake.render.packed import packed_distortion_loss
    from nerfbake.render.stepfun import distortion_loss

    g = torch.Generator().manual_seed(8)
    s = torch.sort(torch.rand(5, 9, generator=g), dim=-1).values
    w = torch.rand(5, 8, generator=g) / 8
    ray_idx = torch.arange(5).repeat_interleave(8)
    packed = packed_distortion_loss(s[:, :-1].reshape(-1), s[:, 1:].reshape(-1), w.reshape(-1), ray_idx, 5)
    torch.testing.assert_close(packed, distortion_loss(s, w))


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="flush-to-zero as tested is x86's")
def test_trainers_and_the_kernel_pool_round_subnormal_floats_to_zero():
    """A trainer's process, and every kernel pool thread, computes with subnormals flushed (``flush_denormals``):
    Adam's decaying moments went subnormal mid-distillation and made its dense step ~6× slower."""
    def tiny(_=None):
        return (torch.full((64,), 1e-39) * 1.0).abs().max().item()

    DataParallel()  # what every trainer builds first
    assert tiny() == 0.0
    assert parallel_map(tiny, range(4)) == [0.0] * 4
