"""The torch splat rasteriser against closed forms: one Gaussian's footprint, two Gaussians' compositing order,
and gradients against finite differences."""
import math

import numpy as np
import torch

from nerfbake.data.cameras import Camera
from nerfbake.splats.rasterize import LOW_PASS, rasterize


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


def test_one_gaussian_draws_its_projected_footprint():
    cam = camera()
    sigma, opacity = 0.05, 0.8
    img = rasterize(*one([[0.0, 0.0, 0.0]], [[sigma] * 3], [opacity], [[1.0, 0.0, 0.0]]), cam, (0.0, 0.0, 1.0))
    var_px = (cam.fx * sigma / 5.0) ** 2 + LOW_PASS
    ys, xs = np.mgrid[0:24, 0:32] + 0.5
    r2 = (xs - 16) ** 2 + (ys - 12) ** 2
    alpha = opacity * np.exp(-0.5 * r2 / var_px)
    alpha = np.where(alpha >= 1 / 255, alpha, 0.0)
    want = np.stack([alpha, np.zeros_like(alpha), 1 - alpha], -1)
    np.testing.assert_allclose(img.numpy(), want, atol=1e-9)


def test_nearer_gaussians_are_composited_first_and_offscreen_ones_skipped():
    cam = camera()
    args = one([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 9.0], [50.0, 0.0, 0.0]], [[0.3] * 3] * 4,
               [0.6, 0.9, 0.9, 0.9], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    centre = rasterize(*args, cam, (0.0, 0.0, 0.0))[12, 16].numpy()
    d1, d2 = 4.5, 5.5  # pixel (16, 12) is 0.5 px off the axis in x and y; the red one is nearer; the one behind the camera and the one off screen add nothing
    a1 = 0.6 * math.exp(-0.5 * 0.5 / ((cam.fx * 0.3 / d1) ** 2 + LOW_PASS))
    a2 = 0.9 * math.exp(-0.5 * 0.5 / ((cam.fx * 0.3 / d2) ** 2 + LOW_PASS))
    np.testing.assert_allclose(centre, [a1, (1 - a1) * a2, 0.0], atol=1e-9)


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
        return (rasterize(*p, cam, (0.2, 0.3, 0.4)) * weights).sum()

    assert torch.autograd.gradcheck(loss, params, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_fitting_raises_the_psnr_of_the_views_it_fits(tiny_tree, tiny_scene):
    """Leaf splats of a tree, fitted to two training photos through the rasteriser's autograd: both get closer."""
    from nerfbake.data.formats import load_dataset
    from nerfbake.eval.metrics import psnr
    from nerfbake.octree.io import load_tree
    from nerfbake.splats.fit import FitConfig, fit_gaussians
    from nerfbake.splats.from_tree import gaussians_from_tree
    from nerfbake.splats.rasterize import render_gaussians

    ds = load_dataset(tiny_scene)
    views = [(ds.frames[i].camera, ds.image(i)[..., :3]) for i in ds.split("train")[:2]]
    g = gaussians_from_tree(load_tree(tiny_tree), sh_degree=1, max_splats=3000)

    def score(gs):
        return [float(psnr(np.clip(render_gaussians(gs, cam).numpy(), 0, 1), img)) for cam, img in views]

    before = score(g)
    fitted, history = fit_gaussians(g, views, FitConfig(steps=40, crop=32))
    after = score(fitted)
    assert len(history) == 40 and all(a > b + 0.5 for a, b in zip(after, before)), (before, after)
