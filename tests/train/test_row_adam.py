"""RowAdam: torch.optim.Adam's arithmetic on the rows a step wrote, nothing elsewhere."""
import copy

import pytest
import torch

from nerfbake.train.row_adam import RowAdam


def _pair(rows=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    grid = torch.randn(rows, 8, generator=g)
    dense = torch.randn(5, 3, generator=g)
    return grid, dense, g


def _opts(grid, dense, masks_on: bool):
    a = [torch.nn.Parameter(grid.clone()), torch.nn.Parameter(dense.clone())]
    b = [torch.nn.Parameter(grid.clone()), torch.nn.Parameter(dense.clone())]
    mask = torch.zeros(grid.shape[0], dtype=torch.uint8)
    groups = lambda p: [{"params": [p[0]], "lr": 0.05}, {"params": [p[1]], "lr": 0.01}]  # noqa: E731
    ref = torch.optim.Adam(groups(a), betas=(0.9, 0.99), eps=1e-15)
    mine = RowAdam(groups(b), row_masks={b[0]: mask} if masks_on else None, betas=(0.9, 0.99), eps=1e-15)
    return a, ref, b, mine, mask


def test_every_row_touched_is_torch_adam_step_for_step():
    grid, dense, g = _pair()
    a, ref, b, mine, mask = _opts(grid, dense, True)
    for _ in range(6):
        grads = [torch.randn(p.shape, generator=g) for p in a]
        for opt, ps in ((ref, a), (mine, b)):
            opt.zero_grad()
            for p, gr in zip(ps, grads):
                p.grad = gr.clone() if p.grad is None else p.grad.add_(gr)
        mask.fill_(1)
        ref.step()
        mine.step()
        for p, q in zip(a, b):
            torch.testing.assert_close(p, q, atol=1e-6, rtol=1e-6)
        assert int(mask.sum()) == 0 and not b[0].grad.any()  # the step consumed the mask and zeroed the rows


def test_untouched_rows_keep_value_and_moments_touched_rows_follow_adam_on_their_own():
    grid, dense, g = _pair(seed=1)
    a, ref, b, mine, mask = _opts(grid, dense, True)
    rows = torch.tensor([3, 10, 11, 40])
    for _ in range(4):  # the same rows every step: on them RowAdam is Adam, elsewhere nothing moves
        gr = torch.zeros_like(grid)
        gr[rows] = torch.randn(len(rows), 8, generator=g)
        gd = torch.randn(dense.shape, generator=g)
        mine.zero_grad()
        b[0].grad = gr.clone() if b[0].grad is None else b[0].grad.add_(gr)
        b[1].grad = gd.clone()
        mask[rows] = 1
        mine.step()
        ref.zero_grad()
        a[0].grad, a[1].grad = gr.clone(), gd.clone()
        ref.step()
    others = torch.ones(grid.shape[0], dtype=torch.bool)
    others[rows] = False
    assert torch.equal(b[0].detach()[others], grid[others])
    assert not mine.state[b[0]]["exp_avg"][others].any()
    torch.testing.assert_close(b[0].detach()[rows], a[0].detach()[rows], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(b[1], a[1], atol=1e-6, rtol=1e-6)
    # dense Adam kept moving a row after its gradient stopped; RowAdam leaves it where its last gradient put it
    mask.zero_()
    before = b[0].detach().clone()
    b[0].grad.zero_()
    mine.step()
    assert torch.equal(b[0].detach(), before)


def test_loads_a_torch_adam_checkpoint_and_continues_as_adam():
    grid, dense, g = _pair(seed=2)
    a, ref, b, mine, mask = _opts(grid, dense, True)
    for _ in range(3):
        ref.zero_grad()
        for p in a:
            p.grad = torch.randn(p.shape, generator=g)
        ref.step()
    with torch.no_grad():
        for p, q in zip(a, b):
            q.copy_(p)
    mine.load_state_dict(copy.deepcopy(ref.state_dict()))  # a checkpoint holds copies, not the live moments
    grads = [torch.randn(p.shape, generator=g) for p in a]
    for p, q, gr in zip(a, b, grads):
        p.grad, q.grad = gr.clone(), gr.clone()
    mask.fill_(1)
    ref.step()
    mine.step()
    for p, q in zip(a, b):
        torch.testing.assert_close(p, q, atol=1e-6, rtol=1e-6)


def test_a_mask_that_does_not_fit_its_parameter_is_refused():
    p = torch.nn.Parameter(torch.zeros(10, 8))
    with pytest.raises(ValueError, match="one uint8 per row"):
        RowAdam([p], row_masks={p: torch.zeros(9, dtype=torch.uint8)})
    with pytest.raises(ValueError, match="one uint8 per row"):
        RowAdam([p], row_masks={p: torch.zeros(10, dtype=torch.bool)})
