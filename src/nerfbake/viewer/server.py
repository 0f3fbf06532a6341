"""``nerfbake view``: serve the web viewer and one scene over HTTP.

Three URL spaces and nothing else: ``/`` and ``/viewer/...`` are the static viewer files shipped in the package,
``/scene.json`` describes the scene, ``/scene/...`` are the scene's own files; for a splat file (``.ply``,
``.splat``) also ``/gsplat/...``, the gsplat.js library that draws it (installed from npm by ``make setup``). A
request for ``X.raw`` or ``X.json`` that exists on disk only as ``X.raw.gz`` / ``X.json.gz`` is answered with the
compressed bytes and ``Content-Encoding: gzip`` (what the official SMERF viewer expects of its server).

Only the scene the user named is served: a whole asset folder, one ``sm_XXX`` folder (with its sibling ``sm_XXX``
submodel folders, which the viewer streams, and nothing else of the parent), or one ``.npz``. Every path, the
``.gz`` fallback included, is resolved through symlinks and refused with 403 unless it lands inside what is served;
dotfiles are refused. Files are streamed in chunks with ``Range`` support, by a bounded pool of worker threads, so
a 1.6 GB raw tree neither sits in memory per request nor lets many clients exhaust the machine.
"""
from __future__ import annotations

import json
import mimetypes
import re
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

from nerfbake.errors import NerfbakeError

STATIC = Path(__file__).resolve().parent / "static"
CHUNK = 1 << 20  # bytes per write while streaming a file
WORKERS = 16  # requests handled at once; further connections wait in the listen queue
CLIENT_TIMEOUT_S = 60  # a client that sends or reads nothing for this long is dropped, freeing its worker
SUBMODEL = re.compile(r"sm_\d+")
SPLAT_SUFFIXES = (".ply", ".splat")
# gsplat.js (npm ``gsplat``), which draws splat files; ``make setup`` installs it into the environment's npm folder
GSPLAT_DIST = Path(sys.prefix) / "npm" / "node_modules" / "gsplat" / "dist"
GSPLAT_MISSING = (f"{GSPLAT_DIST}: gsplat.js is not installed; run make setup with npm available "
                  "(npm install --prefix .venv/npm gsplat@1.2.9)")


class SceneError(NerfbakeError):
    """A path that is neither a baked SMERF asset directory nor a PlenOctree ``.npz``, or a server that cannot start."""


@dataclass
class Scene:
    kind: str  # "smerf" | "octree" | "splats"
    root: Path  # folder whose files appear under /scene/
    entry: str  # path below root the viewer starts from: "sm_000", "tree.npz" or "scene.ply"
    name: str
    served: list[Path] = field(default_factory=list)  # resolved folders/files below root that may be served

    def __post_init__(self):
        self.root = self.root.resolve()
        if not self.served:
            self.served = [self.root]
        self.served = [p.resolve() for p in self.served]

    def describe(self) -> dict:
        out = {"kind": self.kind, "name": self.name, "base": "/scene/", "entry": self.entry}
        if self.kind == "smerf":
            out["submodels"] = sorted(p.name for p in self.served if p.is_dir() and SUBMODEL.fullmatch(p.name)) \
                if self.served != [self.root] else sorted(p.name for p in self.root.glob("sm_*") if p.is_dir())
        return out

    def allows(self, path: Path) -> bool:
        """Whether a resolved path lies inside what this scene serves."""
        return any(path == s or s in path.parents for s in self.served)


def _has_params(folder: Path) -> bool:
    return (folder / "scene_params.json").is_file() or (folder / "scene_params.json.gz").is_file()


