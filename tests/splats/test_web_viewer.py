"""Our exported splats in a published web viewer: gsplat.js (npm) parses the .ply and the .splat and draws them in
headless chromium from a test camera; its picture must match our rasteriser's of what the file holds under the web
viewers' rules (and differ from the reference rules' picture, which is why the export fits under the former)."""
import numpy as np
import pytest

from nerfbake.data.formats import load_dataset
from nerfbake.eval.metrics import psnr
from nerfbake.octree.io import load_tree
from nerfbake.splats.from_tree import gaussians_from_tree
from nerfbake.kernels.splat_raster import REFERENCE, WEB
from nerfbake.splats.io import read_ply, read_splat, web_quantized, write_splats
from nerfbake.splats.rasterize import render_gaussians
from nerfbake.splats.web_viewer import render_with_gsplat
from nerfbake.viewer.server import GSPLAT_DIST

pytestmark = pytest.mark.skipif(not (GSPLAT_DIST / "index.es.js").is_file(),
                                reason=f"gsplat.js not installed at {GSPLAT_DIST} (make setup installs it with npm)")


@pytest.mark.parametrize("fmt,read", [("splat", read_splat), ("ply", read_ply)])
def test_gsplat_draws_our_file_as_our_rasteriser_does(tiny_tree, tiny_scene, tmp_path, fmt, read):
    ds = load_dataset(tiny_scene)
    camera = ds.frames[ds.split("test")[0]].camera.scaled(0.25)  # 128 x 128
    path = write_splats(gaussians_from_tree(load_tree(tiny_tree), sh_degree=0), tmp_path / f"scene.{fmt}", fmt)
    theirs = render_with_gsplat(path, camera, (1.0, 1.0, 1.0))
    held = web_quantized(read(path))
    ours = {name: np.clip(render_gaussians(held, camera, (1.0, 1.0, 1.0), rules).numpy(), 0, 1)
            for name, rules in (("web", WEB), ("reference", REFERENCE))}
    assert theirs.shape == ours["web"].shape == (camera.height, camera.width, 3)
    assert (np.abs(theirs - 1.0).max(-1) > 0.1).mean() > 0.05  # it drew the scene, not only the background
    score = {name: float(psnr(theirs, img)) for name, img in ours.items()}
    # The tiny teacher's tree is a translucent fog, where gsplat.js's 8-bit blending leaves per-pixel rounding noise
    # (36 dB here; lego's opaque surfaces agree to 50 dB, benchmarks/splat_export.py); the reference rules'
    # picture is 32.7 dB away, its low-pass blurring every splat.
    assert score["web"] > 34.5, f"gsplat.js vs our rasteriser under the web rules: {score}"
    assert score["web"] > score["reference"] + 2.5, score
