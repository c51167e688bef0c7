"""``ms3d view WORKDIR``: serve a work dir's 3D Tiles output and the viewer page on localhost.

    /                 -> redirect to the viewer page
    /viewer/...       -> the repository's viewer/ folder (index.html, main.js)
    /node_modules/... -> viewer/node_modules (three, 3d-tiles-renderer, installed by ``npm ci`` in viewer/)
    /output/...       -> WORKDIR/output (tileset.json, content/, overview.glb, georef.json, and points/: the
                         thinned MLS points overlay, shown by the page's "MLS points" checkbox)

A 3D Tiles archive is served the same way, its entries read through its index
(:class:`storage.formats.threetz.ThreeTzReader`) under ``/output/``, so the page reads it unchanged: given a
``.3tz`` file (``ms3d view output/tileset.3tz``), or a work dir whose output is only ``tileset.3tz``.

The server binds 127.0.0.1 only and serves files read-only; nothing is fetched from the internet.
With ``label=True`` (``ms3d view WORKDIR --label``) it also mounts the labelling API of
:mod:`flows.label_server` under ``/api/`` (the only writes: ``WORKDIR/labels/user-<date>.csv``) and the page
opens in labelling mode; requests from anything but a loopback address are refused (403).
"""

from __future__ import annotations

import functools
import json
import posixpath
import sys
import threading
import urllib.parse
from dataclasses import dataclass
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from storage.errors import InputError
from storage.formats.threetz import ThreeTzReader
from storage.workdir.layout import WorkDir

VIEWER_DIR = Path(__file__).resolve().parents[1] / "viewer"
PAGE = "/viewer/index.html?tileset=/output/tileset.json"
LOOPBACK = ("127.0.0.1", "::1")
MAX_BODY = 4096  # bytes: a label is ~40


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):  # one line, never a traceback
        print(f"ms3d viewer: request from {client_address[0]} failed: {sys.exc_info()[1]}", file=sys.stderr, flush=True)


class _Handler(SimpleHTTPRequestHandler):
    extensions_map = {  # noqa: RUF012 (the base class's own attribute, overridden)
        **SimpleHTTPRequestHandler.extensions_map,
        ".js": "text/javascript", ".mjs": "text/javascript", ".wasm": "application/wasm",
        ".glb": "model/gltf-binary", ".json": "application/json", ".subtree": "application/octet-stream",
    }  # fmt: skip

    def __init__(self, *args, roots: dict[str, Path], api=None, **kwargs):
        self.roots = roots
        self.api = api
        super().__init__(*args, directory=str(roots["viewer"]), **kwargs)

    def _loopback(self) -> bool:
        if self.client_address[0] in LOOPBACK:
            return True
        self.send_error(403, "loopback clients only")
        return False

    def _api(self, method: str) -> None:
        """A labelling API request: JSON in, JSON out; a failure is one line in the log, never a traceback."""
        try:
            n = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            n = -1
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0].strip("[]")
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if host not in ("127.0.0.1", "localhost", "::1"):  # a page of another site (DNS rebinding) may not call
            status, doc = 403, {"error": f"Host {host or '(none)'} is not this loopback server"}
        elif method == "POST" and ctype != "application/json":  # no cross-site 'simple' POST: JSON only
            status, doc = 415, {"error": "Content-Type must be application/json"}
        elif n < 0:
            status, doc = 400, {"error": "bad Content-Length"}
        elif n > MAX_BODY:
            status, doc = 413, {"error": f"body over {MAX_BODY} bytes"}
        elif self.api is None:
            status, doc = 404, {"error": "labelling is off: start the viewer with --label"}
        else:
            try:
                status, doc = self.api.handle(method, self.path, self.rfile.read(n) if n else b"")
            except Exception as exc:  # noqa: BLE001 - the server keeps serving; the log gets one line
                status, doc = 500, {"error": f"{type(exc).__name__}: {exc}"}
        if status >= 400:
            print(f"ms3d viewer: {status} {method} {urllib.parse.urlsplit(self.path).path}: {doc['error']}",
                  file=sys.stderr, flush=True)
        data = json.dumps(doc).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def do_POST(self):
        if not self._loopback():
            return
        if urllib.parse.urlsplit(self.path).path.startswith("/api/"):
            self._api("POST")
        else:
            self.send_error(405, "read-only")

    def do_HEAD(self):
        if self._loopback() and not self._from_archive(head=True):
            super().do_HEAD()

    def _from_archive(self, head: bool) -> bool:
        """Serve an ``/output/...`` request from the archive when the output is one; False otherwise."""
        archive = self.roots["output"]
        path = posixpath.normpath(urllib.parse.unquote(urllib.parse.urlsplit(self.path).path))
        parts = [p for p in path.split("/") if p and p not in (".", "..")]
        if not isinstance(archive, ThreeTzReader) or not parts or parts[0] != "output":
            return False
        name = "/".join(parts[1:])
        found = archive.open_entry(name) if name else None
        if found is None:
            self.send_error(404, "not in the archive")
            return True
        size, chunks = found
        self.send_response(200)
        self.send_header("Content-Type", self.guess_type(name))
        self.send_header("Content-Length", str(size))
        self.end_headers()
        if not head:
            for chunk in chunks:
                self.wfile.write(chunk)
        return True

    def translate_path(self, path: str) -> str:
        path = posixpath.normpath(urllib.parse.unquote(urllib.parse.urlsplit(path).path))
        parts = [p for p in path.split("/") if p and p not in (".", "..")]
        if not parts or parts[0] not in self.roots:
            return str(self.roots["viewer"] / "__missing__")
        return str(self.roots[parts[0]].joinpath(*parts[1:]))

    def do_GET(self):
        if not self._loopback():
            return
        path = urllib.parse.urlsplit(self.path).path
        if path.startswith("/api/"):
            self._api("GET")
            return
        if path in ("", "/"):
            self.send_response(302)
            self.send_header("Location", PAGE + ("&label=1" if self.api is not None else ""))
            self.end_headers()
            return
        if not self._from_archive(head=False):
            super().do_GET()

    def end_headers(self):
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, fmt, *args):  # quiet: the terminal shows the URL, not every request
        pass