def find_scene(path: str | Path) -> Scene:
    """A SMERF asset directory (the folder holding ``sm_XXX/``, or one ``sm_XXX`` folder), a tree ``.npz`` or a
    splat file (``.ply`` / ``.splat``, as ``nerfbake export`` writes)."""
    path = Path(path).expanduser().resolve()
    if not path.exists():
        raise SceneError(f"{path}: no such scene; pass a baked SMERF folder (nerfbake bake), a tree .npz or a splat "
                         ".ply/.splat (nerfbake export)")
    if path.is_file():
        if path.suffix.lower() in SPLAT_SUFFIXES:
            if not (GSPLAT_DIST / "index.es.js").is_file():
                raise SceneError(GSPLAT_MISSING)
            return Scene("splats", path.parent, path.name, path.stem, [path])
        if path.suffix != ".npz":
            raise SceneError(f"{path}: not a PlenOctree .npz, a splat .ply/.splat or a SMERF asset folder")
        return Scene("octree", path.parent, path.name, path.stem, [path])
    if _has_params(path):  # an sm_XXX folder itself, as the official viewer's ?dir= takes
        siblings = [p for p in path.parent.iterdir() if SUBMODEL.fullmatch(p.name) and p.is_dir() and _has_params(p)]
        return Scene("smerf", path.parent, path.name, path.parent.name, sorted(set(siblings) | {path}))
    subs = sorted(p for p in path.glob("sm_*") if p.is_dir() and _has_params(p))
    if not subs:
        raise SceneError(f"{path}: no sm_XXX/scene_params.json inside; not a SMERF asset directory "
                         "(bake one with `nerfbake bake`, or pass a PlenOctree .npz)")
    return Scene("smerf", path, subs[0].name, path.name)


def resolve_inside(root: Path, rel: str, allowed=None) -> Path | None:
    """``root/rel`` resolved (symlinks included) if ``rel`` is a plain relative path without dotfile parts and
    the result stays inside ``root`` (and passes ``allowed``), else None."""
    if not rel or rel.startswith("/") or "\\" in rel or "\x00" in rel:
        return None
    parts = rel.split("/")
    if any(p == "" or p.startswith(".") for p in parts):  # "..", ".", dotfiles, "//"
        return None
    root = root.resolve()
    target = (root / rel).resolve()
    if not (target == root or root in target.parents):
        return None
    return target if allowed is None or allowed(target) else None


def parse_range(header: str | None, size: int) -> tuple[int, int] | None | str:
    """A single ``bytes=a-b`` / ``a-`` / ``-n`` range as (first, last) inclusive; None for no (or an ignorable)
    header; "unsatisfiable" when it selects nothing of a ``size``-byte file."""
    if not header:
        return None
    m = re.fullmatch(r"\s*bytes\s*=\s*(\d*)\s*-\s*(\d*)\s*", header)
    if not m or (m.group(1) == "" and m.group(2) == ""):
        return None  # multiple or malformed ranges: RFC 9110 lets a server answer with the whole file
    a, b = m.group(1), m.group(2)
    if a == "":
        n = int(b)
        if n == 0 or size == 0:
            return "unsatisfiable"
        return max(0, size - n), size - 1
    first = int(a)
    last = size - 1 if b == "" else min(int(b), size - 1)
    if first >= size or last < first:
        return "unsatisfiable"
    return first, last


