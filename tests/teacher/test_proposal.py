"""Proposal sampling with one level (the preset) and with a second, finer level (``refine_samples``)."""
from __future__ import annotations

import torch

from nerfbake.render import sample_pdf
from nerfbake.teacher.proposal import ProposalConfig, ProposalSampler

R = 32


def _rays(seed=0):
    g = torch.Generator().manual_seed(seed)
    origins = 0.3 * torch.randn(R, 3, generator=g)
    dirs = torch.nn.functional.normalize(torch.randn(R, 3, generator=g), dim=-1)
    return origins, dirs, torch.full((R,), 0.05)


def _sampler(**kw):
    torch.manual_seed(0)
    cfg = ProposalConfig(proposal_samples=16, final_samples=8, levels=3, log2_table=10, max_res=64, **kw)
    return ProposalSampler(cfg, torch.zeros(3), torch.ones(3))


def test_one_level_draws_the_final_samples_from_its_weights():
    sampler = _sampler()
    assert sampler.noise_dims == 17 + 9 and sampler.proposal_samples == 16 and not hasattr(sampler, "refine")
    o, d, near = _rays()
    noise = torch.rand(R, sampler.noise_dims, generator=torch.Generator().manual_seed(1))
    s_f, t_f, levels = sampler.sample(o, d, near, noise)
    [(s_p, w_p)] = levels
    expected = sample_pdf(s_p, w_p.detach(), 9, u=noise[:, 17:], stratified=True)
    torch.testing.assert_close(s_f, torch.sort(expected, dim=-1)[0])
    assert t_f.shape == (R, 9) and (t_f[:, 1:] >= t_f[:, :-1]).all() and (t_f[:, 0] >= near - 1e-6).all()


def test_a_second_level_refines_the_first_and_both_learn_from_the_final_weights():
    sampler = _sampler(refine_samples=12, refine_max_res=128)
    assert sampler.noise_dims == 17 + 13 + 9 and sampler.proposal_samples == 28
    assert sampler.refine.grid.max_res == 128 and sampler.density.grid.max_res == 64
    o, d, near = _rays()
    noise = torch.rand(R, sampler.noise_dims, generator=torch.Generator().manual_seed(1))
    s_f, _, levels = sampler.sample(o, d, near, noise)
    (s_p, w_p), (s_r, w_r) = levels
    assert s_p.shape == (R, 17) and s_r.shape == (R, 13) and s_f.shape == (R, 9)
    # The refined edges come from the first level's weights, the final ones from the refined level's.
    torch.testing.assert_close(s_r, torch.sort(sample_pdf(s_p, w_p.detach(), 13, u=noise[:, 17:30], stratified=True), -1)[0])
    torch.testing.assert_close(s_f, torch.sort(sample_pdf(s_r, w_r.detach(), 9, u=noise[:, 30:], stratified=True), -1)[0])
    # Final weights that neither level bounds: the interlevel loss reaches both density fields.
    w_final = torch.zeros(R, 8)
    w_final[:, 4] = 0.9
    losses = sampler.losses(s_f, w_final, levels)
    assert float(losses["interlevel"].detach()) > 0
    losses["interlevel"].backward()
    for net in (sampler.density, sampler.refine):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    # Evaluation placement: no noise, the same edges every time.
    with torch.no_grad():
        a, b = sampler.sample(o, d, near, None)[0], sampler.sample(o, d, near, None)[0]
    torch.testing.assert_close(a, b)
