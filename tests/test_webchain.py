"""The whole browser chain: a real sender -> ``facewire web`` -> the page in headless Chromium.

The sender is a real sender's sockets (``PacketPublisher``, and the control thread
``sender.responder.Responder`` with an ``UpdateStore``) publishing lp_d0 encoded by the real
sender pipeline with the conftest's model of that person, at the Hello's rate, on loopback;
the gateway is ``serve_gateway`` on a thread, as ``facewire web`` runs it; the page is the
gateway's own ``/`` (index.html and its modules, as a user opens it) in headless Chromium with
WebGL2 through SwiftShader (``tests/browser.py``). Nothing in between is a stand-in.

What the page shows is judged on a real screenshot (DevTools ``Page.captureScreenshot``, the
whole page with its panel), taken while ``window.facewire.paused`` holds the canvas, the panel
and ``window.facewire.state`` on one slot: the canvas's pixels against Python's
``receiver.scene.StateRenderer`` rendering of the state Python's own playout makes of the same
packet, from the sender's camera (face SSIM, ``test_webrender``'s measure).
"""

from __future__ import annotations

import base64
import dataclasses
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from conftest import free_endpoint, start
from logsender import encoded_log, hello_for
from sessionlog import learned_update
from test_webrender import _face_ssim

from facewire.models.modelfile import PersonModel, load_model
from facewire.models.update import apply_update, encode_update
from facewire.protocol.control import Hello, model_chunks
from facewire.protocol.packet import decode, encode
from facewire.protocol.shaper import UpdateShaper
from facewire.protocol.transport import ControlServer, PacketPublisher, control_endpoint
from facewire.receiver.gateway import serve_gateway
from facewire.receiver.playout import FrameState, Playout
from facewire.receiver.scene import StateRenderer
from facewire.sender.responder import Responder
from facewire.sender.updates import UpdateStore

WIDTH, HEIGHT = 640, 480  # the page's canvas
PAGE = (1000, 600)  # the tab's size, CSS pixels at 1 device pixel each: the canvas and panel
FRAMES = 4  # slots screenshotted and compared with Python
FAST = (10**9, 1.1, (1e9, 1e9))  # an update shaper that holds nothing (test_gateway's)


class _Sender(threading.Thread):
    """A real sender's sockets on ``endpoint`` publishing the log's packets in a loop at the
    Hello's rate, numbered on from 0, with the model version ``serial`` and the region values
    ``q`` ({packet slot: value}) in place of the log's; the control thread answers the Hello,
    the model's chunks and the updates of ``store``. ``sent`` maps each seq published to its
    bytes."""

    def __init__(self, endpoint: str, model_path: Path, hello: Hello,
                 packets: list[bytes]) -> None:
        super().__init__(daemon=True)
        self.hello, self.frames = hello, [decode(p) for p in packets]
        self.store = UpdateStore(hello.model_sha256)
        self.pub = PacketPublisher(endpoint)
        self.server = ControlServer(control_endpoint(endpoint))
        self.responder = Responder(self.server, hello,
                                   model_chunks(model_path.read_bytes(), hello.model_sha256),
                                   self.store, UpdateShaper(*FAST))
        self.serial = 0
        self.q: dict[int, float] = {}
        self.sent: dict[int, bytes] = {}
        self._halt = threading.Event()
        self.responder.start()
        self.start()

    def run(self) -> None:
        period, at, n = 1.0 / self.hello.rate_hz, time.monotonic(), 0
        while not self._halt.wait(max(0.0, at - time.monotonic())):
            frame = self.frames[n % len(self.frames)]
            q = frame.q.copy()
            for slot, value in self.q.items():
                q[slot] = value
            packet = encode(dataclasses.replace(frame, seq=n % 65536, serial=self.serial, q=q))
            self.sent[n % 65536] = packet
            self.pub.send(packet)
            n, at = n + 1, at + period

    def close(self) -> None:
        self._halt.set()
        self.join(10)
        self.responder.stop()
        self.server.close()
        self.pub.close()


def _until(condition: Callable[[], Any], what: str, timeout: float = 60.0) -> Any:
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        assert time.monotonic() < deadline, f"timed out waiting until {what}"
        time.sleep(0.1)
    return value


