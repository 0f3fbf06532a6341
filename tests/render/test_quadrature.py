import torch

from nerfbake.render import alpha_from_density, composite, transmittance_from_alpha, weights_from_density
from nerfbake.render.sampling import uniform_t


def test_weights_sum_to_one_minus_final_transmittance():
    g = torch.Generator().manual_seed(0)
    sigma = torch.rand(64, 32, generator=g) * 5
    t = torch.sort(torch.rand(64, 33, generator=g) * 4, dim=-1).values
    w, alpha = weights_from_density(sigma, t)
    trans = transmittance_from_alpha(alpha)
    assert (w >= 0).all()
    assert (w.sum(-1) <= 1 + 1e-6).all()
    torch.testing.assert_close(w.sum(-1), 1 - trans[:, -1])


def test_constant_density_matches_beer_lambert():
    sigma = torch.full((1, 100), 0.7)
    t = uniform_t(torch.tensor([1.0]), torch.tensor([3.0]), 100)
    w, _ = weights_from_density(sigma, t)
    torch.testing.assert_close(w.sum(), torch.tensor(1 - torch.exp(torch.tensor(-0.7 * 2.0)).item()))


def test_composite_background_and_depth():
    # One opaque interval at t in [2, 2.2] in front of a white background.
    t = torch.tensor([[0.0, 1.0, 2.0, 2.2, 5.0]])
    sigma = torch.tensor([[0.0, 0.0, 1e4, 0.0]])
    w, _ = weights_from_density(sigma, t)
    rgb = torch.tensor([[[0.0, 0, 0], [0, 0, 0], [0.2, 0.4, 0.6], [0, 0, 0]]])
    out = composite(w, rgb, background=1.0, t=t)
    torch.testing.assert_close(out["rgb"], torch.tensor([[0.2, 0.4, 0.6]]))
    torch.testing.assert_close(out["acc"], torch.tensor([1.0]))
    torch.testing.assert_close(out["depth"], torch.tensor([2.1]))
    # Empty ray: background only.
    out = composite(torch.zeros(1, 4), rgb, background=torch.tensor([0.1, 0.2, 0.3]))
    torch.testing.assert_close(out["rgb"], torch.tensor([[0.1, 0.2, 0.3]]))


def test_alpha_is_stable_for_tiny_densities():
    a = alpha_from_density(torch.tensor([1e-9]), torch.tensor([1.0]))
    torch.testing.assert_close(a, torch.tensor([1e-9]), rtol=1e-4, atol=0)
