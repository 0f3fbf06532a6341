"""Training on real photographs: per-image appearance corrections fit exposure and white-balance changes
between photos and average to the identity (what every later stage and the held-out scores see); light that
passes through an opaque photo's rays costs loss."""
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
    assert float(loss.detach()) < 1e-5
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


class _Transparent(torch.nn.Module):
    """A teacher whose every ray lets all light through: it renders whatever background it is given."""

    noise_dims = 1

    def render_rays(self, origins, dirs, background=None, noise=None):
        rgb = background if background is not None else torch.zeros_like(origins)
        return {"rgb": rgb, "acc": torch.zeros(origins.shape[0]), "num_samples": 0}

    def extra_losses(self, out, generator):
        return {}


def test_light_through_an_opaque_photo_is_wrong_on_a_random_background():
    """Opaque photos: the prediction alone goes on each ray's random colour, so a transparent field cannot match a
    photo (on black it could have darkened every pixel by letting light through, and rendered hazy elsewhere)."""
    from nerfbake.teacher.presets import preset
    from nerfbake.teacher.train import loss_terms

    cfg = preset("hash", "cpu-small")
    assert cfg.random_background
    gen = torch.Generator().manual_seed(0)
    n = 4096
    target = torch.zeros(n, 3)  # a black photo: on a black background a transparent field would match it exactly
    batch = {"origins": torch.zeros(n, 3), "directions": torch.ones(n, 3), "target": target,
             "background": torch.rand(n, 3, generator=gen), "noise": torch.rand(n, 1, generator=gen),
             "cam_idx": torch.zeros(n, dtype=torch.long)}
    loss, terms, _, _ = loss_terms(_Transparent(), batch, n, gen)
    torch.testing.assert_close(loss, batch["background"].square().mean())  # E[u^2] = 1/3 for uniform colours
    assert float(loss) > 0.3