@dataclasses.dataclass
class Chain:
    """The running chain and what was seen before the sender came."""

    model: PersonModel
    model_path: Path
    hello: Hello
    sender: _Sender
    browser: Any  # browser.DevTools
    session: str
    waiting: str  # the page's status line before there was a sender
    folder: Path

    def js(self, expression: str, timeout: float = 30.0) -> Any:
        """The value of a JavaScript expression in the page (promises awaited)."""
        result = self.browser.call("Runtime.evaluate", {
            "expression": expression, "returnByValue": True, "awaitPromise": True},
            self.session, timeout=timeout)
        if "exceptionDetails" in result:
            raise RuntimeError(f"page script failed: {result['exceptionDetails']}")
        return result["result"].get("value")

    def held_frame(self) -> tuple[dict[str, Any], np.ndarray]:
        """Pause the page on the slot it shows: that state (arrays as lists) and a
        screenshot of the whole page (H, W, 3) RGB; the page plays on after."""
        state = self.js("""(() => { window.facewire.paused = true;
            const s = window.facewire.state;
            return Object.fromEntries(Object.entries(s).map(
                ([k, v]) => [k, ArrayBuffer.isView(v) ? Array.from(v) : v])); })()""")
        try:
            shot = self.browser.call("Page.captureScreenshot", {"format": "png"},
                                     self.session, timeout=30)
        finally:
            self.js("window.facewire.paused = false")
        png = np.frombuffer(base64.b64decode(shot["data"]), np.uint8)
        return state, cv2.imdecode(png, cv2.IMREAD_COLOR)[..., ::-1]

    def canvas_box(self) -> tuple[int, int]:
        """The canvas's top-left corner in the page, CSS pixels (= device pixels here)."""
        x, y = self.js("""(() => { const r = document.getElementById("face")
            .getBoundingClientRect(); return [r.left, r.top]; })()""")
        return round(x), round(y)


@pytest.fixture(scope="module")
def chain(person_model: Path, shared_data: Path,
          tmp_path_factory: pytest.TempPathFactory) -> Iterator[Chain]:
    from browser import WEBGL_FLAGS, DevTools, find_chromium
    from webpage import open_tab

    chromium = find_chromium()
    log = encoded_log(person_model, shared_data / "video" / "lp_d0.mp4")
    hello = hello_for(person_model, log.hello)
    folder = tmp_path_factory.mktemp("chain")
    endpoint = free_endpoint()
    served = threading.Event()
    urls: list[str] = []

    def ready(url: str) -> None:
        urls.append(url)
        served.set()

    thread, stop, result = start(serve_gateway, connect=endpoint, http="127.0.0.1:0",
                                 cache_dir=str(folder / "cache"), ready=ready)
    sender = browser = None
    try:
        _until(lambda: served.is_set() or "error" in result, "the gateway serves")
        assert "error" not in result, result
        browser = DevTools(chromium, folder / "profile", folder / "chromium.log", WEBGL_FLAGS)
        session = open_tab(browser, urls[0], "window.facewire !== undefined")
        browser.call("Emulation.setDeviceMetricsOverride", {
            "width": PAGE[0], "height": PAGE[1], "deviceScaleFactor": 1, "mobile": False},
            session)
        waiting = _until(lambda: (s := browser.evaluate(session, "window.facewire.status"))
                         and "waiting" in s and s, "the page says it waits for a sender")
        sender = _Sender(endpoint, person_model, hello, [p.tobytes() for p in log.packets])
        yield Chain(load_model(person_model), person_model, hello, sender, browser, session,
                    waiting, folder)
    finally:
        if browser is not None:
            browser.close()
        stop.set()
        thread.join(20)
        if sender is not None:
            sender.close()
    assert "error" not in result, result


def _playing(chain: Chain) -> dict[str, Any]:
    """The page's statistics once it has drawn frames for a second with the model loaded."""
    return _until(lambda: (s := chain.js("window.facewire.stats"))["fps"] > 0 and
                  s["frames"] > 30 and chain.js("window.facewire.model.shown") is not None
                  and s, "the page plays frames with the model", timeout=120)


