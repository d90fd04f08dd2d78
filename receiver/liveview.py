"""The live view: a local web page showing the rendered stream and the receiver's statistics.

``facewire receive --view`` serves it with the standard library (``http.server``, one thread
per connection, the server loop on a daemon thread); a browser on the same host opens
``LiveView.url``. The render loop hands over each frame with ``publish``, which only copies
the frame and wakes the waiting connections (0.3 ms median at 640 x 480, with or without
browsers watching, on the 2-core test machine); it never encodes, never waits for a browser
and never blocks on the network.

Endpoints (HTTP/1.0, one request per connection; a query string is ignored)
---------------------------------------------------------------------------
``/``            the page: the stream in an ``<img>`` and a statistics panel that polls
                 ``/stats.json`` four times a second. The headline numbers are the stats keys
                 ``HEADLINE`` names (fps, kbit/s, loss, latency); every other key is listed
                 below them as it is. Values are written with ``textContent`` (never parsed
                 as HTML).
``/stream.mjpg`` ``multipart/x-mixed-replace; boundary=frame`` (MJPEG): each part is
                 ``Content-Type: image/jpeg``, ``Content-Length: n``, a blank line, the JPEG
                 and CRLF, and the next ``--frame`` boundary follows each JPEG at once (a
                 browser shows a part when it sees the boundary after it). Each connection
                 waits on a ``threading.Condition`` for a frame newer than the one it sent
                 last, so a slow browser skips frames instead of queueing them and an idle
                 one costs nothing.
``/frame.jpg``   the latest frame as one JPEG (503 before the first frame).
``/stats.json``  ``{"frame": n, "age_s": s, "stats": {...}}``: the number of frames
                 published, the seconds since the last of them, and the latest stats.

JPEG. A frame is encoded (RGB to BGR, ``cv2.imencode`` at quality ``JPEG_QUALITY`` = 80) at
most once, lazily, by the first connection that needs it, on that connection's thread
(OpenCV releases the GIL, so on two cores it runs beside the render loop); with no browser
watching nothing is encoded. 640 x 480 frames of a real face take 1.1 ms and about 20 kB
(a 30 Hz stream is about 5 Mbit/s on loopback).

Stats. A flat dict of str keys; values are numbers, strings, booleans or None (numpy scalars
are converted). Non-finite floats (NaN while a number is unknown) are sent as null, shown as
a dash.

Binding and safety. The page carries the face stream unencrypted and without any
authentication, so it binds to ``127.0.0.1`` by default and refuses any host that is not a
loopback address (127.0.0.0/8, ::1, localhost) unless ``allow_remote=True`` is passed
explicitly (then anyone who can reach the port can watch). On loopback it also answers only
requests whose ``Host`` header names a loopback host (403 otherwise), so a web page that
rebinds its own domain name to 127.0.0.1 cannot read the stream (``protocol.loopback``). A
port already in use is a ``LiveViewError`` naming it.

Shutdown. ``close`` (or leaving the ``with`` block) stops the server loop, wakes every
connection waiting for a frame, shuts the open connections' sockets down (a browser still
reading the stream sees the end of it), waits up to ``CLOSE_WAIT_S`` for their threads to
finish and closes the listening socket. Publishing after ``close`` raises ``ValueError``.
"""

from __future__ import annotations

import errno
import json
import math
import numbers
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Self
from urllib.parse import urlsplit

import cv2
import numpy as np

from facewire.protocol.errors import FacewireError
from facewire.protocol.loopback import host_header_is_loopback, is_loopback

JPEG_QUALITY = 80
BOUNDARY = "frame"
CLOSE_WAIT_S = 5.0
SOCKET_TIMEOUT_S = 10.0  # a connection that neither sends a request nor reads is dropped
# Stats keys the page shows as headline numbers: key, label, decimals, unit.
HEADLINE = (("fps", "fps", 1, ""), ("kbps", "bitrate", 1, " kbit/s"),
            ("loss_pct", "loss", 1, " %"), ("latency_ms", "latency", 0, " ms"))


class LiveViewError(FacewireError, OSError):
    """The live view cannot be served (port in use, host refused); the message says why."""


