"""``nerfbake view``: serve the web viewer and one scene over HTTP.

Three URL spaces and nothing else: ``/`` and ``/viewer/...`` are the static viewer files shipped in the package,
``/scene.json`` describes the scene, ``/scene/...`` are the scene's own files. A request for ``X.raw`` or ``X.json``
that exists on disk only as ``X.raw.gz`` / ``X.json.gz`` is answered with the compressed bytes and
``Content-Encoding: gzip`` (what the official SMERF viewer expects of its server). Paths are resolved and must stay
inside their folder: ``..``, absolute paths and symlinks leaving the folder are refused with 403.
"""
from __future__ import annotations

import json
import mimetypes
import threading
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

STATIC = Path(__file__).resolve().parent / "static"


class SceneError(ValueError):
    """A path that is neither a baked SMERF asset directory nor a PlenOctree ``.npz``."""


@dataclass
class Scene:
    kind: str  # "smerf" | "octree"
    root: Path  # folder served under /scene/
    entry: str  # path below root the viewer starts from: "sm_000" or "tree.npz"
    name: str

    def describe(self) -> dict:
        out = {"kind": self.kind, "name": self.name, "base": "/scene/", "entry": self.entry}
        if self.kind == "smerf":
            out["submodels"] = sorted(p.name for p in self.root.glob("sm_*") if p.is_dir())
        return out


def _has_params(folder: Path) -> bool:
    return (folder / "scene_params.json").is_file() or (folder / "scene_params.json.gz").is_file()


def find_scene(path: str | Path) -> Scene:
    """A SMERF asset directory (the folder holding ``sm_XXX/``, or one ``sm_XXX`` folder) or a tree ``.npz``."""
    path = Path(path).expanduser().resolve()
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such scene; pass a baked SMERF folder (nerfbake bake) or a tree .npz")
    if path.is_file():
        if path.suffix != ".npz":
            raise SceneError(f"{path}: not a PlenOctree .npz or SMERF asset folder")
        return Scene("octree", path.parent, path.name, path.stem)
    if _has_params(path):  # an sm_XXX folder itself, as the official viewer's ?dir= takes
        return Scene("smerf", path.parent, path.name, path.parent.name)
    subs = sorted(p for p in path.glob("sm_*") if p.is_dir() and _has_params(p))
    if not subs:
        raise SceneError(f"{path}: no sm_XXX/scene_params.json inside; not a SMERF asset directory "
                         "(bake one with `nerfbake bake`, or pass a PlenOctree .npz)")
    return Scene("smerf", path, subs[0].name, path.name)


def resolve_inside(root: Path, rel: str) -> Path | None:
    """``root/rel`` if it stays inside ``root`` (after resolving ``..`` and symlinks), else None."""
    if not rel or rel.startswith("/") or "\\" in rel or "\x00" in rel:
        return None
    parts = rel.split("/")
    if any(p in ("..", "") for p in parts[:-1]) or parts[-1] == "..":
        return None
    root = root.resolve()
    target = (root / rel).resolve()
    return target if target == root or root in target.parents else None


def make_handler(scene: Scene):
    class Handler(BaseHTTPRequestHandler):
        server_version = "nerfbake-view"

        def log_message(self, fmt, *args):  # quiet: the terminal shows the URL, not every texture fetch
            pass

        def do_HEAD(self):
            self._serve(head=True)

        def do_GET(self):
            self._serve(head=False)

        def _send(self, status, body: bytes, ctype: str, headers: dict | None = None, head=False):
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            for k, v in (headers or {}).items():
                self.send_header(k, v)
            self.end_headers()
            if not head:
                self.wfile.write(body)

        def _error(self, status: HTTPStatus, head: bool):
            self._send(status, f"{status.value} {status.phrase}\n".encode(), "text/plain", {"Cache-Control": "no-store"}, head)

        def _serve(self, head: bool):
            raw_path = urlsplit(self.path).path
            path = unquote(raw_path)
            if path in ("/", "/index.html"):
                return self._file(STATIC / "index.html", head, cache="no-cache")
            if path == "/scene.json":
                body = json.dumps(scene.describe()).encode()
                return self._send(HTTPStatus.OK, body, "application/json", {"Cache-Control": "no-cache"}, head)
            for prefix, root, cache in (("/viewer/", STATIC, "no-cache"), ("/scene/", scene.root, "public, max-age=3600")):
                if path.startswith(prefix):
                    target = resolve_inside(root, path[len(prefix):])
                    if target is None:
                        return self._error(HTTPStatus.FORBIDDEN, head)
                    if scene.kind == "octree" and root is scene.root and target.name != scene.entry:
                        return self._error(HTTPStatus.FORBIDDEN, head)  # only the tree itself, not its neighbours
                    return self._file(target, head, cache)
            return self._error(HTTPStatus.NOT_FOUND, head)

        def _file(self, target: Path, head: bool, cache: str):
            headers = {"Cache-Control": cache}
            gz = target.with_name(target.name + ".gz")
            if not target.is_file() and gz.is_file():
                target = gz
                headers["Content-Encoding"] = "gzip"
                ctype = mimetypes.guess_type(gz.name[:-3])[0] or "application/octet-stream"
            elif target.is_file():
                ctype = mimetypes.guess_type(target.name)[0] or "application/octet-stream"
            else:
                return self._error(HTTPStatus.NOT_FOUND, head)
            if target.suffix in (".js", ".mjs"):
                ctype = "text/javascript"
            self._send(HTTPStatus.OK, target.read_bytes(), ctype, headers, head)

    return Handler


class ViewerServer:
    """A threaded HTTP server for one scene, started in the background (``with ViewerServer(...) as s: s.url``)."""

    def __init__(self, scene: str | Path | Scene, host: str = "127.0.0.1", port: int = 8000):
        self.scene = scene if isinstance(scene, Scene) else find_scene(scene)
        self.httpd = ThreadingHTTPServer((host, port), make_handler(self.scene))
        self.httpd.daemon_threads = True
        self.host = host
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return self.httpd.server_address[1]

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}/"

    def start(self) -> "ViewerServer":
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
