"""``ms3d view WORKDIR``: serve a work dir's 3D Tiles output and the viewer page on localhost.

    /                 -> redirect to the viewer page
    /viewer/...       -> the repository's viewer/ folder (index.html, main.js)
    /node_modules/... -> viewer/node_modules (three, 3d-tiles-renderer, installed by ``npm ci`` in viewer/)
    /output/...       -> WORKDIR/output (tileset.json, content/, overview.glb, georef.json, and points/: the
                         thinned MLS points overlay, shown by the page's "MLS points" checkbox)

The server binds 127.0.0.1 only and serves files read-only; nothing is fetched from the internet.
"""

from __future__ import annotations

import functools
import posixpath
import threading
import urllib.parse
from dataclasses import dataclass
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from storage.errors import InputError

VIEWER_DIR = Path(__file__).resolve().parents[1] / "viewer"


class _Handler(SimpleHTTPRequestHandler):
    extensions_map = {  # noqa: RUF012 (the base class's own attribute, overridden)
        **SimpleHTTPRequestHandler.extensions_map,
        ".js": "text/javascript", ".mjs": "text/javascript", ".wasm": "application/wasm",
        ".glb": "model/gltf-binary", ".json": "application/json",
    }  # fmt: skip

    def __init__(self, *args, roots: dict[str, Path], **kwargs):
        self.roots = roots
        super().__init__(*args, directory=str(roots["viewer"]), **kwargs)

    def translate_path(self, path: str) -> str:
        path = posixpath.normpath(urllib.parse.unquote(urllib.parse.urlsplit(path).path))
        parts = [p for p in path.split("/") if p and p not in (".", "..")]
        if not parts or parts[0] not in self.roots:
            return str(self.roots["viewer"] / "__missing__")
        return str(self.roots[parts[0]].joinpath(*parts[1:]))

    def do_GET(self):
        if urllib.parse.urlsplit(self.path).path in ("", "/"):
            self.send_response(302)
            self.send_header("Location", "/viewer/index.html?tileset=/output/tileset.json")
            self.end_headers()
            return
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

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host}:{port}/viewer/index.html?tileset=/output/tileset.json"

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        if self.thread is not None:
            self.thread.join(timeout=5)


def _roots(work_dir: str | Path) -> dict[str, Path]:
    output = Path(work_dir).absolute() / "output"
    if not (output / "tileset.json").is_file():
        raise InputError(output, "no tileset.json: run the pipeline (export stage) first")
    modules = VIEWER_DIR / "node_modules"
    if not (modules / "three").is_dir() or not (modules / "3d-tiles-renderer").is_dir():
        raise InputError(modules, "viewer packages missing: run `npm ci --prefix viewer` (make install does)")
    return {"viewer": VIEWER_DIR, "node_modules": modules, "output": output}


def start_viewer(work_dir: str | Path, port: int = 0) -> ViewerServer:
    """Serve in a background thread (port 0 = any free port); returns the running server."""
    handler = functools.partial(_Handler, roots=_roots(work_dir))
    httpd = ThreadingHTTPServer(("127.0.0.1", port), handler)
    thread = threading.Thread(target=httpd.serve_forever, name="ms3d-viewer", daemon=True)
    thread.start()
    return ViewerServer(httpd, thread)


def serve_viewer(work_dir: str | Path, port: int = 8765) -> None:
    """Serve until interrupted (Ctrl-C); prints the viewer's URL."""
    handler = functools.partial(_Handler, roots=_roots(work_dir))
    httpd = ThreadingHTTPServer(("127.0.0.1", port), handler)
    server = ViewerServer(httpd, None)
    print(f"ms3d viewer: {server.url}  (Ctrl-C to stop)", flush=True)
    try:
        httpd.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        httpd.server_close()
