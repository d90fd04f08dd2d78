"""The live view: its HTTP endpoints from Python, and the page in real headless Chromium.

The browser test (``tests/browser.py`` drives Chromium) opens the page while a thread
publishes frames that carry their own number as a row of black and white blocks (bit i of n
is block i), and reads, from the page itself, the ``<img>`` of the MJPEG stream drawn into a
canvas (block means, a pixel hash) and the statistics panel's text, several times.
"""

from __future__ import annotations

import http.client
import itertools
import json
import socket
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from browser import DevTools, find_chromium

from facewire.receiver.liveview import BOUNDARY, LiveView, LiveViewError

W, H = 640, 480
BITS = 16  # frame-number blocks in the top row, BLOCK x BLOCK px each
BLOCK = W // BITS


def numbered_frame(n: int) -> np.ndarray:
    """A (H, W, 3) uint8 RGB frame showing ``n``: its bits as blocks, a colour, the digits."""
    image = np.empty((H, W, 3), np.uint8)
    image[:] = ((n * 37) % 200 + 30, (n * 11) % 200 + 30, 120)
    for bit in range(BITS):
        image[:BLOCK, bit * BLOCK:(bit + 1) * BLOCK] = 255 if n >> bit & 1 else 0
    cv2.putText(image, str(n), (40, 300), cv2.FONT_HERSHEY_SIMPLEX, 5, (255, 255, 255), 10)
    return image


def read_number(block_means: list[float]) -> int:
    """The frame number from the grey means of the ``BITS`` blocks."""
    return sum(1 << bit for bit, mean in enumerate(block_means) if mean > 128)


