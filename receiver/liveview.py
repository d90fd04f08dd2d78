"""The live view: a local web page showing the rendered stream and the receiver's statistics.

``facewire receive --view`` serves it from one thread of its own, an asyncio event loop
(every connection is a task of that loop, none has a thread); a browser on the same host
opens ``LiveView.url``. The render loop hands over each frame with ``publish``, which only
copies the frame and wakes the loop; it never encodes, never waits for a browser and never
blocks on the network.

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
                 waits for a frame newer than the one it sent last, and for what it sent to
                 be taken by the kernel, so a slow browser skips frames instead of queueing
                 them and an idle one costs nothing; one that has gone (end of stream or
                 reset) is dropped at once, frame or no frame.
``/frame.jpg``   the latest frame as one JPEG (503 before the first frame).
``/stats.json``  ``{"frame": n, "age_s": s, "stats": {...}}``: the number of frames
                 published, the seconds since the last of them, and the latest stats.

JPEG. A frame is encoded (RGB to BGR, ``cv2.imencode`` at quality ``JPEG_QUALITY`` = 80) at
most once, lazily, on the loop's thread, by the first connection that needs it (OpenCV
releases the GIL, so on two cores it runs beside the render loop); with no browser watching
nothing is encoded.

Stats. A flat dict of str keys; values are numbers, strings, booleans or None (numpy scalars
are converted). Non-finite floats (NaN while a number is unknown) are sent as null, shown as
a dash.

Bounds (nobody is authenticated here). A request's head (request line and headers) is at
most ``MAX_HEAD_BYTES`` and ``MAX_HEADERS`` headers, read within ``HEAD_TIMEOUT_S`` in all
(400, 431 or the connection closed otherwise); only ``GET`` is answered (405). Connections
are admitted by ``serverguard.Admission``: at most ``MAX_PENDING`` reading their request
(the oldest evicted after ``EVICT_AFTER_S`` when more come) and ``MAX_CONNECTIONS`` in all,
below the open-files limit (``serverguard.open_file_caps``); a browser that takes nothing
for ``WRITE_TIMEOUT_S`` is cut off. A peer that resets mid-request ends its task quietly;
errors the loop reports are one line per ``ERROR_EVERY_S`` on stderr
(``serverguard.QuietErrors``), never a traceback.

Binding and safety. The page carries the face stream unencrypted and without any
authentication, so it binds to ``127.0.0.1`` by default and refuses any host that is not a
loopback address (127.0.0.0/8, ::1, localhost) unless ``allow_remote=True`` is passed
explicitly (then anyone who can reach the port can watch). On loopback it also answers only
requests whose ``Host`` header names a loopback host (403 otherwise; 400 for two of them),
so a web page that rebinds its own domain name to 127.0.0.1 cannot read the stream
(``protocol.loopback``). A port already in use is a ``LiveViewError`` naming it.

Shutdown. ``close`` (or leaving the ``with`` block) stops listening, ends every stream and
closes every connection (each sends what it holds, then the end of the stream: a browser
still reading sees it), waits up to ``CLOSE_WAIT_S`` for them (aborting the rest) and stops
the loop's thread. Publishing after ``close`` raises ``ValueError``.
"""

from __future__ import annotations

import asyncio
import errno
import json
import math
import numbers
import socket
import sys
import threading
import time
from http import HTTPStatus
from typing import Any, Self
from urllib.parse import urlsplit

import cv2
import numpy as np

from facewire.protocol.errors import FacewireError
from facewire.protocol.loopback import host_header_is_loopback, is_loopback
from facewire.receiver.serverguard import Admission, QuietErrors, open_file_caps

JPEG_QUALITY = 80
BOUNDARY = "frame"
CLOSE_WAIT_S = 5.0
MAX_HEAD_BYTES = 16 * 1024
MAX_HEADERS = 32
HEAD_TIMEOUT_S = 5.0
WRITE_TIMEOUT_S = 10.0  # a browser that takes nothing this long is cut off
MAX_CONNECTIONS = 64
MAX_PENDING = 16
EVICT_AFTER_S = 0.25
ERROR_EVERY_S = 10.0
# Stats keys the page shows as headline numbers: key, label, decimals, unit.
HEADLINE = (("fps", "fps", 1, ""), ("kbps", "bitrate", 1, " kbit/s"),
            ("loss_pct", "loss", 1, " %"), ("latency_ms", "latency", 0, " ms"))


class LiveViewError(FacewireError, OSError):
    """The live view cannot be served (port in use, host refused); the message says why."""


