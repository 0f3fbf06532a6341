"""The splat rasterisers (Warp kernels and the torch reference) against closed forms: one Gaussian's footprint, two
Gaussians' compositing order; the reference's gradients against finite differences, the kernels' against the
reference's and against finite differences of their own."""
import math

import numpy as np
import torch

from nerfbake.data.cameras import Camera
import pytest

from nerfbake.kernels.splat_raster import REFERENCE, WEB
from nerfbake.splats.rasterize import rasterize, rasterize_reference

LOW_PASS = REFERENCE.low_pass

BOTH = pytest.mark.parametrize("raster", [rasterize, rasterize_reference], ids=["warp", "reference"])


def camera(width=32, height=24, f=30.0):
    """At (0, 0, 5) looking down -Z at the origin (OpenGL axes)."""
    c2w = np.eye(4)
    c2w[2, 3] = 5.0
    return Camera(c2w, width, height, f, f, width / 2, height / 2)


def one(means, scales, opacity, rgb):
    n = len(means)
    sh = torch.zeros(n, 3, 1, dtype=torch.float64)
    sh[:, :, 0] = (torch.as_tensor(rgb, dtype=torch.float64) - 0.5) / 0.28209479177387814
    q = torch.zeros(n, 4, dtype=torch.float64)
    q[:, 0] = 1
    o = torch.as_tensor(opacity, dtype=torch.float64)
    return (torch.as_tensor(means, dtype=torch.float64), torch.log(torch.as_tensor(scales, dtype=torch.float64)), q,
            torch.log(o / (1 - o)), sh)


@BOTH
def test_one_gaussian_draws_its_projected_footprint(raster):
    cam = camera()
    sigma, opacity = 0.05, 0.8
    img = raster(*one([[0.0, 0.0, 0.0]], [[sigma] * 3], [opacity], [[1.0, 0.0, 0.0]]), cam, (0.0, 0.0, 1.0))
    var_px = (cam.fx * sigma / 5.0) ** 2 + LOW_PASS
    ys, xs = np.mgrid[0:24, 0:32] + 0.5
    r2 = (xs - 16) ** 2 + (ys - 12) ** 2
    alpha = opacity * np.exp(-0.5 * r2 / var_px)
    alpha = np.where(alpha >= 1 / 255, alpha, 0.0)
    want = np.stack([alpha, np.zeros_like(alpha), 1 - alpha], -1)
    np.testing.assert_allclose(img.numpy(), want, atol=1e-6)


@BOTH
def test_web_rules_cut_the_footprint_at_sqrt8_sigma_and_clamp_colour(raster):
    """Under the web viewers' rules the low-pass is a quarter of the reference's, a splat ends where 0.5 d^T Sigma^-1 d = 4 (2.83 sigma), however faint it is there,
    nothing is skipped for being faint inside, and a colour over 1 is drawn as 1."""
    cam = camera()
    sigma, opacity = 0.5, 0.15
    img = raster(*one([[0.0, 0.0, 0.0]], [[sigma] * 3], [opacity], [[1.4, 0.0, 0.0]]), cam, (0.0, 0.0, 1.0),
                 rules=WEB)
    var_px = (cam.fx * sigma / 5.0) ** 2 + WEB.low_pass
    ys, xs = np.mgrid[0:24, 0:32] + 0.5
    r2 = (xs - 16) ** 2 + (ys - 12) ** 2
    alpha = np.where(0.5 * r2 / var_px <= 4.0, opacity * np.exp(-0.5 * r2 / var_px), 0.0)
    assert ((alpha > 0) & (alpha < 1 / 255)).any() and (alpha == 0).any()  # both rules differ from the reference here
    want = np.stack([alpha, np.zeros_like(alpha), 1 - alpha], -1)
    np.testing.assert_allclose(img.numpy(), want, atol=1e-6)


@BOTH
def test_nearer_gaussians_are_composited_first_and_offscreen_ones_skipped(raster):
    cam = camera()
    args = one([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 9.0], [50.0, 0.0, 0.0]], [[0.3] * 3] * 4,
               [0.6, 0.9, 0.9, 0.9], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    centre = raster(*args, cam, (0.0, 0.0, 0.0))[12, 16].numpy()
    d1, d2 = 4.5, 5.5  # pixel (16, 12) is 0.5 px off the axis in x and y; the red one is nearer; the one behind the camera and the one off screen add nothing
    a1 = 0.6 * math.exp(-0.5 * 0.5 / ((cam.fx * 0.3 / d1) ** 2 + LOW_PASS))
    a2 = 0.9 * math.exp(-0.5 * 0.5 / ((cam.fx * 0.3 / d2) ** 2 + LOW_PASS))
    np.testing.assert_allclose(centre, [a1, (1 - a1) * a2, 0.0], atol=1e-6)