class LiveView:
    """A local web page of the rendered stream and statistics.

    Use as a context manager::

        with LiveView() as view:          # any free port on 127.0.0.1
            print("open", view.url)
            for ...:
                view.publish(rgb, {"fps": 29.8, "kbps": 9.6, "loss_pct": 0.0, "latency_ms": 112})

    Args:
        port: TCP port, 0 for any free one (``url`` tells which).
        host: address to bind, a loopback address unless ``allow_remote``.
        allow_remote: allow a non-loopback ``host`` (the stream is then open to anyone who
            can reach the port: no encryption, no authentication).

    Raises:
        LiveViewError: the host is not loopback and ``allow_remote`` is not set, or the
            address cannot be bound (the port is in use, the host is not this machine's).
        ValueError: ``port`` is not an int in [0, 65535] or ``host`` is empty.
    """

    def __init__(self, port: int = 0, host: str = "127.0.0.1", allow_remote: bool = False) -> None:
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"port: expected an int in [0, 65535], got {port!r}")
        if not isinstance(host, str) or not host:
            raise ValueError(f"host: expected a host name or address, got {host!r}")
        self.loopback_only = not allow_remote
        if self.loopback_only and not is_loopback(host):
            raise LiveViewError(
                f"live view: refusing to serve on {host}: the page shows the face stream "
                f"unencrypted and without authentication, so it binds to 127.0.0.1 only "
                f"(pass allow_remote=True to serve on another address)")
        self._cond = threading.Condition()
        self._closed = False
        self._seq = 0  # frames published; the latest is number _seq
        self._rgb: np.ndarray | None = None
        self._published_at = time.monotonic()
        self._stats_json = "{}"
        self._encode_lock = threading.Lock()
        self._jpeg_seq = 0
        self._jpeg = b""
        self._connections: set[socket.socket] = set()

        server_class = _Server6 if ":" in host else _Server
        try:
            self._server = server_class((host, port), _Handler)
        except OSError as exc:
            raise LiveViewError(f"live view: cannot serve on {host} port {port}: "
                                f"{_bind_reason(exc, port)}") from exc
        self._server.view = self
        self.host = host
        self.port = int(self._server.server_address[1])
        self._thread = threading.Thread(target=self._server.serve_forever, name="liveview",
                                        kwargs={"poll_interval": 0.1}, daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """The page's address, e.g. ``http://127.0.0.1:8000/``."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def publish(self, rgb: np.ndarray | None, stats: dict[str, Any]) -> None:
        """Make a frame and statistics the latest ones; returns at once.

        Args:
            rgb: (H, W, 3) uint8 RGB image (copied: the caller may reuse its buffer), or None
                to update the statistics only (e.g. while waiting for a sender).
            stats: flat dict of str keys to numbers, strings, booleans or None; the keys in
                ``HEADLINE`` are the page's headline numbers.

        Raises:
            ValueError: a wrong image shape or dtype, or a closed view.
            TypeError: ``stats`` is not such a dict.
        """
        if rgb is not None:
            if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 \
                    or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
                raise ValueError(f"rgb: expected an (H, W, 3) uint8 array, got "
                                 f"{_describe(rgb)}")
            rgb = np.array(rgb, order="C", copy=True)
        text = json.dumps(_plain_stats(stats), allow_nan=False)
        with self._cond:
            if self._closed:
                raise ValueError("publish: the live view is closed")
            if rgb is not None:
                self._rgb = rgb
                self._seq += 1
                self._published_at = time.monotonic()
            self._stats_json = text
            self._cond.notify_all()

    def close(self) -> None:
        """Stop serving and release every connection (see the module docstring); idempotent."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self._server.shutdown()
        with self._cond:
            for sock in self._connections:
                _shut(sock)
            self._cond.wait_for(lambda: not self._connections, timeout=CLOSE_WAIT_S)
        self._server.server_close()
        self._thread.join(CLOSE_WAIT_S)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- used by the connection threads ---

    def _track(self, sock: socket.socket, open_: bool) -> None:
        with self._cond:
            if open_ and self._closed:  # accepted just before close: release it at once
                _shut(sock)
            if open_:
                self._connections.add(sock)
            else:
                self._connections.discard(sock)
            self._cond.notify_all()

    def _next_frame(self, after: int) -> tuple[int, bytes] | None:
        """Wait for a frame newer than number ``after``: (number, JPEG), or None once closed."""
        with self._cond:
            self._cond.wait_for(lambda: self._closed or self._seq > after)
            if self._closed:
                return None
        return self._latest_jpeg()

    def _latest_jpeg(self) -> tuple[int, bytes]:
        """The latest frame as (number, JPEG), encoded at most once per frame; (0, b"")
        before the first."""
        with self._cond:
            seq, rgb = self._seq, self._rgb
        with self._encode_lock:
            if seq > self._jpeg_seq:  # an older frame is never cached over a newer one
                assert rgb is not None  # seq > 0: a frame was published
                ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                                       [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
                if not ok:
                    raise RuntimeError(f"JPEG encoding of a {rgb.shape} frame failed")
                self._jpeg_seq, self._jpeg = seq, buf.tobytes()
            return self._jpeg_seq, self._jpeg

    def _stats_body(self) -> bytes:
        with self._cond:
            return (f'{{"frame": {self._seq}, '
                    f'"age_s": {time.monotonic() - self._published_at:.3f}, '
                    f'"stats": {self._stats_json}}}').encode()

    def _host_allowed(self, header: str | None) -> bool:
        """The request's Host header names a loopback host (always true with allow_remote)."""
        return not self.loopback_only or host_header_is_loopback(header)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    block_on_close = False  # LiveView.close waits for the connections itself
    view: LiveView


class _Server6(_Server):
    address_family = socket.AF_INET6


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    timeout = SOCKET_TIMEOUT_S
    server_version = "facewire-liveview"

    def setup(self) -> None:
        super().setup()
        self.server.view._track(self.connection, True)

    def finish(self) -> None:
        try:
            super().finish()
        except OSError:
            pass  # the peer went away before the last bytes were flushed
        finally:
            self.server.view._track(self.connection, False)

    def log_message(self, format: str, *args: Any) -> None:
        """Silent: the receiver's status line owns the terminal."""

    def do_GET(self) -> None:
        view = self.server.view
        if not view._host_allowed(self.headers.get("Host")):
            self._send(HTTPStatus.FORBIDDEN, "text/plain; charset=utf-8",
                       b"the live view answers only requests to a loopback host\n")
            return
        path = urlsplit(self.path).path
        try:
            if path == "/":
                self._send(HTTPStatus.OK, "text/html; charset=utf-8", _PAGE)
            elif path == "/stats.json":
                self._send(HTTPStatus.OK, "application/json", view._stats_body())
            elif path == "/frame.jpg":
                seq, jpeg = view._latest_jpeg()
                if seq == 0:
                    self._send(HTTPStatus.SERVICE_UNAVAILABLE, "text/plain; charset=utf-8",
                               b"no frame published yet\n")
                else:
                    self._send(HTTPStatus.OK, "image/jpeg", jpeg)
            elif path == "/stream.mjpg":
                self._stream(view)
            else:
                self._send(HTTPStatus.NOT_FOUND, "text/plain; charset=utf-8",
                           b"not found: try /, /stream.mjpg, /frame.jpg or /stats.json\n")
        except (ConnectionError, TimeoutError):
            pass  # the browser closed the page or stopped reading

    def _send(self, status: HTTPStatus, content_type: str, body: bytes) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _stream(self, view: LiveView) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(f"--{BOUNDARY}\r\n".encode())
        sent = 0
        while (frame := view._next_frame(sent)) is not None:
            sent, jpeg = frame
            self.wfile.write(f"Content-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n"
                             .encode() + jpeg + f"\r\n--{BOUNDARY}\r\n".encode())
            self.wfile.flush()


def _shut(sock: socket.socket) -> None:
    """End a connection both ways: a thread blocked reading or writing it returns."""
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass  # the peer already closed it


def _bind_reason(exc: OSError, port: int) -> str:
    if exc.errno == errno.EADDRINUSE:
        return (f"port {port} is already in use (another receiver or program listens on it); "
                f"choose another port, or 0 for any free one")
    if exc.errno == errno.EADDRNOTAVAIL:
        return "that address is not one of this machine's"
    return str(exc)


def _plain_stats(stats: dict[str, Any]) -> dict[str, Any]:
    """``stats`` with numpy scalars as Python numbers and non-finite floats as None."""
    if not isinstance(stats, dict):
        raise TypeError(f"stats: expected a dict, got {type(stats).__name__}")
    plain: dict[str, Any] = {}
    for key, value in stats.items():
        if not isinstance(key, str):
            raise TypeError(f"stats: keys must be str, got {key!r}")
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        elif not (value is None or isinstance(value, (str, bool, numbers.Integral, float))):
            raise TypeError(f"stats[{key!r}]: expected a number, string, bool or None, got "
                             f"{type(value).__name__}")
        plain[key] = value
    return plain


def _describe(value: object) -> str:
    if isinstance(value, np.ndarray):
        return f"{value.dtype} array of shape {value.shape}"
    return type(value).__name__


_PAGE_TEMPLATE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>facewire live view</title>
<style>
  body { margin: 0; background: #111; color: #ddd; font: 15px system-ui, sans-serif; }
  main { display: flex; flex-wrap: wrap; gap: 16px; padding: 16px; align-items: flex-start; }
  #stream { max-width: 100%; background: #000; min-width: 320px; min-height: 240px; }
  #panel { min-width: 220px; }
  .headline { display: grid; grid-template-columns: auto auto; gap: 4px 16px; }
  .headline .value { font-size: 22px; font-variant-numeric: tabular-nums; text-align: right; }
  .label { color: #999; }
  table { margin-top: 12px; border-collapse: collapse; font-variant-numeric: tabular-nums; }
  td { padding: 1px 8px 1px 0; }
  #status { margin-top: 12px; color: #999; }
</style>
</head>
<body>
<main>
  <img id="stream" src="/stream.mjpg" alt="rendered face stream">
  <section id="panel">
    <div class="headline">%HEADLINE%</div>
    <table id="more"></table>
    <p id="status">connecting...</p>
  </section>
</main>
<script>
"use strict";
const HEADLINE = %HEADLINE_JSON%;
const headlineKeys = new Set(HEADLINE.map(h => h[0]));
function show(value, decimals, unit) {
  if (value === null || value === undefined) return "\\u2013";
  if (typeof value === "number") return value.toFixed(decimals) + unit;
  return String(value) + unit;
}
function fillTable(stats) {
  const table = document.getElementById("more");
  const rows = [];
  for (const [key, value] of Object.entries(stats)) {
    if (headlineKeys.has(key)) continue;
    const row = document.createElement("tr");
    const name = document.createElement("td");
    const cell = document.createElement("td");
    name.className = "label";
    name.textContent = key;
    cell.dataset.stat = key;
    cell.textContent = typeof value === "number" && !Number.isInteger(value)
      ? value.toFixed(2) : show(value, 0, "");
    row.append(name, cell);
    rows.push(row);
  }
  table.replaceChildren(...rows);
}
async function poll() {
  const status = document.getElementById("status");
  try {
    const response = await fetch("/stats.json", {cache: "no-store"});
    const data = await response.json();
    for (const [key, , decimals, unit] of HEADLINE) {
      document.getElementById("stat-" + key).textContent = show(data.stats[key], decimals, unit);
    }
    fillTable(data.stats);
    status.textContent = data.frame === 0 ? "waiting for the first frame"
      : "frame " + data.frame + (data.age_s > 1 ? " (no new frame for "
        + data.age_s.toFixed(0) + " s)" : "");
  } catch (error) {
    status.textContent = "the receiver is not answering";
  }
  setTimeout(poll, 250);
}
const stream = document.getElementById("stream");
stream.addEventListener("error", () => {
  setTimeout(() => { stream.src = "/stream.mjpg?" + Date.now(); }, 1000);
});
poll();
</script>
</body>
</html>
"""


_PAGE = (_PAGE_TEMPLATE
         .replace("%HEADLINE%", "".join(
             f'<span class="label">{label}</span>'
             f'<span class="value" id="stat-{key}" data-stat="{key}">\u2013</span>'
             for key, label, _, _ in HEADLINE))
         .replace("%HEADLINE_JSON%", json.dumps(HEADLINE))).encode()
