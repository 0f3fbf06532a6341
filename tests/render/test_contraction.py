import torch

from nerfbake.render import contract, uncontract


def test_identity_inside_unit_cube():
    x = torch.rand(1000, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    torch.testing.assert_close(contract(x), x)


def test_range_and_inverse():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(5000, 3, generator=g, dtype=torch.float64) * torch.exp(torch.randn(5000, 1, generator=g, dtype=torch.float64) * 2)
    c = contract(x)
    assert (c.abs().amax(-1) < 2).all()
    torch.testing.assert_close(uncontract(c), x, rtol=1e-9, atol=1e-9)


def test_formula_outside():
    x = torch.tensor([[4.0, 2.0, -1.0]], dtype=torch.float64)
    # inf-norm 4 attained by x: 2 - 1/4; the others divided by 4.
    torch.testing.assert_close(contract(x), torch.tensor([[1.75, 0.5, -0.25]], dtype=torch.float64))


def test_continuous_across_the_unit_cube_and_between_faces():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(2000, 3, generator=g, dtype=torch.float64)
    x = x / x.abs().amax(-1, keepdim=True)  # on the cube's surface
    for eps in (1e-6, 1e-8):
        torch.testing.assert_close(contract(x * (1 + eps)), contract(x * (1 - eps)), atol=5 * eps, rtol=0)
    # Inside one pyramid (same coordinate attains the inf-norm) the map is continuous too.
    p = torch.tensor([[3.0, 2.0, 0.5]], dtype=torch.float64)
    torch.testing.assert_close(contract(p + 1e-7), contract(p), atol=1e-6, rtol=0)


def test_lines_stay_lines_within_a_pyramid():
    # Piecewise projective: collinear points in one pyramid (x attains the inf-norm) stay collinear.
    a, b = torch.tensor([2.0, 0.3, -0.5], dtype=torch.float64), torch.tensor([6.0, 1.5, 2.0], dtype=torch.float64)
    s = torch.linspace(0, 1, 7, dtype=torch.float64)[:, None]
    c = contract(a + s * (b - a))
    d = c[1:] - c[0]
    cross = torch.linalg.cross(d, d[-1].expand_as(d))
    assert cross.abs().max() < 1e-12
