"""The hash teacher's occupancy grid: which cells an update evaluates, and that pruning follows the field."""
import torch

from nerfbake.teacher.sampling import OccupancyGrid


def ball_density(x: torch.Tensor) -> torch.Tensor:
    """Dense (100 per unit) inside a ball of radius 0.3 at the origin, empty elsewhere."""
    return torch.where(x.norm(dim=-1) < 0.3, 100.0, 0.0)


def test_update_evaluates_everything_first_then_a_random_share_and_prunes_to_the_field():
    grid = OccupancyGrid([-1.0] * 3, [1.0] * 3, resolution=32, dt=0.01, alpha_thresh=0.01)
    gen = torch.Generator().manual_seed(0)
    n = 32 ** 3
    assert torch.equal(grid.cells_to_update(gen), torch.arange(n))
    grid.update(ball_density, gen)
    idx = grid.cells_to_update(gen)
    assert (idx[1:] > idx[:-1]).all()  # sorted and unique
    assert 0.9 * n * grid.fraction < idx.numel() <= n * grid.fraction
    # Cells inside the ball are occupied, cells far outside pruned; the ball's cells stay occupied as updates go on.
    inside = grid.occupied[16, 16, 16]
    assert inside and not grid.occupied[0, 0, 0]
    for _ in range(20):
        grid.update(ball_density, gen)
    assert grid.occupied[16, 16, 16] and not grid.occupied[0, 0, 0]
    assert grid.occupancy_fraction < 0.05
    # Without pruning every cell stays occupied while the estimate keeps following the field.
    grid.update(ball_density, gen, prune=False)
    assert grid.occupied.all() and grid.density[0, 0, 0] < grid.density[16, 16, 16]



def test_final_refresh_finds_thin_structures_the_running_estimate_lets_decay():
    """A sheet 1/8 of a cell thick beside a dense ball: one jittered point per update rarely lands in the sheet and
    the running estimate decays between hits, so at any moment it holds many of the sheet's cells empty; the
    end-of-training refresh (16 points per cell) marks them, and nothing in the empty space around."""
    res, cell = 16, 2.0 / 16
    lo = -1.0 + 5 * cell + 0.4 * cell  # inside the sixth layer of cells along x, away from its centre

    def density(x):
        sheet = (x[:, 0] > lo) & (x[:, 0] < lo + cell / 8)
        return torch.where(sheet, 10.0, 0.0) + ball_density(x - 0.5) * 10  # the ball keeps the mean density high

    gen = torch.Generator().manual_seed(0)
    grid = OccupancyGrid([-1.0] * 3, [1.0] * 3, resolution=res, dt=0.01, alpha_thresh=0.01)
    for _ in range(200):
        grid.update(density, gen)
    held = grid.occupied[5].float().mean()
    assert held < 0.7  # the running estimate holds a large share of the sheet's cells empty
    grid.refresh(density, gen)
    assert grid.occupied[5].float().mean() > max(0.8, held)  # P(16 points all miss a 1/8 slab) = (7/8)^16 ~ 0.12
    assert not grid.occupied[:5].any() and not grid.occupied[6:9].any()


def test_dilated_lookup_finds_the_cell_a_point_is_in_contracted_or_not():
    """The octree builder skips queries where ``may_be_occupied`` (this lookup, grown by a cell) is False: on a
    contracted grid the point must be mapped through the contraction, not linearly over the box."""
    for contracted in (False, True):
        grid = OccupancyGrid([0.0] * 3, [2.0] * 3, resolution=16, contracted=contracted)
        grid.occupied.zero_()
        p = torch.tensor([[1.7, 1.1, 0.4]])  # inside the box: contracted, it lies in the grid's middle half
        cell = ((grid.to_grid_space(p) - grid.grid_min) / (grid.grid_max - grid.grid_min) * 16).long()[0]
        grid.occupied[tuple(cell)] = True
        assert grid.occupied_at(p).item()
        cell_width = 4 / 16 if contracted else 2 / 16  # in world units: inside the box the contraction is x - 1
        beside = p + torch.tensor([[cell_width, 0.0, 0.0]])  # the next cell along x
        assert not grid.occupied_at(beside).item() and grid.occupied_at(beside, dilate=1).item()
        far = torch.tensor([[0.1, 1.9, 1.9]])
        assert not grid.occupied_at(far, dilate=1).item()