def test_the_page_waits_for_the_sender_then_plays_its_stream(chain: Chain) -> None:
    assert chain.waiting.startswith("waiting for the sender")
    print(f"playing: {_playing(chain)}")
    status = chain.js("window.facewire.status")
    assert "sender connected" in status or "the sender is connected" in status, status
    assert "waiting" not in status and "refused" not in status, status
    assert chain.js("window.facewire.model.sha256") == chain.model.sha256
    # what the page downloaded for the model: at most the .fwm and 10 %
    loads = chain.js("""performance.getEntriesByType("resource")
        .filter((e) => new URL(e.name).pathname.startsWith("/model/"))
        .map((e) => [new URL(e.name).pathname, e.encodedBodySize, e.decodedBodySize])""")
    sha = chain.model.sha256
    assert sorted(p for p, _, _ in loads) == [f"/model/{sha}.glb", f"/model/{sha}.rig"]
    fwm = chain.model_path.stat().st_size
    downloaded = sum(n for _, n, _ in loads)
    print(f"model: {downloaded} bytes downloaded ({sum(n for _, _, n in loads)} decoded) "
          f"for a .fwm of {fwm} ({100 * (downloaded / fwm - 1):+.1f} %)")
    assert 0 < downloaded <= 1.10 * fwm
    # the panel: fps, kbit/s (the 43-byte packets at the Hello's rate), loss, latency and
    # frame time; requestAnimationFrame's rate beside the frames drawn
    raf = chain.js("""new Promise((done) => { let n = 0; const t0 = performance.now();
        const tick = () => { n += 1; const s = (performance.now() - t0) / 1000;
          if (s < 3) requestAnimationFrame(tick); else done(n / s); };
        requestAnimationFrame(tick); })""")
    stats = chain.js("window.facewire.stats")
    counts = chain.js("window.facewire.counts")
    panel = chain.js("""Object.fromEntries(["fps", "kbps", "loss", "latency", "render", "state"]
        .map((id) => [id, document.getElementById(id).textContent]))""")
    kbps = [stats["kbps"]]
    for _ in range(4):
        time.sleep(0.5)
        kbps.append(chain.js("window.facewire.stats.kbps"))
    print(f"page stats: {stats}; panel: {panel}; requestAnimationFrame {raf:.1f} Hz; "
          f"kbit/s {kbps}; counts: {counts}; playout: {chain.js('window.facewire.playout')}")
    wire = 8 * 43 * chain.hello.rate_hz / 1000
    assert abs(np.mean(kbps) - wire) < 0.15 * wire, (kbps, wire)
    assert stats["fps"] > 2 and stats["render_ms"] is not None and stats["render_ms"] > 0
    if raf < 50:  # held below the display's rate by the (software) GPU: the frame time says so
        assert stats["render_ms"] >= 1000 / (2 * raf), (stats, raf)
    assert stats["latency_ms"] is not None and 0 <= stats["latency_ms"] < 1000
    assert stats["loss_percent"] is not None and stats["loss_percent"] <= 10
    assert counts["decoded"] > 30 and sum(counts["corrupt"].values()) == 0
    assert panel["fps"] != "-" and panel["kbps"] != "-" and panel["loss"] != "-"
    assert panel["latency"].endswith(" ms") and panel["render"].endswith(" ms")
    assert panel["state"].startswith(("received", "held"))


def _python_state(chain: Chain, seq: int) -> FrameState:
    """The state Python's playout makes of the packet ``seq`` as the sender sent it."""
    playout = Playout(chain.hello.rate_hz)
    playout.push(chain.sender.sent[seq], 0.0)
    while (state := playout.pop()).seq is None:  # the countdown of a new stream
        pass
    return state


