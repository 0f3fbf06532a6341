"""The web viewer in a real headless chromium (SwiftShader here): its pictures against the Python renderers on the
same views, streaming across submodels, benchmark output, and the server's path rules."""
import json
import shutil

import numpy as np
import pytest

from nerfbake.cli import main
from tests.conftest import shared_data

pytestmark = pytest.mark.skipif(shutil.which("chromium") is None, reason="needs Debian's chromium (make test installs it)")


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2) / 255.0 ** 2
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


# --- pictures against the Python renderers ----------------------------------------------------------------------------

@pytest.mark.parametrize("which", ["ours", "official"])
def test_smerf_view_matches_the_python_renderer(which, tiny_assets_dir):
    from nerfbake.smerf.assets import SceneAssets
    from nerfbake.smerf.baked_render import read_test_frames, render_baked
    from nerfbake.viewer.browser import ViewerPage

    assets = tiny_assets_dir if which == "ours" else shared_data("smerf_tiny")
    w, h = (48, 40) if which == "ours" else (80, 50)
    scene = SceneAssets.open(assets)
    cam = read_test_frames(scene.root / "sm_000" / "test_frames.json", w, h)[0]
    ref = np.round(render_baked(scene, cam) * 255)
    with ViewerPage(assets) as page:
        img = page.render_test_view(0, w, h)
        assert page.errors == []
    assert ref.std() > 5  # the view shows something
    assert psnr(img, ref) >= 35


@pytest.mark.parametrize("which,query", [("built", ""), ("built", "maxTextureSize=64"), ("env-map", ""), ("svox", ""),
                                         ("svox-deflate", ""), ("compressed", ""), ("ours-compressed", "")])
def test_octree_view_matches_the_python_renderer(which, query, tiny_tree, tiny_scene, tmp_path):
    from nerfbake.data.cameras import Camera
    from nerfbake.data.formats import load_dataset
    from nerfbake.octree.io import load_tree
    from nerfbake.octree.render import RenderOptions, render_camera
    from nerfbake.viewer.browser import ViewerPage, octree_camera

    if which in ("built", "env-map", "ours-compressed"):
        path = tiny_tree
        cam = load_dataset(tiny_scene).frames[load_dataset(tiny_scene).split("test")[0]].camera
    if which == "ours-compressed":  # bits chosen by measured error, k-means codebooks, the compression record key
        from nerfbake.octree.compress import compress_tree

        path = compress_tree(tiny_tree, tmp_path / "c.npz", data=tiny_scene, views=2, sigma_thresh=0.1)["tree"]
    elif which == "env-map":  # what lies beyond the box drawn from an environment map (render/envmap.py)
        import torch

        from nerfbake.octree.io import save_tree

        tree = load_tree(tiny_tree)
        tree.env_map = torch.rand(8, 16, 3, generator=torch.Generator().manual_seed(0))
        path = save_tree(tree, tmp_path / "env.npz")
    elif which != "built":
        name = {"svox": "good_svox_raw.npz", "svox-deflate": "good_svox_deflate.npz", "compressed": "good_compressed_numpy.npz"}
        path = shared_data("octree_fixtures") / name[which]
        tree = load_tree(path)
        c = ((0.5 - tree.offset) / tree.invradius).numpy()  # the sphere's centre, seen from an oblique direction
        eye = c + np.array([0.9, -1.1, 0.7]) / tree.invradius.numpy() * 1.2
        f = (c - eye) / np.linalg.norm(c - eye)
        r = np.cross(f, [0, 0, 1.0])
        r /= np.linalg.norm(r)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([r, np.cross(r, f), -f], 1)
        c2w[:3, 3] = eye
        cam = Camera(c2w, 40, 32, 40.0, 40.0, 20.0, 16.0)
    ref = np.round(np.clip(render_camera(load_tree(path), cam, RenderOptions())["rgb"], 0, 1) * 255)
    with ViewerPage(path, query=query) as page:
        img = page.render_camera(octree_camera(cam), cam.width, cam.height)
        state = page.state()
        assert page.errors == []
    if query:
        assert state["tiles"]["data"]["layers"] > 1  # one texture would exceed the limit: tiled over layers
    assert state["envMap"] == ([8, 16] if which == "env-map" else None)
    assert ref.std() > 5
    assert psnr(img, ref) >= 35
    if which == "env-map":  # the view does show the map
        plain = np.round(np.clip(render_camera(load_tree(tiny_tree), cam, RenderOptions())["rgb"], 0, 1) * 255)
        assert np.mean(np.abs(plain - ref).max(-1) > 20) > 0.2


# --- streaming ----------------------------------------------------------------------------------------------------------

