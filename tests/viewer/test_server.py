"""The viewer's HTTP server: it serves exactly the scene named and the viewer's files, streams with Range support on a
bounded pool of threads, and refuses everything else (no browser needed)."""
import gzip
import http.client
import json
import os
import shutil
import socket
import tracemalloc
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from nerfbake.cli import main
from nerfbake.viewer.server import SceneError, ViewerServer, find_scene, parse_range
from tests.conftest import shared_data

SECRET = b"not for the browser"


def _get(server, path, method="GET", headers=None):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    conn.request(method, path, headers=headers or {})
    res = conn.getresponse()
    out = res.status, dict(res.getheaders()), res.read()
    conn.close()
    return out


@pytest.fixture
def tree_of_secrets(tmp_path):
    """An asset folder next to files that must never be served: a secret, a dot folder, symlinks out of the scene."""
    assets = tmp_path / "scene"
    shutil.copytree(shared_data("smerf_tiny"), assets)
    (tmp_path / "secret.txt").write_bytes(SECRET)
    (tmp_path / ".ssh").mkdir()
    (tmp_path / ".ssh" / "id_rsa").write_bytes(SECRET)
    (assets / ".env").write_bytes(SECRET)
    (assets / "sm_000" / "link.raw").symlink_to(tmp_path / "secret.txt")
    (assets / "sm_000" / "evil.raw.gz").symlink_to(tmp_path / "secret.txt")  # reached through the X.raw -> X.raw.gz fallback
    return tmp_path, assets


def test_serves_gzip_assets_the_viewer_and_the_scene_description(tree_of_secrets):
    _, assets = tree_of_secrets
    with ViewerServer(assets, port=0) as server:
        status, headers, body = _get(server, "/scene/sm_000/sparse_grid_block_indices.raw")
        assert status == 200 and headers["Content-Encoding"] == "gzip" and "max-age" in headers["Cache-Control"]
        assert gzip.decompress(body) == gzip.decompress((assets / "sm_000" / "sparse_grid_block_indices.raw.gz").read_bytes())
        status, headers, body = _get(server, "/scene/sm_000/deferred_mlp.json")
        assert status == 200 and "ResampleDense_0/kernel" in json.loads(gzip.decompress(body))
        assert _get(server, "/")[0] == 200 and _get(server, "/viewer/main.js")[1]["Content-Type"] == "text/javascript"
        info = json.loads(_get(server, "/scene.json")[2])
        assert info["kind"] == "smerf" and info["entry"] == "sm_000" and info["submodels"] == ["sm_000"]
        assert _get(server, "/scene/sm_000/nothing.raw")[0] == 404
        assert _get(server, "/elsewhere")[0] == 404


@pytest.mark.parametrize("path", [
    "/scene/../secret.txt", "/scene/%2e%2e/secret.txt", "/scene/%2E%2E%2Fsecret.txt", "/scene/sm_000/../../secret.txt",
    "/scene/sm_000/%2e%2e%2f%2e%2e%2fsecret.txt", "/scene/..%5csecret.txt", "/scene//etc/passwd", "/scene/%2Fetc%2Fpasswd",
    "/scene/%2e%2e/.ssh/id_rsa", "/scene/.env", "/scene/sm_000/./scene_params.json", "/scene/sm_000/link.raw",
    "/scene/sm_000/evil.raw", "/scene/sm_000/scene_params.json%00.png", "/viewer/../server.py", "/viewer/%2e%2e/server.py",
])
def test_nothing_outside_the_scene_is_served(tree_of_secrets, path):
    _, assets = tree_of_secrets
    with ViewerServer(assets, port=0) as server:
        for method in ("GET", "HEAD"):
            status, _, body = _get(server, path, method)
            assert status == 403 and SECRET not in body, (method, path, status)


def test_one_submodel_folder_serves_its_scene_and_nothing_else_of_the_parent(tree_of_secrets):
    root, assets = tree_of_secrets
    shutil.copytree(assets / "sm_000", assets / "sm_001")
    (assets / "notes.txt").write_bytes(SECRET)
    (assets / "sm_backup").mkdir()
    (assets / "sm_backup" / "scene_params.json").write_bytes(SECRET)
    with ViewerServer(assets / "sm_000", port=0) as server:
        info = json.loads(_get(server, "/scene.json")[2])
        assert info["entry"] == "sm_000" and info["submodels"] == ["sm_000", "sm_001"]
        assert _get(server, "/scene/sm_000/scene_params.json")[0] == 200
        assert _get(server, "/scene/sm_001/scene_params.json")[0] == 200  # a sibling submodel of the same scene
        for bad in ("/scene/notes.txt", "/scene/sm_backup/scene_params.json", "/scene/.env", "/scene/../secret.txt"):
            status, _, body = _get(server, bad)
            assert status == 403 and SECRET not in body, bad


def test_a_tree_serves_only_itself_not_a_same_named_file_elsewhere(tmp_path):
    tree = tmp_path / "t.npz"
    tree.write_bytes((shared_data("octree_fixtures") / "good_svox_raw.npz").read_bytes())
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "t.npz").write_bytes(SECRET)
    (tmp_path / "secret.txt").write_bytes(SECRET)
    with ViewerServer(tree, port=0) as server:
        assert _get(server, "/scene/t.npz")[2] == tree.read_bytes()
        for bad in ("/scene/secret.txt", "/scene/sub/t.npz"):
            assert _get(server, bad)[0] == 403, bad