def test_gradients_match_finite_differences():
    cam = camera(12, 10, 20.0)
    gen = torch.Generator().manual_seed(0)
    means = (torch.randn(5, 3, generator=gen, dtype=torch.float64) * 0.3)
    log_scales = torch.log(torch.rand(5, 3, generator=gen, dtype=torch.float64) * 0.2 + 0.1)
    quats = torch.randn(5, 4, generator=gen, dtype=torch.float64)
    logits = torch.randn(5, generator=gen, dtype=torch.float64)
    sh = torch.randn(5, 3, 4, generator=gen, dtype=torch.float64) * 0.3
    params = [p.requires_grad_() for p in (means, log_scales, quats, logits, sh)]
    weights = torch.rand(10, 12, 3, generator=gen, dtype=torch.float64)

    def loss(*p):
        return (rasterize_reference(*p, cam, (0.2, 0.3, 0.4)) * weights).sum()

    assert torch.autograd.gradcheck(loss, params, eps=1e-6, atol=1e-5, rtol=1e-3)


def random_scene(n, seed=0):
    """n Gaussians in front of camera(): a mix of faint and nearly opaque ones (so that the 0.99 clamp, the 1/255 cut
    and the stop at transmittance 1e-4 all occur), colours from degree-1 SH."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen) * 0.6
    log_scales = torch.log(torch.rand(n, 3, generator=gen) * 0.15 + 0.03)
    quats = torch.randn(n, 4, generator=gen)
    logits = torch.randn(n, generator=gen) * 3 + 1
    sh = torch.randn(n, 3, 4, generator=gen) * 0.3
    return [means, log_scales, quats, logits, sh]


@pytest.mark.parametrize("rules", [REFERENCE, WEB], ids=["reference-rules", "web-rules"])
def test_warp_kernels_match_the_reference_in_picture_and_gradients(rules):
    cam = camera(70, 50, 60.0)
    scene = random_scene(400)
    weights = torch.rand(50, 70, 3, generator=torch.Generator().manual_seed(1))
    grads, images = [], []
    for raster in (rasterize, rasterize_reference):
        params = [p.clone().requires_grad_() for p in scene]
        img = raster(*params, cam, (0.2, 0.3, 0.4), rules)
        (img * weights).sum().backward()
        images.append(img.detach())
        grads.append([p.grad for p in params])
    assert float(images[1].std()) > 0.1  # the picture shows the Gaussians
    np.testing.assert_allclose(images[0].numpy(), images[1].numpy(), atol=2e-6)
    for name, a, b in zip(("means", "log_scales", "quats", "opacity_logits", "sh"), *grads):
        assert float(b.abs().max()) > 0.1, name
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=2e-4 * float(b.abs().max()), err_msg=name)


def test_warp_compositing_gradients_match_finite_differences():
    """The kernels' own backward (screen-space inputs) against central differences of their forward. The splats are
    wide and the image small, so that no pixel crosses the 1/255 cut, the 0.99 clamp or the transmittance stop within
    a difference (each is a step in the picture, where a difference means nothing)."""
    from nerfbake.kernels.splat_raster import composite

    gen = torch.Generator().manual_seed(3)
    n, w, h = 5, 20, 18
    xy = torch.rand(n, 2, generator=gen) * torch.tensor([w, h])
    var = torch.rand(n, 2, generator=gen) * 60 + 60  # px^2
    corr = (torch.rand(n, generator=gen) - 0.5) * 0.8
    cov = torch.stack([var[:, 0], corr * var.prod(1).sqrt(), corr * var.prod(1).sqrt(), var[:, 1]], -1).reshape(n, 2, 2)
    inv = torch.linalg.inv(cov)
    conic = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    inputs = [xy, conic, torch.rand(n, generator=gen) * 0.5 + 0.3, torch.rand(n, 3, generator=gen)]
    radius = torch.full((n,), 100.0)
    weights = torch.rand(h, w, 3, generator=gen, dtype=torch.float64)

    def loss(*x):
        return (composite(*x, radius, w, h, (0.2, 0.3, 0.4)).double() * weights).sum()  # summed in float64

    params = [x.clone().requires_grad_() for x in inputs]
    loss(*params).backward()
    for which, eps in ((0, 1e-2), (1, 5e-4), (2, 1e-3), (3, 1e-3)):
        grad = params[which].grad.reshape(-1)
        assert float(grad.abs().max()) > 1e-2, which
        for i in range(grad.numel()):
            def at(delta):
                x = [t.clone() for t in inputs]
                x[which].view(-1)[i] += delta
                return float(loss(*x))
            fd = (at(eps) - at(-eps)) / (2 * eps)
            assert abs(fd - float(grad[i])) <= 1e-2 * abs(fd) + 5e-3, (which, i, fd, float(grad[i]))