def make_handler(scene: Scene, static: Path = STATIC):
    class Handler(BaseHTTPRequestHandler):
        server_version = "nerfbake-view"
        timeout = CLIENT_TIMEOUT_S

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

        def _error(self, status: HTTPStatus, head: bool, headers: dict | None = None):
            self._send(status, f"{status.value} {status.phrase}\n".encode(), "text/plain",
                       {"Cache-Control": "no-store", **(headers or {})}, head)

        def _serve(self, head: bool):
            path = unquote(urlsplit(self.path).path)
            if path in ("/", "/index.html"):
                page = "splats.html" if scene.kind == "splats" else "index.html"
                return self._file(static / page, None, head, cache="no-cache")
            if path == "/scene.json":
                body = json.dumps(scene.describe()).encode()
                return self._send(HTTPStatus.OK, body, "application/json", {"Cache-Control": "no-cache"}, head)
            if path.startswith("/viewer/"):
                rel, root, allowed, cache = path[len("/viewer/"):], static, None, "no-cache"
            elif path.startswith("/scene/"):
                rel, root, allowed, cache = path[len("/scene/"):], scene.root, scene.allows, "public, max-age=3600"
            elif path.startswith("/gsplat/") and scene.kind == "splats":
                rel, root, allowed, cache = path[len("/gsplat/"):], GSPLAT_DIST, None, "public, max-age=3600"
            else:
                return self._error(HTTPStatus.NOT_FOUND, head)
            target = resolve_inside(root, rel, allowed)
            if target is None:
                return self._error(HTTPStatus.FORBIDDEN, head)
            gz = None
            if not target.is_file():  # X.raw answered from X.raw.gz, under the same containment rule
                gz = resolve_inside(root, rel + ".gz", allowed)
                if gz is None and (root / (rel + ".gz")).exists():
                    return self._error(HTTPStatus.FORBIDDEN, head)
            return self._file(target, gz, head, cache)

        def _file(self, target: Path, gz: Path | None, head: bool, cache: str):
            headers = {"Cache-Control": cache, "Accept-Ranges": "bytes"}
            name = target.name
            if not target.is_file():
                if gz is None or not gz.is_file():
                    return self._error(HTTPStatus.NOT_FOUND, head)
                target = gz
                headers["Content-Encoding"] = "gzip"
            ctype = mimetypes.guess_type(name)[0] or "application/octet-stream"
            if name.endswith((".js", ".mjs")):
                ctype = "text/javascript"
            try:
                f = open(target, "rb")
            except OSError:
                return self._error(HTTPStatus.NOT_FOUND, head)
            with f:
                size = f.seek(0, 2)
                rng = parse_range(self.headers.get("Range"), size)
                if rng == "unsatisfiable":
                    return self._error(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE, head, {"Content-Range": f"bytes */{size}"})
                first, last = rng if rng is not None else (0, size - 1)
                self.send_response(HTTPStatus.PARTIAL_CONTENT if rng is not None else HTTPStatus.OK)
                if rng is not None:
                    headers["Content-Range"] = f"bytes {first}-{last}/{size}"
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(last - first + 1))
                for k, v in headers.items():
                    self.send_header(k, v)
                self.end_headers()
                if head:
                    return
                f.seek(first)
                left = last - first + 1
                while left > 0:
                    chunk = f.read(min(CHUNK, left))
                    if not chunk:
                        break
                    self.wfile.write(chunk)
                    left -= len(chunk)

    return Handler


class PooledHTTPServer(ThreadingHTTPServer):
    """ThreadingHTTPServer with a fixed pool of worker threads instead of one new thread per connection."""

    daemon_threads = True

    def __init__(self, address, handler, workers: int = WORKERS):
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="nerfbake-view")
        super().__init__(address, handler)

    def process_request(self, request, client_address):
        self._pool.submit(self.process_request_thread, request, client_address)

    def server_close(self):
        super().server_close()
        self._pool.shutdown(wait=False, cancel_futures=True)


class ViewerServer:
    """A threaded HTTP server for one scene, started in the background (``with ViewerServer(...) as s: s.url``)."""

    def __init__(self, scene: str | Path | Scene, host: str = "127.0.0.1", port: int = 8000, workers: int = WORKERS,
                 static: Path = STATIC):
        """``static``: the viewer's page and scripts (another copy only for benchmarks/viewer_speed.py's baseline)."""
        self.scene = scene if isinstance(scene, Scene) else find_scene(scene)
        try:
            self.httpd = PooledHTTPServer((host, port), make_handler(self.scene, Path(static)), workers)
        except OSError as exc:
            raise SceneError(f"cannot listen on {host}:{port} ({exc.strerror or exc}); another program (or another "
                             f"nerfbake view) may hold the port: pass --port with a free one, or --port 0 for any") from exc
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