def number_in(rgb: np.ndarray) -> int:
    """The frame number shown in a (H, W, 3) image (each block's middle column)."""
    return read_number(list(rgb[:BLOCK, BLOCK // 2::BLOCK].mean(axis=(0, 2))))


def frame_stats(n: int) -> dict[str, Any]:
    return {"fps": 30.0, "kbps": 9.0 + n / 10, "loss_pct": float("nan"),
            "latency_ms": 100 + n, "frames": n}


def get(view: LiveView, path: str, host: str | None = None) -> tuple[int, str, bytes]:
    """GET ``path``: (status, content type, body)."""
    conn = http.client.HTTPConnection(view.host, view.port, timeout=5)
    try:
        conn.putrequest("GET", path, skip_host=host is not None)
        if host is not None:
            conn.putheader("Host", host)
        conn.endheaders()
        response = conn.getresponse()
        return response.status, response.getheader("Content-Type", ""), response.read()
    finally:
        conn.close()


def decode_jpeg(data: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, "not a JPEG"
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


class MjpegReader:
    """The parts of ``/stream.mjpg`` as they arrive, read from a raw socket."""

    def __init__(self, view: LiveView) -> None:
        self.sock = socket.create_connection((view.host, view.port), timeout=5)
        self.sock.sendall(f"GET /stream.mjpg HTTP/1.0\r\nHost: 127.0.0.1:{view.port}\r\n\r\n"
                          .encode())
        self.buffer = b""
        head = self._until(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.0 200"), head
        assert f"multipart/x-mixed-replace; boundary={BOUNDARY}".encode() in head
        assert self._until(b"\r\n") == f"--{BOUNDARY}".encode()

    def _fill(self) -> None:
        chunk = self.sock.recv(65536)
        if not chunk:
            raise EOFError("the stream ended")
        self.buffer += chunk

    def _until(self, mark: bytes) -> bytes:
        while mark not in self.buffer:
            self._fill()
        head, self.buffer = self.buffer.split(mark, 1)
        return head

    def part(self, timeout: float = 5.0) -> bytes:
        """The next JPEG; ``TimeoutError`` when none comes within ``timeout`` s."""
        self.sock.settimeout(timeout)
        headers = dict(line.split(": ", 1) for line in self._until(b"\r\n\r\n").decode()
                       .split("\r\n"))
        assert headers["Content-Type"] == "image/jpeg"
        size = int(headers["Content-Length"])
        while len(self.buffer) < size + 2:
            self._fill()
        jpeg, self.buffer = self.buffer[:size], self.buffer[size + 2:]
        assert self._until(b"\r\n") == f"--{BOUNDARY}".encode()  # sent with the part
        return jpeg


def test_endpoints_serve_the_latest_frame_and_stats() -> None:
    with LiveView() as view:
        assert view.url == f"http://127.0.0.1:{view.port}/" and view.port > 0
        status, _, body = get(view, "/frame.jpg")
        assert status == 503 and b"no frame" in body
        assert json.loads(get(view, "/stats.json")[2])["frame"] == 0

        view.publish(numbered_frame(5), frame_stats(5))
        frame = numbered_frame(6)
        view.publish(frame, {**frame_stats(6), "state": "playing", "count": np.int64(3)})
        frame[:] = 0  # publish copied it
        status, kind, body = get(view, "/frame.jpg?t=1")
        assert (status, kind) == (200, "image/jpeg")
        shown = decode_jpeg(body)
        assert np.abs(shown.astype(int) - numbered_frame(6)).mean() < 3.0
        assert number_in(shown) == 6

        status, kind, body = get(view, "/stats.json")
        data = json.loads(body)
        assert (status, kind) == (200, "application/json")
        assert data["frame"] == 2 and 0 <= data["age_s"] < 5
        assert data["stats"] == {"fps": 30.0, "kbps": 9.6, "loss_pct": None, "latency_ms": 106,
                                 "frames": 6, "state": "playing", "count": 3}

        view.publish(None, {"state": "waiting"})  # stats only: the frame stays
        assert json.loads(get(view, "/stats.json")[2]) | {"age_s": 0} == \
            {"frame": 2, "age_s": 0, "stats": {"state": "waiting"}}

        status, kind, page = get(view, "/")
        assert (status, kind) == (200, "text/html; charset=utf-8")
        for needle in (b'<img id="stream" src="/stream.mjpg"', b'id="stat-fps"',
                       b'id="stat-kbps"', b'id="stat-loss_pct"', b'id="stat-latency_ms"',
                       b'fetch("/stats.json"'):
            assert needle in page
        assert get(view, "/nothing")[0] == 404


def test_stream_pushes_each_new_frame_once() -> None:
    with LiveView() as view:
        view.publish(numbered_frame(1), frame_stats(1))
        reader = MjpegReader(view)
        numbers = [number_in(decode_jpeg(reader.part()))]
        for n in (2, 3, 4):
            view.publish(numbered_frame(n), frame_stats(n))
            numbers.append(number_in(decode_jpeg(reader.part())))
        assert numbers == [1, 2, 3, 4]
        view.publish(None, frame_stats(4))  # new stats, no new frame: nothing is pushed
        with pytest.raises(TimeoutError):
            reader.part(timeout=0.3)
        reader.sock.close()


def test_close_releases_waiting_connections() -> None:
    view = LiveView()
    view.publish(numbered_frame(1), frame_stats(1))
    reader = MjpegReader(view)
    reader.part()  # now waiting for the next frame inside the server
    idle = socket.create_connection((view.host, view.port), timeout=5)  # sends no request
    time.sleep(0.1)
    start = time.monotonic()
    view.close()
    assert time.monotonic() - start < 1.0
    with pytest.raises(EOFError):
        reader.part()
    assert idle.recv(1) == b""
    with pytest.raises(OSError):
        socket.create_connection((view.host, view.port), timeout=1)
    with pytest.raises(ValueError, match="closed"):
        view.publish(numbered_frame(2), {})
    view.close()  # idempotent


def test_binding_is_loopback_unless_asked_and_a_busy_port_is_named() -> None:
    with pytest.raises(LiveViewError, match="refusing to serve on 0.0.0.0.*allow_remote"):
        LiveView(host="0.0.0.0")
    with LiveView(host="0.0.0.0", allow_remote=True) as anywhere:
        assert get(anywhere, "/stats.json", host="some-host.example:80")[0] == 200
    with LiveView() as view, \
            pytest.raises(LiveViewError, match=f"port {view.port} is already in use"):
        LiveView(port=view.port)
    with LiveView(host="localhost") as view:
        assert get(view, "/")[0] == 200
    with pytest.raises(ValueError, match="port"):
        LiveView(port=70000)


def test_requests_to_a_foreign_host_name_are_refused() -> None:
    """A page that rebinds its own domain to 127.0.0.1 sends its own name as Host."""
    with LiveView() as view:
        view.publish(numbered_frame(1), frame_stats(1))
        for path in ("/", "/frame.jpg", "/stream.mjpg", "/stats.json"):
            assert get(view, path, host=f"attacker.example:{view.port}")[0] == 403
        assert get(view, "/stats.json", host=f"localhost:{view.port}")[0] == 200
        assert get(view, "/stats.json", host=f"[::1]:{view.port}")[0] == 200


def test_publish_validates_its_arguments() -> None:
    with LiveView() as view:
        for bad in (np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.uint8),
                    np.zeros((0, 4, 3), np.uint8), [[0, 0, 0]]):
            with pytest.raises(ValueError, match="rgb"):
                view.publish(bad, {})  # type: ignore[arg-type]
        with pytest.raises(TypeError, match=r"stats\['fps'\]"):
            view.publish(None, {"fps": [30]})
        with pytest.raises(TypeError, match="keys must be str"):
            view.publish(None, {1: 2})  # type: ignore[dict-item]
        with pytest.raises(TypeError, match="stats: expected a dict"):
            view.publish(None, [("fps", 1)])  # type: ignore[arg-type]


# --- the page in real headless Chromium ---


# What the page shows now: the <img> (the MJPEG stream) drawn into a canvas, as the grey
# means of the frame-number blocks and a hash of all pixels, and the statistics panel's text.
SAMPLE_JS = f"""(() => {{
  const img = document.getElementById("stream");
  if (!img || !img.complete || img.naturalWidth === 0) return null;
  const canvas = document.createElement("canvas");
  canvas.width = img.naturalWidth;
  canvas.height = img.naturalHeight;
  const g = canvas.getContext("2d");
  g.drawImage(img, 0, 0);
  const pixels = g.getImageData(0, 0, canvas.width, canvas.height).data;
  let hash = 2166136261;
  for (let i = 0; i < pixels.length; i += 4) {{
    hash = Math.imul(hash ^ pixels[i] ^ pixels[i + 1] << 8 ^ pixels[i + 2] << 16, 16777619);
  }}
  const blocks = [];
  for (let bit = 0; bit < {BITS}; bit++) {{
    const d = g.getImageData(bit * {BLOCK} + 8, 8, {BLOCK} - 16, {BLOCK} - 16).data;
    let sum = 0;
    for (let i = 0; i < d.length; i += 4) sum += (d[i] + d[i + 1] + d[i + 2]) / 3;
    blocks.push(sum / (d.length / 4));
  }}
  const stats = {{}};
  for (const e of document.querySelectorAll("[data-stat]")) stats[e.dataset.stat] = e.textContent;
  return {{title: document.title, width: img.naturalWidth, height: img.naturalHeight,
          hash: hash >>> 0, blocks, stats,
          status: document.getElementById("status").textContent}};
}})()"""


def test_page_in_headless_chromium(tmp_path: Path) -> None:
    """The page loads, the stream's frames change live, and the statistics follow."""
    chromium = find_chromium()
    published = [0]
    stop = threading.Event()
    with LiveView() as view:
        def perform() -> None:
            while not stop.is_set():
                n = published[0] + 1
                view.publish(numbered_frame(n), frame_stats(n))
                published[0] = n
                time.sleep(1 / 30)

        performer = threading.Thread(target=perform, daemon=True)
        performer.start()
        browser = DevTools(chromium, tmp_path / "profile", tmp_path / "chromium.log")
        try:
            target = browser.call("Target.createTarget", {"url": view.url})["targetId"]
            session = browser.call("Target.attachToTarget",
                                   {"targetId": target, "flatten": True})["sessionId"]
            deadline = time.monotonic() + 10
            while (first := browser.evaluate(session, SAMPLE_JS)) is None \
                    or not first["status"].startswith("frame"):
                assert time.monotonic() < deadline, f"the page did not load: {first}"
                time.sleep(0.1)
            samples = []
            for _ in range(6):
                time.sleep(0.4)
                before = published[0]
                sample = browser.evaluate(session, SAMPLE_JS)
                samples.append((before, published[0], sample))
        finally:
            browser.close()
            stop.set()
            performer.join()

    # (a) the page loaded with the stream's image in it
    assert (first["title"], first["width"], first["height"]) == ("facewire live view", W, H)
    # (b) the <img> shows new frames: each sample a later frame, live (at most 1.5 s old)
    shown = [read_number(sample["blocks"]) for _, _, sample in samples]
    assert all(a < b for a, b in itertools.pairwise(shown)), shown
    for (before, after, _), n in zip(samples, shown, strict=True):
        assert before - 45 <= n <= after, (before, n, after)
    assert len({sample["hash"] for _, _, sample in samples}) == len(samples)
    # (c) the statistics panel follows the published stats
    frames_stat = [int(sample["stats"]["frames"]) for _, _, sample in samples]
    assert all(a < b for a, b in itertools.pairwise(frames_stat)), frames_stat
    for (before, after, sample), n in zip(samples, frames_stat, strict=True):
        assert before - 45 <= n <= after
        assert sample["stats"]["latency_ms"] == f"{100 + n} ms"
        assert sample["stats"]["kbps"] == f"{9.0 + n / 10:.1f} kbit/s"
        assert sample["stats"]["fps"] == "30.0"
        assert sample["stats"]["loss_pct"] == "\u2013"  # NaN: unknown
        assert sample["status"].startswith("frame ")