@dataclass
class ViewerServer:
    """A running viewer server; ``url`` opens the viewer page. ``stop()`` shuts it down."""

    httpd: ThreadingHTTPServer
    thread: threading.Thread | None
    label: bool = False

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host}:{port}{PAGE}" + ("&label=1" if self.label else "")

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        if self.thread is not None:
            self.thread.join(timeout=5)


def _roots(source: str | Path) -> dict[str, Path | ThreeTzReader]:
    """What the server serves: the viewer, its packages, and the output (a folder, or a 3D Tiles archive when
    ``source`` is a ``.3tz`` file or a work dir whose output holds only ``tileset.3tz``)."""
    src = Path(source).absolute()
    wd = WorkDir(src)
    if src.suffix == ".3tz" or (not wd.tileset_json.is_file() and wd.tileset_3tz.is_file()):
        archive = src if src.suffix == ".3tz" else wd.tileset_3tz
        if not archive.is_file():
            raise InputError(archive, "no such 3D Tiles archive")
        output = ThreeTzReader(archive)
        if "tileset.json" not in output:
            raise InputError(archive, "the archive holds no tileset.json")
    else:
        output = wd.output_dir
        if not (output / "tileset.json").is_file():
            raise InputError(output, "no tileset.json: run the pipeline (export stage) first")
    modules = VIEWER_DIR / "node_modules"
    if not (modules / "three").is_dir() or not (modules / "3d-tiles-renderer").is_dir():
        raise InputError(modules, "viewer packages missing: run `npm ci --prefix viewer` (make install does)")
    return {"viewer": VIEWER_DIR, "node_modules": modules, "output": output}


def _httpd(work_dir: str | Path, port: int, label: bool) -> ThreadingHTTPServer:
    api = None
    if label:
        if Path(work_dir).suffix == ".3tz":
            raise InputError(work_dir, "labelling needs the work dir, not an archive")
        from flows.label_server import LabelApi

        api = LabelApi(Path(work_dir).absolute())
    return _Server(("127.0.0.1", port), functools.partial(_Handler, roots=_roots(work_dir), api=api))


def start_viewer(work_dir: str | Path, port: int = 0, label: bool = False) -> ViewerServer:
    """Serve in a background thread (port 0 = any free port); returns the running server. work_dir: a work dir
    or a ``.3tz`` archive (module docstring). label: mount the labelling API (:mod:`flows.label_server`) and
    open the page in labelling mode."""
    httpd = _httpd(work_dir, port, label)
    thread = threading.Thread(target=httpd.serve_forever, name="ms3d-viewer", daemon=True)
    thread.start()
    return ViewerServer(httpd, thread, label)


def serve_viewer(work_dir: str | Path, port: int = 8765, label: bool = False) -> None:
    """Serve until interrupted (Ctrl-C); prints the viewer's URL (``label``: as :func:`start_viewer`)."""
    httpd = _httpd(work_dir, port, label)
    server = ViewerServer(httpd, None, label)
    print(f"ms3d viewer: {server.url}  (Ctrl-C to stop)", flush=True)
    try:
        httpd.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        httpd.server_close()
