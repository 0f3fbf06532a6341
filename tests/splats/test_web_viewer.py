"""Our exported splats in a published web viewer: gsplat.js (npm) parses the .ply and the .splat and draws them in
headless chromium from a test camera; its picture must match our reference rasteriser's of what the file holds."""
import numpy as np
import pytest

from nerfbake.data.formats import load_dataset
from nerfbake.eval.metrics import psnr
from nerfbake.octree.io import load_tree
from nerfbake.splats.from_tree import gaussians_from_tree
from nerfbake.splats.io import read_ply, read_splat, write_splats
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
    ours = np.clip(render_gaussians(read(path), camera, (1.0, 1.0, 1.0)).numpy(), 0, 1)
    assert theirs.shape == ours.shape == (camera.height, camera.width, 3)
    assert (np.abs(theirs - 1.0).max(-1) > 0.1).mean() > 0.05  # it drew the scene, not only the background
    score = float(psnr(theirs, ours))
    assert score > 28.0, f"gsplat.js vs the reference rasteriser: {score:.2f} dB"