def test_a_splat_file_serves_itself_the_splat_page_and_gsplat_js_only(tmp_path):
    from nerfbake.viewer.server import GSPLAT_DIST

    if not (GSPLAT_DIST / "index.es.js").is_file():
        pytest.skip(f"gsplat.js not installed at {GSPLAT_DIST} (make setup installs it with npm)")
    splats = tmp_path / "scene.ply"
    splats.write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n")
    (tmp_path / "secret.txt").write_bytes(SECRET)
    with ViewerServer(splats, port=0) as server:
        assert json.loads(_get(server, "/scene.json")[2])["kind"] == "splats"
        assert b"/viewer/splats.js" in _get(server, "/")[2]
        assert _get(server, "/scene/scene.ply")[2] == splats.read_bytes()
        status, headers, body = _get(server, "/gsplat/index.es.js")
        assert status == 200 and headers["Content-Type"] == "text/javascript" and body == (GSPLAT_DIST / "index.es.js").read_bytes()
        for bad in ("/scene/secret.txt", "/gsplat/../../secret.txt", "/gsplat/%2e%2e/package.json"):
            assert _get(server, bad)[0] in (403, 404), bad
    with ViewerServer(shared_data("smerf_tiny"), port=0) as server:  # other scenes have no /gsplat/
        assert _get(server, "/gsplat/index.es.js")[0] == 404


def test_find_scene_and_the_cli_refuse_what_is_not_a_scene(tmp_path):
    (tmp_path / "secret.txt").write_bytes(SECRET)
    with pytest.raises(SceneError, match="not a SMERF asset directory"):
        find_scene(tmp_path)
    with pytest.raises(SceneError, match="no such scene"):
        find_scene(tmp_path / "missing")
    assert main(["view", str(tmp_path / "secret.txt")]) == 2


def test_range_requests_and_head(tmp_path):
    tree = tmp_path / "t.npz"
    data = np.random.default_rng(0).integers(0, 256, 100_000, dtype=np.uint8).tobytes()
    tree.write_bytes(data)
    with ViewerServer(tree, port=0) as server:
        status, headers, body = _get(server, "/scene/t.npz", headers={"Range": "bytes=10-19"})
        assert status == 206 and body == data[10:20] and headers["Content-Range"] == f"bytes 10-19/{len(data)}"
        status, headers, body = _get(server, "/scene/t.npz", headers={"Range": "bytes=-5"})
        assert status == 206 and body == data[-5:]
        status, headers, body = _get(server, "/scene/t.npz", headers={"Range": "bytes=99990-"})
        assert status == 206 and body == data[99990:]
        status, headers, _ = _get(server, "/scene/t.npz", headers={"Range": "bytes=200000-"})
        assert status == 416 and headers["Content-Range"] == f"bytes */{len(data)}"
        status, headers, body = _get(server, "/scene/t.npz")
        assert status == 200 and body == data and headers["Accept-Ranges"] == "bytes"
        # HEAD: the whole file's length, and no body on the wire
        with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
            s.sendall(b"HEAD /scene/t.npz HTTP/1.0\r\nHost: x\r\n\r\n")
            raw = b""
            while chunk := s.recv(65536):
                raw += chunk
        head, _, rest = raw.partition(b"\r\n\r\n")
        assert f"Content-Length: {len(data)}".encode() in head and rest == b""
    assert parse_range("bytes=0-0,5-9", 10) is None  # several ranges: the whole file is a valid answer
    assert parse_range("bytes=5-2", 10) == "unsatisfiable"


def test_a_busy_port_is_a_clear_error(tmp_path):
    tree = tmp_path / "t.npz"
    tree.write_bytes(b"x")
    with ViewerServer(tree, port=0) as first:
        with pytest.raises(SceneError, match="--port"):
            ViewerServer(tree, port=first.port)
        assert main(["view", str(tree), "--port", str(first.port)]) == 2


def test_many_clients_get_every_byte_and_memory_stays_bounded(tmp_path):
    """32 concurrent clients fetch every asset of a scene for 3 rounds, then 8 fetch one 48 MB file together: every
    byte matches, and the server's Python allocations stay far below what reading whole files per request takes."""
    assets = tmp_path / "scene"
    shutil.copytree(shared_data("smerf_tiny"), assets)
    files = sorted(p for p in (assets / "sm_000").iterdir() if p.is_file())
    big = assets / "sm_000" / "big.raw"
    big.write_bytes(os.urandom(48 << 20))
    with ViewerServer(assets, port=0) as server:
        def fetch_all(_):
            for p in files:
                status, _, body = _get(server, f"/scene/sm_000/{p.name}")
                assert status == 200 and body == p.read_bytes(), p.name
            return True

        with ThreadPoolExecutor(32) as pool:
            assert all(pool.map(fetch_all, range(32 * 3)))

        def fetch_big(_):
            conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=60)
            conn.request("GET", "/scene/sm_000/big.raw")
            res = conn.getresponse()
            n = 0
            while chunk := res.read(1 << 16):  # the client streams too, so what is measured is the server
                n += len(chunk)
            conn.close()
            return res.status == 200 and n == big.stat().st_size

        tracemalloc.start()
        try:
            with ThreadPoolExecutor(8) as pool:
                assert all(pool.map(fetch_big, range(8)))
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert peak < 32 << 20, f"server held {peak / 2**20:.0f} MiB for 8 clients of a 48 MiB file"