def test_the_page_shows_what_python_renders_of_the_same_packets(chain: Chain) -> None:
    _playing(chain)
    x, y = chain.canvas_box()
    shots, states = [], []
    for _ in range(FRAMES * 3):
        state, shot = chain.held_frame()
        if state["status"] == "received":
            shots.append(shot)
            states.append(state)
        if len(states) == FRAMES:
            break
        time.sleep(0.4)
    assert len(states) == FRAMES, [s["status"] for s in states]
    python = [_python_state(chain, s["seq"]) for s in states]
    for got, want in zip(states, python, strict=True):  # the page decoded what Python does
        assert np.array_equal(np.float32(got["q"]), want.q)
        assert np.array_equal(np.float32(got["residuals"]).reshape(9, 2), want.residuals)
        assert np.allclose(np.reshape(got["rotation"], (3, 3)), want.rotation, atol=1e-12)
        assert np.allclose(got["translation"], want.translation, atol=1e-9)
        assert got["serial"] == want.serial and got["flags"] == int(want.flags)
    canvases = [s[y:y + HEIGHT, x:x + WIDTH] for s in shots]
    with StateRenderer(chain.model, WIDTH, HEIGHT, chain.hello.camera) as renderer:
        theirs = [renderer.render(s) for s in python]
        rig = renderer.rig
    ssim = [_face_ssim(rig, chain.hello, s, a, b)
            for s, a, b in zip(python, canvases, theirs, strict=True)]
    worst = int(np.argmin(ssim))
    side = chain.folder / "side_by_side.png"
    page = shots[worst]
    right = np.full((page.shape[0], WIDTH + 32, 3), 17, np.uint8)
    right[y:y + HEIGHT, 16:16 + WIDTH] = theirs[worst]
    cv2.putText(right, f"Python StateRenderer, seq {states[worst]['seq']}", (16, y - 12),
                cv2.FONT_HERSHEY_SIMPLEX, 0.5, (221, 221, 221), 1, cv2.LINE_AA)
    cv2.imwrite(str(side), np.hstack([page, right])[..., ::-1])
    print(f"face SSIM page (screenshot) vs Python, seqs {[s['seq'] for s in states]}: "
          f"{np.round(ssim, 4)}, mean {np.mean(ssim):.4f} (seq {states[worst]['seq']}: {side})")
    assert np.mean(ssim) >= 0.97, (ssim, side)
    assert all(c.mean() > 5 for c in canvases)  # a face drawn
    others = [_face_ssim(rig, chain.hello, python[i], canvases[i], theirs[j])
              for i in range(FRAMES) for j in range(FRAMES) if i != j]
    print(f"face SSIM of the page's slots against Python's other slots: {np.round(others, 4)}")
    assert np.mean(others) < np.mean(ssim) - 0.02  # the measure tells the slots apart


def test_a_model_update_mid_session_reaches_the_page_without_a_reload(chain: Chain) -> None:
    _playing(chain)
    chain.js("window.chainMarker = 1")
    # a new mouth state (the rest state's colours inverted: unmistakable), last of the
    # region's; the sender's packets then name it
    mouth = [r.name for r in chain.model.regions].index("mouth")
    update = learned_update(chain.model, "mouth", 1, chain.model.sha256)
    versions = [chain.model, apply_update(chain.model, update)]
    chain.sender.store.publish_update(1, encode_update(update, chain.model))
    chain.sender.q = {mouth: float(update.position)}
    chain.sender.serial = 1
    shown = _until(lambda: (m := chain.js("window.facewire.model"))["shown"] == 1 and m,
                   "the page shows model version 1", timeout=60)
    assert shown["held"] == 2 and shown["sha256"] == chain.model.sha256
    assert chain.js("window.chainMarker") == 1  # the same page: no reload
    assert "refused" not in chain.js("window.facewire.status")
    # drawn as Python draws version 1, on a slot where the new state shows (the mouth's
    # regions show only where the lips are apart)
    x, y = chain.canvas_box()
    with StateRenderer(versions[1], WIDTH, HEIGHT, chain.hello.camera) as now, \
            StateRenderer(versions[0], WIDTH, HEIGHT, chain.hello.camera) as then:
        for _ in range(20):
            state, shot = chain.held_frame()
            if state["status"] != "received":
                continue
            assert state["serial"] == 1 and state["q"][mouth] == update.position
            python = _python_state(chain, state["seq"])
            theirs, old = now.render(python), then.render(python)
            if np.abs(theirs.astype(int) - old).max() > 64:
                break
            time.sleep(0.3)
        else:
            pytest.fail("no slot of the log shows the mouth's new state")
        page = shot[y:y + HEIGHT, x:x + WIDTH]
        ssim = _face_ssim(now.rig, chain.hello, python, page, theirs)
        before = _face_ssim(now.rig, chain.hello, python, page, old)
    side = chain.folder / "update.png"
    cv2.imwrite(str(side), np.hstack([page, theirs, old])[..., ::-1])
    print(f"version 1 (seq {state['seq']}): face SSIM page vs Python's version 1 {ssim:.4f}, "
          f"vs its version 0 {before:.4f} ({side})")
    assert ssim >= 0.97 and before < ssim - 0.005
