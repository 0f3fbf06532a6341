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

@pytest.mark.parametrize("which,stride", [("ours", None), ("official", None), ("ours", 0), ("official", 0)])
def test_smerf_view_matches_the_python_renderer(which, stride, tiny_assets_dir):
    """Both ways of evaluating the deferred MLP's direction term: on the coarse pixel grid (the default, where the
    browser has float render targets, as SwiftShader has) and per pixel (directionStride=0)."""
    from nerfbake.smerf.assets import SceneAssets
    from nerfbake.smerf.baked_render import read_test_frames, render_baked
    from nerfbake.viewer.browser import ViewerPage

    assets = tiny_assets_dir if which == "ours" else shared_data("smerf_tiny")
    w, h = (48, 40) if which == "ours" else (80, 50)
    scene = SceneAssets.open(assets)
    cam = read_test_frames(scene.root / "sm_000" / "test_frames.json", w, h)[0]
    ref = np.round(render_baked(scene, cam) * 255)
    with ViewerPage(assets, query="" if stride is None else f"directionStride={stride}") as page:
        img = page.render_test_view(0, w, h)
        assert page.errors == []
        grid = page.state()["directionGrid"]
    assert grid == (None if stride == 0 else {"stride": 8, "format": "RGBA32F"})
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

def test_streaming_across_submodels_keeps_two_resident_and_evicts_lru(rooms_k3):
    from nerfbake.smerf.assets import SceneAssets
    from nerfbake.smerf.baked_render import submodel_center
    from nerfbake.viewer.browser import ViewerPage

    _, assets = rooms_k3
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



def test_walkthrough_streams_across_submodels_without_a_blank_frame(rooms_k3, tmp_path, capsys):
    """`view --benchmark --walkthrough PATH` flies through three submodels of a K = 3 scene: every frame is drawn
    (the resident submodel keeps drawing while the next one streams in), at most 2 submodels are on the GPU, and the
    frame-time figures are there."""
    from nerfbake.smerf.assets import SceneAssets
    from nerfbake.smerf.baked_render import submodel_center

    _, assets = rooms_k3
    scene = SceneAssets.open(assets)
    centers = [submodel_center(scene.params, i).tolist() for i in range(3)]
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"frames": [{"position": c, "forward": [0.0, 0.0, -1.0]} for c in centers]}))
    assert main(["view", str(assets), "--benchmark", "--walkthrough", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    # 3 path cameras and 3 interpolated frames on each of the 2 legs, then the last camera held until its own
    # submodel has streamed in (how long that takes is the machine's; that it ends there is the viewer's)
    assert out["console_errors"] == [] and out["frames"] == 3 + 2 * 3 + out["held_frames"] and out["path_cameras"] == 3
    assert out["settled"] and out["per_frame"][-1]["active"] == 2
    assert out["blank_frames"] == 0 and all(f["drawn"] and f["mean"] > 1.0 for f in out["per_frame"])
    assert out["max_resident"] <= 2 and set(out["uploads"]) >= {0, 1, 2}  # and any the legs pass through
    assert set(out["submodels_drawn"]) >= {0, 1, 2}
    for f in out["per_frame"]:
        assert f["loading"] is None or f["active"] != f["loading"]  # while one streams, another is drawn
    assert 0 < out["p50_ms"] <= out["p95_ms"] <= out["max_ms"]
    # `--walkthrough test`: every test view of the scene in the dataset's order, across the submodels holding them
    assert main(["view", str(assets), "--benchmark", "--walkthrough", "test", "--json"]) == 0
    walk = json.loads(capsys.readouterr().out)
    views = json.loads((assets / "test_frames.json").read_text())["test_frames"]
    assert walk["path_cameras"] == len(views) and walk["blank_frames"] == 0 and walk["max_resident"] <= 2
    assert len(set(walk["submodels_drawn"])) >= 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"frames": [{"position": [0, 0, 0]}]}))
    assert main(["view", str(assets), "--benchmark", "--walkthrough", str(bad)]) == 2
    assert "bad.json" in capsys.readouterr().err


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


def test_benchmark_times_frames_on_the_gpu_where_the_timer_query_is_offered():
    """`view --benchmark --gpu` asks for GPU time (EXT_disjoint_timer_query_webgl2); SwiftShader offers the extension
    too, so the path runs here: each view gets a GPU figure within the frame's own wall time, and the result says
    which timer its headline figure is."""
    from nerfbake.viewer.browser import ViewerPage

    with ViewerPage(shared_data("smerf_tiny")) as page:
        offered = page.evaluate("() => !!window.nerfbake.app.gl.getExtension('EXT_disjoint_timer_query_webgl2')")
        timed = page.benchmark(64, 48, frames_per_view=3, warmup=1, gpu_timer=True)
        plain = page.benchmark(64, 48, frames_per_view=1, warmup=1)
        assert page.errors == []
    assert plain["timer"] == "cpu" and "gpu_mean_ms_per_frame" not in plain
    if not offered:
        assert timed["timer"] == "cpu" and "not offered" in timed["timer_note"]
        return
    assert timed["timer"] == "gpu"
    for view in timed["views"]:
        assert 0 < view["gpu_ms_per_frame"] <= 1.1 * view["ms_per_frame"]  # the draws lie inside the timed interval
    assert timed["gpu_mean_ms_per_frame"] == pytest.approx(
        sum(v["gpu_ms_per_frame"] for v in timed["views"]) / len(timed["views"]))


# --- phones ---------------------------------------------------------------------------------------------------------------

def test_touch_controls_move_the_camera_in_phone_emulation():
    """One finger orbits, a pinch zooms, two fingers moving together pan: driven by touch events that go through
    chromium's own input pipeline (DevTools Input.dispatchTouchEvent), as a phone's screen sends them."""
    from nerfbake.viewer.browser import PHONE_EMULATION, ViewerPage

    with ViewerPage(shared_data("smerf_tiny"), query="quality=phone&mouseMode=orbit", size=(390, 844),
                    device=PHONE_EMULATION) as page:
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


def test_viewer_speed_benchmark_compares_the_frozen_baseline_with_the_current_viewer(tmp_path):
    """benchmarks/viewer_speed.py opens one scene with the frozen viewer files and the current ones: every figure is
    there and the two pictures agree within the browser-vs-Python threshold (the speed-ups change no picture);
    --phone does the same under phone emulation at both of quality=phone's frame sizes."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "viewer_speed.py"
    quick = ["--rounds", "1", "--frames", "1", "--warmup", "1", "--out", str(tmp_path)]
    run = subprocess.run([sys.executable, str(script), "--assets", str(shared_data("smerf_tiny")), "--size", "96,64",
                          *quick], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["baseline_ms"] > 0 and out["current_ms"] > 0 and out["speedup"] == out["baseline_ms"] / out["current_ms"]
    assert out["psnr_current_vs_baseline"] >= 35
    assert all(Path(p).is_file() for p in out["screenshots"].values())
    run = subprocess.run([sys.executable, str(script), "--assets", str(shared_data("smerf_tiny")), "--phone", *quick],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert "quality=phone" in out["query"] and out["device"]["has_touch"]
    assert (out["resting"]["width"], out["resting"]["height"]) == (390, 844)
    assert out["moving"]["width"] * out["moving"]["height"] <= 300 * 450 + 600
    for size in ("resting", "moving"):
        assert out[size]["current_ms"] > 0 and out[size]["psnr_current_vs_baseline"] >= 35
        assert out[size]["gpu_bytes"]["current"] > 0
