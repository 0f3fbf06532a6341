"""Per-image appearance corrections: they fit exposure and white-balance changes between photos, and their
mean is the identity (what every later stage and the held-out scores see)."""
import pytest
import torch

from nerfbake.teacher.appearance import ImageAppearance, resolve_appearance


def test_corrections_fit_per_image_colour_changes_and_average_to_the_identity():
    gen = torch.Generator().manual_seed(0)
    images = 5
    # Each photo's true colour change: an exposure gain and a white-balance shift, centred over the photos.
    gains = torch.tensor([0.7, 0.85, 1.0, 1.15, 1.3])
    shifts = torch.randn(images, 3, generator=gen) * 0.05
    shifts -= shifts.mean(0)
    rgb = torch.rand(4096, 3, generator=gen)
    image = torch.randint(0, images, (4096,), generator=gen)
    target = rgb * gains[image, None] + shifts[image]
    model = ImageAppearance(images)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(600):
        loss = (model(rgb, image) - target).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss) < 1e-5
    p = model.centred().detach()
    diag = p[:, :9].view(images, 3, 3).diagonal(dim1=1, dim2=2)
    torch.testing.assert_close(diag, (gains - 1)[:, None].expand(images, 3), atol=2e-3, rtol=0)
    torch.testing.assert_close(p[:, 9:], shifts, atol=2e-3, rtol=0)
    # The mean correction is the identity: the centred parameters sum to zero over the photos.
    torch.testing.assert_close(p.mean(0), torch.zeros(12), atol=1e-6, rtol=0)


def test_auto_turns_corrections_on_for_photographs_only():
    assert resolve_appearance("auto", has_alpha=False) == "affine"
    assert resolve_appearance("auto", has_alpha=True) == "none"
    assert resolve_appearance("none", has_alpha=False) == "none"
    with pytest.raises(ValueError, match="choose one of"):
        resolve_appearance("nerf-w", has_alpha=False)
