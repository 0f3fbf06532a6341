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
