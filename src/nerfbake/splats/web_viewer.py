"""Our splat files in a published web viewer: gsplat.js (npm ``gsplat``, installed by ``make setup`` into
``.venv/npm``), as ``nerfbake view scene.ply`` serves it (``viewer/static/splats.js``), draws a ``.splat`` or ``.ply``
in headless chromium from one of our cameras, so a test or benchmark can compare its picture with our rasteriser's
(an independent reader and renderer of the same file).

gsplat.js's camera is OpenCV-style (x right, y down, z forward; the view matrix is [R^T | -R^T p] for the camera's
rotation R and position p) with the principal point at the image centre; ours are OpenGL (y up, -z forward), so
R = R_gl diag(1, -1, -1). It composites front to back into a transparent canvas (premultiplied colour); the
picture is read back with readPixels and laid over the background here.
"""
from __future__ import annotations

import numpy as np

from nerfbake.data.cameras import Camera
from nerfbake.render.rotations import matrix_quaternion
from nerfbake.viewer.browser import ViewerPage


def gsplat_camera(camera: Camera) -> dict:
    """Our OpenGL camera as gsplat.js's position and (x, y, z, w) rotation quaternion, and its focal lengths."""
    if abs(camera.cx - camera.width / 2) > 0.5 or abs(camera.cy - camera.height / 2) > 0.5:
        raise ValueError("gsplat.js puts the principal point at the image centre; this camera's is elsewhere")
    w, x, y, z = matrix_quaternion(camera.c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0]))
    return {"position": camera.c2w[:3, 3].tolist(), "rotation": [x, y, z, w],
            "fx": float(camera.fx), "fy": float(camera.fy)}


def render_with_gsplat(splat_file, camera: Camera, background=(1.0, 1.0, 1.0), software_gl: bool = True) -> np.ndarray:
    """(H, W, 3) float image of ``splat_file`` drawn by gsplat.js in headless chromium from ``camera``."""
    return render_cameras_with_gsplat(splat_file, [camera], background, software_gl)[0]


def render_cameras_with_gsplat(splat_file, cameras: list[Camera], background=(1.0, 1.0, 1.0),
                               software_gl: bool = True) -> list[np.ndarray]:
    """:func:`render_with_gsplat` for several cameras of one size, in one page load (without gsplat.js installed,
    opening the page raises the viewer's SceneError saying how to install it)."""
    w, h = cameras[0].width, cameras[0].height
    if any((c.width, c.height) != (w, h) for c in cameras):
        raise ValueError("render_cameras_with_gsplat draws cameras of one size")
    images = []
    with ViewerPage(splat_file, size=(w, h), software_gl=software_gl) as page:
        for camera in cameras:
            pixels = page.evaluate("([c, w, h]) => window.nerfbake.renderCamera(c, w, h)", [gsplat_camera(camera), w, h])
            rgba = np.asarray(pixels, np.float64).reshape(h, w, 4)[::-1] / 255.0  # readPixels rows run bottom-up
            images.append(rgba[..., :3] + (1.0 - rgba[..., 3:]) * np.asarray(background))
        if page.errors:
            raise RuntimeError(f"gsplat.js failed on {splat_file}: {page.errors[0]}")
    return images
