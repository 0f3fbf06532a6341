import torch

from nerfbake.render import sample_pdf, stratified_t, uniform_t


def test_stratified_sorted_and_within_bounds():
    g = torch.Generator().manual_seed(0)
    near, far = torch.full((100,), 2.0), torch.full((100,), 6.0)
    t = stratified_t(near, far, 64, generator=g)
    assert t.shape == (100, 65)
    assert (t[:, 1:] >= t[:, :-1]).all()
    assert (t[:, 0] == 2).all() and (t[:, -1] == 6).all()


def test_sample_pdf_follows_the_histogram():
    t = uniform_t(torch.tensor([0.0]), torch.tensor([4.0]), 4)  # intervals [0,1] [1,2] [2,3] [3,4]
    w = torch.tensor([[0.0, 0.75, 0.25, 0.0]])
    s = sample_pdf(t, w, 20000, generator=torch.Generator().manual_seed(0), eps=0.0)
    assert (s[:, 1:] >= s[:, :-1]).all()
    frac_12 = ((s >= 1) & (s < 2)).float().mean()
    frac_23 = ((s >= 2) & (s <= 3)).float().mean()
    assert abs(frac_12 - 0.75) < 0.02 and abs(frac_23 - 0.25) < 0.02
    det = sample_pdf(t, w, 5, deterministic=True, eps=0.0)
    assert (det >= 1).all() and (det <= 3).all()


def test_interlevel_loss_zero_when_proposal_bounds_final_and_distortion_prefers_compact():
    from nerfbake.render.stepfun import distortion_loss, inner_outer, interlevel_loss

    t = torch.linspace(0, 1, 9)[None]
    w = torch.tensor([[0.0, 0.1, 0.4, 0.3, 0.1, 0.0, 0.0, 0.0]])
    assert float(interlevel_loss(t, w, t, w)) == 0.0
    coarse_t = torch.linspace(0, 1, 3)[None]
    _, outer = inner_outer(t, coarse_t, torch.tensor([[0.8, 0.1]]))
    assert torch.allclose(outer[0, :4], torch.full((4,), 0.8)) and torch.allclose(outer[0, 4:], torch.full((4,), 0.1))
    assert float(interlevel_loss(t, w, coarse_t, torch.tensor([[0.1, 0.1]]))) > 0
    spread = torch.full((1, 8), 0.125)
    compact = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0]])
    assert float(distortion_loss(t, compact)) < float(distortion_loss(t, spread))


def test_proposal_spacing_is_linear_near_and_disparity_far():
    from nerfbake.teacher.proposal import s_to_t

    near = torch.tensor([0.01, 0.5])
    s = torch.linspace(0, 1, 101).expand(2, -1)
    t = s_to_t(s, near, 1000.0)
    torch.testing.assert_close(t[:, 0], near)
    torch.testing.assert_close(t[:, -1], torch.full((2,), 1000.0), rtol=1e-3, atol=0)  # float32 near g = 1
    assert (t[:, 1:] > t[:, :-1]).all()
    # From a small near plane about half the samples lie before t = 1, in even steps (not crowded at the camera).
    inside = t[0] < 1
    assert 0.45 < inside.float().mean() < 0.55
    steps = t[0, 1:][inside[1:]] - t[0, :-1][inside[1:]]
    torch.testing.assert_close(steps, torch.full_like(steps, float(steps.mean())), rtol=1e-3, atol=1e-5)


def test_sample_pdf_stratified_draw():
    """Stratified draws put edge i of n at a cdf quantile in [i/n, (i+1)/n); evaluation draws are deterministic.
    The proposal sampler draws its final samples this way (``ProposalConfig.stratified``)."""
    s = uniform_t(torch.zeros(2000), torch.ones(2000), 4)
    w = torch.tensor([0.0, 1.0, 0.0, 0.0]).expand(2000, 4)
    noise = torch.rand(2000, 9, generator=torch.Generator().manual_seed(0))
    edges = sample_pdf(s, w, 9, u=noise, stratified=True)
    assert edges.shape == (2000, 9) and (edges.diff(dim=-1) >= 0).all()
    assert ((edges >= 0.25) & (edges <= 0.5)).float().mean() > 0.99  # all the mass is in the second interval
    quantile = (edges - 0.25) / 0.25  # the cdf at each edge
    k = torch.arange(9)
    assert ((quantile >= k / 9 - 1e-3) & (quantile <= (k + 1) / 9 + 1e-3)).all()
    iid_gaps = ((sample_pdf(s, w, 9, u=noise) - 0.25) / 0.25).diff(dim=-1)
    assert float(quantile.diff(dim=-1).max()) < 2 / 9 + 1e-3 < float(iid_gaps.max())  # sorted uniforms: wide gaps
    assert torch.equal(sample_pdf(s, w, 9, deterministic=True, stratified=True), sample_pdf(s, w, 9, deterministic=True))