def test_streaming_across_submodels_keeps_two_resident_and_evicts_lru(rooms_k2):
    from nerfbake.smerf.assets import SceneAssets
    from nerfbake.smerf.baked_render import submodel_center
    from nerfbake.viewer.browser import ViewerPage

    _, assets = rooms_k2
    scene = SceneAssets.open(assets)
    n = scene.params["num_local_submodels"]
    assert n >= 3
    centers = [submodel_center(scene.params, i) for i in range(n)]
    start = ",".join(str(v) for v in [*centers[0], 0.0, 0.0, -1.0])  # in submodel 0, looking down -z
    with ViewerPage(assets, query=f"submodelCacheSize=1&frameLog=1&mouseMode=fly&pose={start}", size=(48, 32)) as page:
        for target in [1, 2, 0, 1]:
            page.evaluate("() => window.nerfbake.clearFrameLog()")
            page.evaluate("([p, f]) => window.nerfbake.setPose(p, f)", [list(centers[target]), [0.0, 0.0, -1.0]])
            page.page.wait_for_function(f"() => window.nerfbake.state().active === {target}", timeout=120_000)
            page.page.wait_for_function("() => window.nerfbake.frameLog().length > 2", timeout=120_000)
            log = page.evaluate("() => window.nerfbake.frameLog()")
            assert all(f["drawn"] and f["mean"] > 1.0 for f in log), log  # never a black frame while loading
            assert all(len(f["resident"]) <= 2 for f in log)
        state = page.state()
        assert page.errors == []
    assert state["fetches"][:4] == [0, 1, 2, 0]  # 0 again: evicted from the 1-entry host cache, fetched anew
    assert state["evictions"][:3] == [0, 1, 2] and len(state["hostCache"]) == 1
    assert len(state["resident"]) == 2 and state["active"] == 1


# --- benchmark ----------------------------------------------------------------------------------------------------------

def test_view_benchmark_prints_ms_per_frame_for_both_sizes(tiny_tree, capsys):
    quick = ["--benchmark", "--frames", "1", "--warmup", "1", "--max-views", "1", "--json"]
    assert main(["view", str(shared_data("smerf_tiny")), *quick]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["kind"] == "smerf" and out["console_errors"] == []
    for key in ("ms_per_frame_512x512", "ms_per_frame_1280x720"):
        assert out[key] > 0
    assert main(["view", str(tiny_tree), *quick]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["kind"] == "octree" and out["ms_per_frame_1280x720"] > 0 and len(out["sizes"][0]["views"]) == 1


# --- phones ---------------------------------------------------------------------------------------------------------------

PHONE = {"viewport": {"width": 390, "height": 844}, "device_scale_factor": 3, "is_mobile": True, "has_touch": True}


def test_touch_controls_move_the_camera_in_phone_emulation():
    """One finger orbits, a pinch zooms, two fingers moving together pan: driven by touch events that go through
    chromium's own input pipeline (DevTools Input.dispatchTouchEvent), as a phone's screen sends them."""
    from nerfbake.viewer.browser import ViewerPage

    with ViewerPage(shared_data("smerf_tiny"), query="quality=phone&mouseMode=orbit", size=(390, 844),
                    device=PHONE) as page:
        cdp = page.page.context.new_cdp_session(page.page)

        def gesture(paths):  # paths: one list of (x, y) per finger, all the same length
            def send(kind, k):
                points = [] if kind == "touchEnd" else [{"x": p[k][0], "y": p[k][1], "id": i} for i, p in enumerate(paths)]
                cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": points})
            send("touchStart", 0)
            for k in range(1, len(paths[0])):
                send("touchMove", k)
            send("touchEnd", 0)

        assert page.evaluate("() => window.innerWidth") == 390 and page.evaluate("() => window.devicePixelRatio") == 3
        start = page.controls()
        gesture([[(150 + 20 * k, 400 + 4 * k) for k in range(6)]])  # one finger: orbit
        orbit = page.controls()
        assert abs(orbit["yaw"] - start["yaw"]) > 0.2 and abs(orbit["pitch"] - start["pitch"]) > 0.02
        assert orbit["distance"] == pytest.approx(start["distance"]) and orbit["target"] == pytest.approx(start["target"])
        assert np.linalg.norm(np.subtract(orbit["position"], start["position"])) > 0.01

        gesture([[(195, 400 - 15 * k) for k in range(6)], [(195, 440 + 15 * k) for k in range(6)]])  # pinch out
        pinch = page.controls()
        assert pinch["distance"] < 0.6 * orbit["distance"]  # 40 px apart -> 190 px apart: zoomed in
        # the midpoint stays put: the target drifts by under 2 % of the distance (each finger's event pans by half
        # its motion at the distance of that moment), and the view does not turn
        assert np.linalg.norm(np.subtract(pinch["target"], orbit["target"])) < 0.02 * orbit["distance"]
        assert pinch["yaw"] == orbit["yaw"]

        gesture([[(150 + 20 * k, 400) for k in range(6)], [(150 + 20 * k, 480) for k in range(6)]])  # two-finger pan
        pan = page.controls()
        assert np.linalg.norm(np.subtract(pan["target"], pinch["target"])) > 0.1 * pinch["distance"]
        assert pan["distance"] == pytest.approx(pinch["distance"]) and pan["yaw"] == pinch["yaw"]
        frames = page.state()["frames"]
        page.page.wait_for_function(f"() => window.nerfbake.state().frames > {frames + 2}")  # and it keeps drawing
        assert page.errors == []
