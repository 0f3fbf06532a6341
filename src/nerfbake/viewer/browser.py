"""Driving the viewer in a real headless browser (Playwright + Debian's chromium; SwiftShader where there is no GPU):
the benchmark command and the tests both go through :class:`ViewerPage`."""
from __future__ import annotations

import base64
import contextlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from nerfbake.viewer.server import ViewerServer

CHROMIUM_FLAGS = [
    "--no-sandbox", "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--no-first-run", "--disable-quic", "--ignore-gpu-blocklist",
]
SOFTWARE_GL_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
# Playwright's phone emulation (ViewerPage's ``device``): an iPhone-sized portrait viewport at scale 3 with touch.
PHONE_EMULATION = {"viewport": {"width": 390, "height": 844}, "device_scale_factor": 3, "is_mobile": True,
                   "has_touch": True}


def chromium_path() -> str:
    exe = os.environ.get("NERFBAKE_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not exe:
        raise FileNotFoundError("no chromium found: install Debian's chromium (apt-get install chromium) or set "
                                "NERFBAKE_CHROMIUM to a Chrome/Chromium binary")
    return exe


class ViewerPage:
    """The viewer open on one scene in headless chromium; console errors are collected in ``errors``."""

    def __init__(self, scene, query: str = "", size=(320, 240), software_gl: bool = True, timeout_s: float = 300,
                 static=None, device: dict | None = None):
        """``static``: serve another copy of the viewer's files (a benchmark's baseline); ``device``: Playwright
        context options such as a phone's ``viewport``, ``device_scale_factor``, ``is_mobile``, ``has_touch``."""
        self.scene, self.query, self.size, self.software_gl, self.timeout_ms = scene, query, size, software_gl, timeout_s * 1000
        self.static, self.device = static, device or {}
        self.errors: list[str] = []
        self.console: list[str] = []

    def __enter__(self) -> "ViewerPage":
        from playwright.sync_api import sync_playwright

        self._stack = contextlib.ExitStack()
        extra = {"static": self.static} if self.static else {}
        self.server = self._stack.enter_context(ViewerServer(self.scene, port=0, **extra))
        self._pw = self._stack.enter_context(sync_playwright())
        profile = self._stack.enter_context(tempfile.TemporaryDirectory(prefix="nerfbake-chromium-"))
        flags = CHROMIUM_FLAGS + (SOFTWARE_GL_FLAGS if self.software_gl else ["--enable-gpu", "--use-angle=default"])
        context = self._pw.chromium.launch_persistent_context(
            profile, executable_path=chromium_path(), headless=True, args=flags,
            **{"viewport": {"width": self.size[0], "height": self.size[1]}, **self.device})
        self._stack.callback(context.close)
        self.page = context.pages[0] if context.pages else context.new_page()
        self.page.set_default_timeout(self.timeout_ms)
        self.page.on("console", self._on_console)
        self.page.on("pageerror", lambda exc: self.errors.append(f"page error: {exc}"))
        sep = "&" if self.query else ""
        self.page.goto(f"{self.server.url}?s={self.size[0]},{self.size[1]}{sep}{self.query}")
        self.page.wait_for_function("() => window.nerfbake !== undefined")
        failure = self.page.evaluate("() => window.nerfbake.ready.then(() => null, (e) => String(e && e.message || e))")
        if failure:
            self.close()
            raise RuntimeError(f"the viewer failed to open {self.scene}: {failure}")
        return self

    def _on_console(self, msg) -> None:
        self.console.append(f"{msg.type}: {msg.text}")
        if msg.type == "error":
            self.errors.append(msg.text)

    def close(self) -> None:
        self._stack.close()

    def __exit__(self, *exc) -> None:
        self.close()

    def evaluate(self, js: str, arg=None):
        return self.page.evaluate(js, arg)

    def _image(self, b64: str, width: int, height: int) -> np.ndarray:
        return np.frombuffer(base64.b64decode(b64), np.uint8).reshape(height, width, 4)[..., :3]

    def render_test_view(self, index: int, width: int, height: int) -> np.ndarray:
        """(H, W, 3) uint8 image of a SMERF ``test_frames.json`` view."""
        b64 = self.evaluate("([i, w, h]) => window.nerfbake.renderTestView(i, w, h)", [index, width, height])
        return self._image(b64, width, height)

    def render_camera(self, camera: dict, width: int, height: int) -> np.ndarray:
        b64 = self.evaluate("([c, w, h]) => window.nerfbake.renderCamera(c, w, h)", [camera, width, height])
        return self._image(b64, width, height)

    def state(self) -> dict:
        return self.evaluate("() => window.nerfbake.state()")

    def benchmark(self, width: int, height: int, frame_mult: int = 1, frames_per_view: int = 6, warmup: int = 2,
                  max_views: int | None = None, gpu_timer: bool = False) -> dict:
        """Mean ms/frame over the scene's benchmark views at one size (``gpu_timer``: also GPU time, where the browser
        offers EXT_disjoint_timer_query_webgl2; the result's ``timer`` says which figure is which)."""
        return self.evaluate("([w, h, k, n, m, v, g]) => window.nerfbake.benchmark(w, h, k, n, m, v, g)",
                             [width, height, frame_mult, frames_per_view, warmup, max_views or 0, gpu_timer])

    def controls(self) -> dict:
        """The camera controls' state: position, rotation rows, orbit target, distance, yaw, pitch."""
        return self.evaluate("() => window.nerfbake.controls()")


def octree_camera(cam) -> dict:
    """A :class:`nerfbake.data.cameras.Camera` as the viewer's octree camera (pinhole, camera-to-world rows)."""
    return {"position": cam.c2w[:3, 3].tolist(), "rotation": cam.c2w[:3, :3].tolist(),
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}


def run_benchmark(scene, sizes=((512, 512), (1280, 720)), frame_mult: int = 1, frames_per_view: int = 6, warmup: int = 2,
                  max_views: int | None = None, software_gl: bool = True) -> dict:
    """Mean ms/frame per size over the scene's benchmark views, measured in the browser; on a real GPU
    (``software_gl=False``) each frame is also timed by the GPU where the browser offers a timer query, and
    ``ms_per_frame_WxH`` is then that GPU time."""
    out = {"scene": str(getattr(scene, "root", scene)), "sizes": []}
    with ViewerPage(scene, size=(256, 256), software_gl=software_gl) as page:
        for w, h in sizes:
            out["sizes"].append(page.benchmark(w, h, frame_mult, frames_per_view, warmup, max_views,
                                               gpu_timer=not software_gl))
        out["console_errors"] = page.errors
    first = out["sizes"][0]
    out.update(kind=first["kind"], renderer=first["renderer"], timer=first["timer"], gpu_bytes=first["gpu_bytes"])
    if "timer_note" in first:
        out["timer_note"] = first["timer_note"]
    for r in out["sizes"]:
        out[f"ms_per_frame_{r['width']}x{r['height']}"] = r.get("gpu_mean_ms_per_frame", r["mean_ms_per_frame"])
        out[f"wall_ms_per_frame_{r['width']}x{r['height']}"] = r["mean_ms_per_frame"]
    return out


def read_walkthrough(path, scene=None) -> list[dict] | None:
    """A camera path file for ``nerfbake view --walkthrough``: ``test`` (the scene's test cameras in order), a
    ``test_frames.json`` (``{"test_frames": [{position, rotation, projection}, ...]}``), or ``{"frames": [...]}`` /
    a list of ``{"position": [x, y, z], "forward": [x, y, z]}`` poses in the viewer's frame.

    ``test`` on a SMERF ``scene`` is the bake's own walk, ``test_frames.json`` beside the ``sm_XXX/`` folders, which
    holds every test view in the dataset's order: each folder's own file holds only the views whose camera that
    submodel holds, so the entry folder's views never leave it. Bakes from before that file walk every folder's views,
    folder after folder. None: the viewer's own test views (an octree's orbit)."""
    if str(path) == "test":
        if scene is None or scene.kind != "smerf":
            return None
        whole = scene.root / "test_frames.json"
        if whole.is_file():
            return read_walkthrough(whole)
        folders = sorted(p for p in scene.root.glob("sm_*") if (p / "test_frames.json").is_file())
        frames = [f for folder in folders for f in json.loads((folder / "test_frames.json").read_text())["test_frames"]]
        return frames if len(frames) >= 2 else None
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: no such walkthrough file; give a JSON camera path or 'test'") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p}: not a JSON camera path ({exc}); give test_frames.json, {{\"frames\": [...]}} or 'test'") from None
    frames = data.get("test_frames", data.get("frames")) if isinstance(data, dict) else data
    if not isinstance(frames, list) or len(frames) < 2:
        raise ValueError(f"{p}: a walkthrough needs a list of at least 2 cameras under 'test_frames' or 'frames'")
    for i, f in enumerate(frames):
        ok = isinstance(f, dict) and _numbers(f.get("position"), 3) and (
            _numbers(f.get("forward"), 3) or (_numbers(f.get("rotation"), 16) and _numbers(f.get("projection"), 16)))
        if not ok:
            raise ValueError(f"{p}: camera {i} needs position [3] and forward [3] (or rotation [16] and projection [16])")
    return frames


def _numbers(v, n: int) -> bool:
    return isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) and math.isfinite(x) for x in v)


def run_walkthrough(scene, path: list[dict] | None = None, size=(512, 512), between: int = 3,
                    software_gl: bool = True) -> dict:
    """Fly the viewer along a camera path (None: the scene's test cameras in order) with ``between`` interpolated
    frames per leg, streaming submodels as the interactive viewer does; per-frame times (p50/p95/max), frames drawn
    while a submodel was loading, blank frames, the most submodels resident on the GPU and the host cache size."""
    with ViewerPage(scene, size=(64, 64), software_gl=software_gl) as page:
        out = page.evaluate("([p, w, h, b]) => window.nerfbake.walkthrough(p, w, h, b)", [path, size[0], size[1], between])
        out["console_errors"] = page.errors
    out["scene"] = str(getattr(scene, "root", scene))
    return out

