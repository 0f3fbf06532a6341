"""Our splat files in a published web viewer: gsplat.js (npm ``gsplat``, installed by ``make setup`` into
``.venv/npm``) opens a ``.splat`` or ``.ply`` in headless chromium and draws it from one of our cameras, so a test
can compare its picture with the reference rasteriser's (an independent reader and renderer of the same file).

gsplat.js's camera is OpenCV-style (x right, y down, z forward; the view matrix is [R^T | -R^T p] for the camera's
rotation R and position p) with the principal point at the image centre; ours are OpenGL (y up, -z forward), so
R = R_gl diag(1, -1, -1). It composites front to back into a transparent canvas (premultiplied colour); the
picture is read back with readPixels and laid over the background here.
"""
from __future__ import annotations

import contextlib
import functools
import http.server
import shutil
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

from nerfbake.data.cameras import Camera
from nerfbake.errors import NerfbakeError
from nerfbake.render.rotations import matrix_quaternion
from nerfbake.viewer.browser import CHROMIUM_FLAGS, SOFTWARE_GL_FLAGS, chromium_path

GSPLAT_DIST = Path(sys.prefix) / "npm" / "node_modules" / "gsplat" / "dist"

PAGE = """<!doctype html><html><body style="margin:0"><canvas id="c" width="{w}" height="{h}"></canvas>
<script type="module">
import * as SPLAT from "./gsplat/index.es.js";
const canvas = document.getElementById("c");
const renderer = new SPLAT.WebGLRenderer(canvas);
renderer.setSize({w}, {h});
const scene = new SPLAT.Scene();
const camera = new SPLAT.Camera();
window.draw = async (file, cam) => {{
  const buffer = await (await fetch(file)).arrayBuffer();
  if (file.endsWith(".ply")) SPLAT.PLYLoader.LoadFromArrayBuffer(buffer, scene);
  else SPLAT.Loader.LoadFromArrayBuffer(buffer, scene);
  camera.data.fx = cam.fx; camera.data.fy = cam.fy; camera.data.setSize({w}, {h});
  camera.position = new SPLAT.Vector3(...cam.position);
  camera.rotation = new SPLAT.Quaternion(...cam.rotation);
  const gl = renderer.gl, pixels = new Uint8Array({w} * {h} * 4);
  let last = null;
  for (let i = 0; i < 200; i++) {{  // the depth sort runs in a worker: draw until the picture stops changing
    renderer.render(scene, camera);
    gl.readPixels(0, 0, {w}, {h}, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
    const now = Array.from(pixels).join(",");
    if (i > 3 && now === last && pixels.some((v) => v > 0)) break;
    last = now;
    await new Promise((r) => setTimeout(r, 100));
  }}
  return Array.from(pixels);
}};
window.ready = true;
</script></body></html>"""


class SplatViewerMissing(NerfbakeError):
    """gsplat.js is not installed (no npm when ``make setup`` ran)."""


def gsplat_camera(camera: Camera) -> dict:
    """Our OpenGL camera as gsplat.js's position and (x, y, z, w) rotation quaternion, and its focal lengths."""
    if abs(camera.cx - camera.width / 2) > 0.5 or abs(camera.cy - camera.height / 2) > 0.5:
        raise ValueError("gsplat.js puts the principal point at the image centre; this camera's is elsewhere")
    w, x, y, z = matrix_quaternion(camera.c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0]))
    return {"position": camera.c2w[:3, 3].tolist(), "rotation": [x, y, z, w],
            "fx": float(camera.fx), "fy": float(camera.fy)}


def render_with_gsplat(splat_file: str | Path, camera: Camera, background=(1.0, 1.0, 1.0),
                       software_gl: bool = True) -> np.ndarray:
    """(H, W, 3) float image of ``splat_file`` drawn by gsplat.js in headless chromium from ``camera``."""
    if not (GSPLAT_DIST / "index.es.js").is_file():
        raise SplatViewerMissing(f"{GSPLAT_DIST}: gsplat.js is not installed; run make setup with npm available "
                                 "(npm install --prefix .venv/npm gsplat@1.2.9)")
    from playwright.sync_api import sync_playwright

    w, h = camera.width, camera.height
    with contextlib.ExitStack() as stack:
        root = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="nerfbake-gsplat-")))
        (root / "index.html").write_text(PAGE.format(w=w, h=h))
        (root / "gsplat").symlink_to(GSPLAT_DIST, target_is_directory=True)
        name = "scene" + Path(splat_file).suffix
        shutil.copyfile(splat_file, root / name)
        handler = functools.partial(QuietHandler, directory=str(root))
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        stack.callback(server.shutdown)
        pw = stack.enter_context(sync_playwright())
        profile = stack.enter_context(tempfile.TemporaryDirectory(prefix="nerfbake-chromium-"))
        flags = CHROMIUM_FLAGS + (SOFTWARE_GL_FLAGS if software_gl else ["--enable-gpu", "--use-angle=default"])
        context = pw.chromium.launch_persistent_context(profile, executable_path=chromium_path(), headless=True,
                                                        args=flags, viewport={"width": w, "height": h})
        stack.callback(context.close)
        page = context.pages[0] if context.pages else context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
        page.wait_for_function("() => window.ready === true", timeout=60_000)
        pixels = page.evaluate("([f, c]) => window.draw(f, c)", [name, gsplat_camera(camera)])
        if errors:
            raise RuntimeError(f"gsplat.js failed on {splat_file}: {errors[0]}")
    rgba = np.asarray(pixels, np.float64).reshape(h, w, 4)[::-1] / 255.0  # readPixels rows run bottom-up
    return rgba[..., :3] + (1.0 - rgba[..., 3:]) * np.asarray(background)


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    """Static files with the MIME types module scripts and WebAssembly need; no request log."""
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".js": "text/javascript",
                      ".wasm": "application/wasm"}

    def log_message(self, *args) -> None:
        pass