class _BadRequest(Exception):
    """A request refused before it is routed: its status and text."""

    def __init__(self, status: HTTPStatus, text: str) -> None:
        super().__init__(text)
        self.status = status


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
        self._lock = threading.Lock()  # the frame and stats, shared with publish
        self._closed = False
        self._seq = 0  # frames published; the latest is number _seq
        self._rgb: np.ndarray | None = None
        self._published_at = time.monotonic()
        self._stats_json = "{}"
        self._jpeg_seq = 0  # the loop's thread only, as every field below
        self._jpeg = b""
        total, backlog = open_file_caps(MAX_CONNECTIONS)
        self._admission = Admission(total, MAX_PENDING, EVICT_AFTER_S)
        self._tasks: set[asyncio.Task[None]] = set()
        self._wake: asyncio.Event | None = None
        self._stopping = False

        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        try:
            self._listener = socket.create_server((host, port), family=family, backlog=backlog)
        except OSError as exc:
            raise LiveViewError(f"live view: cannot serve on {host} port {port}: "
                                f"{_bind_reason(exc, port)}") from exc
        self.host = host
        self.port = int(self._listener.getsockname()[1])
        self._loop = asyncio.new_event_loop()
        self._loop.set_exception_handler(QuietErrors(_say, "live view", ERROR_EVERY_S))
        self._thread = threading.Thread(target=self._loop.run_forever, name="liveview",
                                        daemon=True)
        self._thread.start()
        self._server = asyncio.run_coroutine_threadsafe(self._start(), self._loop).result()

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
        with self._lock:
            if self._closed:
                raise ValueError("publish: the live view is closed")
            if rgb is not None:
                self._rgb = rgb
                self._seq += 1
                self._published_at = time.monotonic()
            self._stats_json = text
            if rgb is not None:
                self._loop.call_soon_threadsafe(self._woken)

    def show(self, rgb: np.ndarray, stats: dict[str, Any]) -> None:
        """``publish`` for ``receiver.receiver.receive``'s ``view``: its live statistics with
        ``loss_pct``, the share of played slots whose packet was lost."""
        played = stats["received"] + stats["lost"]
        self.publish(rgb, {**stats, "loss_pct": 100 * stats["lost"] / played if played
                           else None})

    def close(self) -> None:
        """Stop serving and release every connection (see the module docstring); idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        done = asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop)
        try:
            done.result(CLOSE_WAIT_S + 1.0)
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(CLOSE_WAIT_S)
            if not self._thread.is_alive():
                self._loop.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the loop's thread ---

    async def _start(self) -> asyncio.Server:
        self._wake = asyncio.Event()
        return await asyncio.start_server(self._client, sock=self._listener,
                                          limit=MAX_HEAD_BYTES)

    def _woken(self) -> None:
        """A frame was published: wake the streams waiting for one."""
        assert self._wake is not None
        self._wake.set()
        self._wake = asyncio.Event()

    async def _shutdown(self) -> None:
        self._stopping = True
        self._server.close()
        self._woken()
        self._admission.close_all()
        if self._tasks:
            _, late = await asyncio.wait(set(self._tasks), timeout=CLOSE_WAIT_S)
            for task in late:
                task.cancel()
            if late:
                await asyncio.wait(late)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One connection: its request read within the bounds, answered (module docstring)."""
        transport = writer.transport
        task = asyncio.current_task()
        if self._stopping or not self._admission.admit(transport):
            transport.abort()
            return
        assert task is not None
        self._tasks.add(task)
        try:
            try:
                path = await asyncio.wait_for(self._request(reader), HEAD_TIMEOUT_S)
            except _BadRequest as bad:
                await _respond(writer, bad.status, "text/plain; charset=utf-8",
                               f"{bad}\n".encode())
                return
            await self._route(path, reader, writer)
        except (ConnectionError, TimeoutError, asyncio.IncompleteReadError,
                asyncio.LimitOverrunError):
            transport.abort()  # gone, too slow or too long: nothing more is said
        finally:
            self._admission.release(transport)
            self._tasks.discard(task)
            transport.close()
            self._admission.tidy()

    async def _request(self, reader: asyncio.StreamReader) -> str:
        """The path of a GET whose head is within the bounds (module docstring).

        Raises:
            _BadRequest: a malformed or refused request.
            asyncio.LimitOverrunError, asyncio.IncompleteReadError: a head too long, or cut.
        """
        try:
            head = await reader.readuntil(b"\r\n\r\n")
        except asyncio.LimitOverrunError:
            raise _BadRequest(HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE,
                              f"the request's head is over {MAX_HEAD_BYTES} bytes") from None
        lines = head.decode("latin-1").split("\r\n")[:-2]
        parts = lines[0].split(" ")
        if len(parts) != 3 or not parts[2].startswith("HTTP/"):
            raise _BadRequest(HTTPStatus.BAD_REQUEST, "expected GET PATH HTTP/1.x")
        if len(lines) - 1 > MAX_HEADERS:
            raise _BadRequest(HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE,
                              f"over {MAX_HEADERS} headers")
        hosts = [line.partition(":")[2].strip() for line in lines[1:]
                 if line.partition(":")[0].strip().lower() == "host"]
        if parts[0] != "GET":
            raise _BadRequest(HTTPStatus.METHOD_NOT_ALLOWED, "only GET is answered")
        if len(hosts) > 1:
            raise _BadRequest(HTTPStatus.BAD_REQUEST, "one Host header, please")
        if self.loopback_only and not host_header_is_loopback(hosts[0] if hosts else None):
            raise _BadRequest(HTTPStatus.FORBIDDEN,
                              "the live view answers only requests to a loopback host")
        return urlsplit(parts[1]).path

    async def _route(self, path: str, reader: asyncio.StreamReader,
                     writer: asyncio.StreamWriter) -> None:
        if path == "/":
            await _respond(writer, HTTPStatus.OK, "text/html; charset=utf-8", _PAGE)
        elif path == "/stats.json":
            await _respond(writer, HTTPStatus.OK, "application/json", self._stats_body())
        elif path == "/frame.jpg":
            seq, jpeg = self._latest_jpeg()
            if seq == 0:
                await _respond(writer, HTTPStatus.SERVICE_UNAVAILABLE,
                               "text/plain; charset=utf-8", b"no frame published yet\n")
            else:
                await _respond(writer, HTTPStatus.OK, "image/jpeg", jpeg)
        elif path == "/stream.mjpg":
            self._admission.promote(writer.transport)
            await self._stream(reader, writer)
        else:
            await _respond(writer, HTTPStatus.NOT_FOUND, "text/plain; charset=utf-8",
                           b"not found: try /, /stream.mjpg, /frame.jpg or /stats.json\n")

    async def _stream(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """``/stream.mjpg`` until the browser goes or the view closes (module docstring)."""
        gone = asyncio.ensure_future(_until_end(reader))
        try:
            writer.write(_head(HTTPStatus.OK, f"multipart/x-mixed-replace; boundary={BOUNDARY}")
                         + f"--{BOUNDARY}\r\n".encode())
            await _drain(writer)
            sent = 0
            while not self._stopping:
                with self._lock:
                    newer = self._seq > sent
                if not newer:
                    assert self._wake is not None
                    woken = asyncio.ensure_future(self._wake.wait())
                    await asyncio.wait({woken, gone}, return_when=asyncio.FIRST_COMPLETED)
                    woken.cancel()
                    if gone.done():
                        return
                    continue
                sent, jpeg = self._latest_jpeg()
                writer.write(f"Content-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n"
                             .encode() + jpeg + f"\r\n--{BOUNDARY}\r\n".encode())
                await _drain(writer)
        finally:
            gone.cancel()

    def _latest_jpeg(self) -> tuple[int, bytes]:
        """The latest frame as (number, JPEG), encoded at most once per frame; (0, b"")
        before the first."""
        with self._lock:
            seq, rgb = self._seq, self._rgb
        if seq > self._jpeg_seq:
            assert rgb is not None  # seq > 0: a frame was published
            ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise RuntimeError(f"JPEG encoding of a {rgb.shape} frame failed")
            self._jpeg_seq, self._jpeg = seq, buf.tobytes()
        return self._jpeg_seq, self._jpeg

    def _stats_body(self) -> bytes:
        with self._lock:
            return (f'{{"frame": {self._seq}, '
                    f'"age_s": {time.monotonic() - self._published_at:.3f}, '
                    f'"stats": {self._stats_json}}}').encode()


def _head(status: HTTPStatus, content_type: str, length: int | None = None) -> bytes:
    """An HTTP/1.0 response head."""
    lines = [f"HTTP/1.0 {status.value} {status.phrase}", "Server: facewire-liveview",
             f"Content-Type: {content_type}", "Cache-Control: no-store", "Connection: close"]
    if length is not None:
        lines.append(f"Content-Length: {length}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


async def _respond(writer: asyncio.StreamWriter, status: HTTPStatus, content_type: str,
                   body: bytes) -> None:
    writer.write(_head(status, content_type, len(body)) + body)
    await _drain(writer)


async def _drain(writer: asyncio.StreamWriter) -> None:
    """Wait until the kernel has taken what is written (``WRITE_TIMEOUT_S`` at most)."""
    await asyncio.wait_for(writer.drain(), WRITE_TIMEOUT_S)


async def _until_end(reader: asyncio.StreamReader) -> None:
    """Return when the peer ends the connection (what it sends meanwhile is dropped)."""
    try:
        while await reader.read(4096):
            pass
    except ConnectionError:
        pass


def _say(text: str) -> None:
    print(f"facewire live view: {text}", file=sys.stderr, flush=True)


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
