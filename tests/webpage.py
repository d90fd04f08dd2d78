"""A loopback HTTP server for browser tests of the page's modules, and a tab opened on it.

``PageServer`` serves the page's files (``facewire.receiver``'s ``web/`` folder) at ``/NAME``
and any extra ``{path: (content type, bytes)}`` the test gives (a test page, a model), on
127.0.0.1 and a free port, from a thread; ``open_tab`` (``facewire.bench.chromium``'s,
re-exported) opens a URL in a ``DevTools`` Chromium and waits until ``ready`` (a JavaScript
expression) is true.
"""

from __future__ import annotations

import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any

from facewire.bench.chromium import open_tab

__all__ = ["PageServer", "open_tab", "web_dir"]

TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
         ".css": "text/css; charset=utf-8", ".vert": "text/plain; charset=utf-8",
         ".frag": "text/plain; charset=utf-8"}


def web_dir() -> Path:
    """The folder of the page's files as installed."""
    return Path(str(resources.files("facewire.receiver") / "web"))


class PageServer:
    """Serve the page's files and ``extra`` paths on loopback until ``close`` (or the with)."""

    def __init__(self, extra: dict[str, tuple[str, bytes]] | None = None) -> None:
        self.extra = dict(extra or {})
        folder = web_dir()
        extra_paths = self.extra

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                path = self.path.split("?", 1)[0]
                if path in extra_paths:
                    kind, body = extra_paths[path]
                else:
                    file = folder / path.lstrip("/")
                    if "/" in path.lstrip("/") or not file.is_file():
                        self.send_error(404)
                        return
                    kind, body = TYPES.get(file.suffix, "application/octet-stream"), \
                        file.read_bytes()
                self.send_response(200)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *_: Any) -> None:
                pass

        self._server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self._server.server_address[1]}"
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join()

    def __enter__(self) -> PageServer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
