import numpy as np
import torch

from nerfbake.data.cameras import Camera, distort, undistort
from nerfbake.data.rays import camera_rays, ndc_rays, random_pixels

FOX_DIST = {"k1": 0.0578421, "k2": -0.0805099, "p1": -0.000980296, "p2": 0.00015575}


def test_undistort_inverts_distort():
    g = torch.Generator().manual_seed(0)
    x, y = (torch.rand(2, 5000, generator=g, dtype=torch.float64) - 0.5) * 1.2
    for dist in (FOX_DIST, {"k1": -0.2, "k2": 0.05, "k3": 0.01, "p1": 0.001, "p2": -0.002}):
        xd, yd = distort(x, y, dist)
        xu, yu = undistort(xd, yd, dist)
        torch.testing.assert_close(xu, x, atol=1e-9, rtol=0)
        torch.testing.assert_close(yu, y, atol=1e-9, rtol=0)


def test_rays_pass_through_their_pixel_centres():
    c2w = np.eye(4)
    c2w[:3, 3] = [0.3, -0.2, 2.0]
    cam = Camera(c2w, 64, 48, 50.0, 52.0, 31.0, 25.0, "OPENCV", dict(FOX_DIST))
    rays = camera_rays(cam)
    assert rays["directions"].shape == (48, 64, 3)
    torch.testing.assert_close(rays["directions"].norm(dim=-1), torch.ones(48, 64))
    pts = (rays["origins"] + 3.0 * rays["directions"]).reshape(-1, 3).double().numpy()
    uv, depth = cam.project(pts)
    rows, cols = np.mgrid[0:48, 0:64]
    np.testing.assert_allclose(uv[:, 0], cols.ravel() + 0.5, atol=1e-3)
    np.testing.assert_allclose(uv[:, 1], rows.ravel() + 0.5, atol=1e-3)
    assert (depth > 0).all()
    # OpenGL convention: the centre pixel looks down -Z, the top row looks up (+Y).
    assert rays["directions"][24, 32, 2] < -0.99 and rays["directions"][0, 32, 1] > 0


def test_random_patches_lie_inside_their_images():
    g = torch.Generator().manual_seed(0)
    sizes = np.array([[10, 8], [5, 4]])
    cam, pix = random_pixels(900, sizes, np.array([3, 7]), g, patch=3)
    assert cam.shape == (100, 3, 3) and pix.shape == (100, 3, 3, 2)
    w = torch.where(cam == 3, 10, 5)
    h = torch.where(cam == 3, 8, 4)
    assert (pix[..., 0] < w).all() and (pix[..., 1] < h).all() and (pix >= 0).all()
    # Each patch is a contiguous 3x3 block.
    assert (pix[:, :, 1:, 0] - pix[:, :, :-1, 0] == 1).all() and (pix[:, 1:, :, 1] - pix[:, :-1, :, 1] == 1).all()


def test_ndc_maps_the_near_plane_to_minus_one():
    o = torch.zeros(4, 3)
    d = torch.tensor([[0.0, 0, -1], [0.1, 0.05, -1], [-0.2, 0.1, -1], [0.0, -0.3, -1]])
    o_ndc, d_ndc = ndc_rays(o, d, 100.0, 100.0, 200, 150, near=1.0)
    torch.testing.assert_close(o_ndc[:, 2], torch.full((4,), -1.0))
    # Points at infinity land at z = +1.
    torch.testing.assert_close((o_ndc + d_ndc)[:, 2], torch.ones(4))
