"""The browser receiver's page in real headless Chromium: its packet decoding (packet.js) and
its playout (playout.js) against the Python definitions (protocol/packet.py,
receiver/playout.py), and the page itself (index.html, main.js) against a WebSocket server
that speaks the gateway's contract (docs/DESIGN.md, "Browser receiver").

The modules are loaded from the installed ``facewire.receiver`` web folder through a test page
of their own (``webpage.PageServer`` extras) that only imports them and turns hex strings into
bytes; the page's own files are unchanged.
"""

from __future__ import annotations

import asyncio
import json
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import asdict
from http import HTTPStatus
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

import numpy as np
import pytest
from browser import WEBGL_FLAGS, DevTools, find_chromium
from sessionlog import learned_update
from webpage import TYPES, PageServer, open_tab, web_dir
from websockets.asyncio.server import serve
from websockets.datastructures import Headers
from websockets.http11 import Response

from facewire.models import webmodel
from facewire.models.modelfile import load_model
from facewire.models.update import apply_update
from facewire.protocol.control import Hello
from facewire.protocol.log import read_log
from facewire.protocol.packet import (
    FRAME_DTYPE,
    MAX_SERIAL,
    PACKET_BYTES,
    QUANTISERS,
    RESERVED_FLAGS,
    VERSION,
    Flag,
    PacketError,
    decode,
    decode_frames,
    encode_frames,
)
from facewire.receiver.playout import FrameState, Playout, replay_states
from facewire.sender.pipeline import encode_video

sys.path.insert(0, str(Path(__file__).parent / "reliability"))  # the fuzz tests' corpus
from packetoracle import Garbage, pack, random_fields  # noqa: E402

TEST_PAGE = """<!doctype html><meta charset="utf-8"><title>modules</title>
<script type="module">
import * as packet from "/packet.js";
import * as playout from "/playout.js";
const bytes = (hex) => Uint8Array.from(hex.match(/../g) ?? [], (x) => parseInt(x, 16));
const plain = (s) => ({...s, rotation: Array.from(s.rotation),
  translation: Array.from(s.translation), residuals: Array.from(s.residuals), q: Array.from(s.q),
  shade: Array.from(s.shade)});
window.table = () => ({quantisers: packet.quantiserTable(), flags: packet.Flag,
  reserved: packet.RESERVED_FLAGS, version: packet.VERSION, bytes: packet.PACKET_BYTES,
  max_serial: packet.MAX_SERIAL});
window.decodeAll = (hexes) => hexes.map((hex) => {
  try {
    const f = packet.decode(bytes(hex));
    return {...f, rotation: Array.from(f.rotation), translation: Array.from(f.translation),
      residuals: Array.from(f.residuals), q: Array.from(f.q), shade: Array.from(f.shade)};
  } catch (error) {
    if (error instanceof packet.PacketError) return error.reason;
    throw error;
  }
});
// receiver.playout.replay_states: a tick clock at rate_hz from the first arrival; before the
// pop of tick k every packet whose time is at most the tick is pushed (time order, then list
// order); the states with a slot, until every packet is pushed and every slot played.
window.replay = (hexes, times, rate, restQ) => {
  const p = new playout.Playout(rate, {restQ});
  const order = [...times.keys()].sort((a, b) => times[a] - times[b] || a - b);
  const start = order.length ? times[order[0]] : 0;
  const states = [];
  for (let i = 0, tick = 0; ; tick++) {
    const now = start + tick / rate;
    for (; i < order.length && times[order[i]] <= now + 1e-9; i++) {
      const hex = hexes[order[i]];
      p.push(hex === null ? null : bytes(hex), times[order[i]]);
    }
    const s = p.pop();
    if (s.seq !== null) states.push(plain(s));
    if (i === order.length && p.drained) break;
  }
  return {states, stats: p.stats};
};
// main.js's clock, as events: after each arrival pop while ready; between arrivals pop at
// each deadline due() that comes first. Each pop is [its time, the state's seq, status].
window.live = (hexes, times, rate) => {
  const p = new playout.Playout(rate);
  const pops = [];
  const drain = (now) => {
    for (;;) {
      const due = p.due();
      if (!(p.ready || (due !== null && now >= due))) return;
      const s = p.pop();
      pops.push([now, s.seq, s.status]);
    }
  };
  for (let i = 0; i < hexes.length; i++) {
    for (let due = p.due(); due !== null && due < times[i]; due = p.due()) drain(due);
    p.push(bytes(hexes[i]), times[i]);
    drain(times[i]);
  }
  return {pops, stats: p.stats};
};
window.ready = true;
</script>"""


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DevTools]:
    chromium = find_chromium()
    folder = tmp_path_factory.mktemp("chromium")
    browser = DevTools(chromium, folder / "profile", folder / "chromium.log", WEBGL_FLAGS)
    yield browser
    browser.close()


@pytest.fixture(scope="module")
def modules(browser: DevTools) -> Iterator[str]:
    """A tab with packet.js and playout.js loaded (the test page's functions on window)."""
    with PageServer({"/test.html": ("text/html; charset=utf-8", TEST_PAGE.encode())}) as server:
        yield open_tab(browser, f"{server.url}/test.html", "window.ready === true")


@pytest.fixture(scope="module")
def log(person_model: Path, shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """lp_d0.mp4 (78 frames, 25 Hz) through the real sender pipeline with its own model."""
    path = tmp_path_factory.mktemp("webpage") / "lp_d0.fwlog"
    encode_video(person_model, shared_data / "video" / "lp_d0.mp4", path)
    return path


def call(browser: DevTools, session: str, function: str, *args: Any) -> Any:
    """The value of ``function(*args)`` in the tab, arguments passed as JSON."""
    return browser.evaluate(session, f"{function}(...{json.dumps(args)})")


def python_reason(item: bytes) -> str | None:
    try:
        decode(item)
    except PacketError as exc:
        return exc.reason
    return None


# -- packet.js -------------------------------------------------------------------------------

def test_the_js_packet_table_is_protocol_packets(browser: DevTools, modules: str) -> None:
    table = call(browser, modules, "table")
    assert table["quantisers"] == [
        {"name": q.name, "count": q.count, "bits": q.bits, "lo": q.lo, "step": q.step,
         "unit": q.unit} for q in QUANTISERS]
    assert table["flags"] == {flag.name: int(flag) for flag in Flag}
    assert (table["reserved"], table["version"], table["bytes"], table["max_serial"]) == \
        (RESERVED_FLAGS, VERSION, PACKET_BYTES, MAX_SERIAL)


def test_js_decoding_agrees_with_python_on_a_real_log_and_the_fuzz_corpus(
        browser: DevTools, modules: str, log: Path) -> None:
    """Every packet of a real log decodes to Python's values exactly (the quantised values as
    float32); the fuzz corpus (``packetoracle``: random bytes of any length, bit errors of real
    packets, cut and extended packets, CRC-right packets with a bad version or reserved flags,
    CRC-right packets of random fields) gets Python's verdict packet by packet, so the counts
    by reason match."""
    real = read_log(log).packets
    rng = np.random.default_rng(18)
    garbage = Garbage(rng)
    near = [p.tobytes() for p in real]
    corpus = []
    while len(corpus) < 4000:
        item = garbage(near)
        if isinstance(item, (bytes, bytearray, memoryview)):  # what a WebSocket can carry
            corpus.append(bytes(item))
    fields = random_fields(rng, 1000, extremes=0.25)
    fields[:, 0] = np.where(rng.random(1000) < 0.7, VERSION, rng.integers(0, 16, 1000))
    fields[:, 1] = rng.integers(0, 256, 1000)
    corpus += [p.tobytes() for p in pack(fields)]
    items = near + corpus

    got = call(browser, modules, "decodeAll", [item.hex() for item in items])

    want = [python_reason(item) for item in items]
    assert [g if isinstance(g, str) else None for g in got] == want
    counts = Counter(g if isinstance(g, str) else "decoded" for g in got[len(near):])
    assert counts == Counter(w or "decoded" for w in want[len(near):])
    assert {"size", "version", "crc", "reserved", "decoded"} <= set(counts), counts
    assert all(w is None for w in want[:len(near)])
    valid = [i for i, w in enumerate(want) if w is None]
    frames, _ = decode_frames(np.frombuffer(b"".join(items[i] for i in valid), np.uint8)
                              .reshape(-1, PACKET_BYTES))
    js = [got[i] for i in valid]
    for key in ("seq", "flags", "serial"):
        assert [g[key] for g in js] == frames[key].tolist(), key
    for key, shape in (("rotation", (3,)), ("translation", (3,)), ("residuals", (9, 2)),
                       ("q", (8,)), ("shade", (3,))):
        values = np.array([g[key] for g in js], np.float64).reshape(-1, *shape)
        assert np.array_equal(values.astype(np.float32), values), f"{key}: not float32 values"
        assert np.array_equal(values, frames[key].astype(np.float64)), key


# -- playout.js ------------------------------------------------------------------------------

RESTART_SEQ = 20000

def stream(log: Path, seed: int, loss: float) -> tuple[list[bytes | None], np.ndarray, float,
                                                      np.ndarray]:
    """A real log's packets made into a longer, harder stream: the log three times over with
    sequence numbers from 65450 (so they wrap), 30 frames of a lost face (tracking lost, then
    no face), then a sender that restarts at ``RESTART_SEQ`` for its last 40 packets; arrival
    times jittered by up to 1.5 slots (reordering). With ``loss`` that fraction is dropped
    (seeded, never the first), 3 % duplicated, a far stray packet and 40 items of the fuzz
    corpus (bytes and objects that are no bytes, None here) mixed in. Returns the items, their
    times, the rate and a rest Q (each region's, as a model's ``Region.rest``)."""
    recorded = read_log(log)
    rate = recorded.hello.rate_hz
    frames, _ = decode_frames(recorded.packets)
    frames = np.concatenate([frames] * 3)
    n = len(frames)
    frames["seq"] = (65450 + np.arange(n)) % 65536
    frames["seq"][n - 40:] = RESTART_SEQ + np.arange(40)
    frames["flags"][100:115] = Flag.FACE_PRESENT | Flag.TRACKING_LOST
    frames["flags"][115:130] = 0
    packets = [p.tobytes() for p in encode_frames(frames.astype(FRAME_DTYPE))[0]]
    rng = np.random.default_rng(seed)
    times = np.arange(n) / rate + 1000.0 + rng.uniform(0, 1.5 / rate, n)
    times[n - 40:] += 0.5  # the restarted sender's first packet comes half a second later
    items: list[bytes | None] = list(packets)
    keep = np.ones(n, bool)
    if loss:
        keep[1:] = rng.random(n - 1) >= loss
        items = [p for p, k in zip(packets, keep) if k]
        times = times[keep]
        twice = rng.random(len(items)) < 0.03
        items += [p for p, t in zip(items, twice) if t]
        times = np.concatenate([times, times[twice] + rng.uniform(0, 0.1, int(twice.sum()))])
        far = frames[50:51].copy()
        far["seq"] = 30000
        items.append(encode_frames(far)[0][0].tobytes())
        times = np.append(times, times[60])
        garbage = Garbage(rng)
        for _ in range(40):
            item = garbage(packets)
            items.append(bytes(item) if isinstance(item, (bytes, bytearray, memoryview))
                         else None)
            times = np.append(times, rng.uniform(times.min(), times.max()))
    model_rest = np.linspace(0.5, 2.0, 8).astype(np.float32)
    return items, times, rate, model_rest


def as_plain(state: FrameState) -> dict[str, Any]:
    return {"seq": state.seq, "status": state.status, "flags": int(state.flags),
            "weight": state.weight, "arrival_s": state.arrival_s, "serial": state.serial,
            "rotation": state.rotation.ravel(), "translation": state.translation,
            "residuals": state.residuals.ravel(), "q": state.q, "shade": state.shade}


@pytest.mark.parametrize("loss", [0.0, 0.3])
def test_js_playout_gives_pythons_states(browser: DevTools, modules: str, log: Path,
                                         loss: float) -> None:
    """The same items at the same arrival times through ``replay_states`` and through
    playout.js on the same tick clock: the same FrameStates (pose to round-off, expression,
    statuses, serial, light exactly), and the same counts. Through 30 % loss the page keeps
    playing: one state per slot of each stream, the lost ones held and eased as Python's."""
    items, times, rate, rest = stream(log, seed=int(loss * 100), loss=loss)
    playout = Playout(rate, rest_q=rest)
    want = [as_plain(s) for s in replay_states(
        [b"" if i is None else i for i in items], times, rate, playout=playout)]
    # None stands for an object that is no bytes: corrupt in both (b"" is too, in Python)
    got = call(browser, modules, "replay", [None if i is None else i.hex() for i in items],
               times.tolist(), rate, rest.tolist())

    assert got["stats"] == playout.stats
    assert len(got["states"]) == len(want)
    for k, (g, w) in enumerate(zip(got["states"], want)):
        for key in ("seq", "status", "flags", "serial", "arrival_s"):
            assert g[key] == w[key], (k, key, g[key], w[key])
        assert g["weight"] == pytest.approx(w["weight"], abs=1e-12), k
        assert np.allclose(g["rotation"], w["rotation"], rtol=0, atol=1e-12), k
        for key in ("translation", "residuals", "q", "shade"):
            assert np.array_equal(np.array(g[key], np.float64),
                                  np.asarray(w[key], np.float64)), (k, key)
    statuses = Counter(s["status"] for s in want)
    assert {"received", "face_lost", "easing"} <= set(statuses), statuses
    assert any(s["status"] == "face_lost" and s["weight"] == 0 for s in want)  # eased out
    assert playout.stats["restarts"] == 1 and playout.stats["received"] > 0
    seqs = [s["seq"] for s in want]
    restart = next(k for k, seq in enumerate(seqs) if RESTART_SEQ <= seq < RESTART_SEQ + 40)
    for part in (seqs[:restart], seqs[restart:]):  # every slot of each stream, in order
        assert np.all(np.diff(np.array(part) - part[0]) % 65536 == 1), part
    if loss:
        assert "held" in statuses and playout.stats["corrupt"] == 40
        assert playout.stats["duplicate"] > 0 and playout.stats["stray"] >= 1
        concealed = sum(s["arrival_s"] is None for s in want)
        assert 0.2 * len(want) < concealed < 0.4 * len(want)
        assert any(s["q"][0] != rest[0] and s["status"] == "easing" for s in want)


def test_js_playing_on_arrival_follows_pythons_deadlines(browser: DevTools, modules: str,
                                                         log: Path) -> None:
    """main.js's clock (pop while ``ready``, or once ``due()`` has passed) over a lossy, jittered
    stream: the same pops at the same times as the Python playout's ``ready`` and ``due``."""
    items, times, rate, _ = stream(log, seed=7, loss=0.3)
    pairs = sorted((t, i) for t, i in zip(times, items) if i is not None and len(i) == 43)
    hexes = [i.hex() for _, i in pairs]
    arrivals = [t for t, _ in pairs]
    playout = Playout(rate)
    want: list[list[Any]] = []

    def drain(now: float) -> None:
        while True:
            due = playout.due()
            if not (playout.ready or (due is not None and now >= due)):
                return
            state = playout.pop()
            want.append([now, state.seq, state.status])

    for hexed, t in zip(hexes, arrivals):
        while (due := playout.due()) is not None and due < t:
            drain(due)
        playout.push(bytes.fromhex(hexed), t)
        drain(t)
    got = call(browser, modules, "live", hexes, arrivals, rate)

    assert got["stats"] == playout.stats
    assert [p[1:] for p in got["pops"]] == [p[1:] for p in want]
    assert np.allclose([p[0] for p in got["pops"]], [p[0] for p in want], rtol=0, atol=1e-9)
    assert sum(p[2] == "held" for p in want) > 10


# -- the page --------------------------------------------------------------------------------

class ContractServer:
    """A stand-in for ``facewire web`` on loopback that speaks the gateway's contract
    (docs/DESIGN.md, "Browser receiver"): the page's files at ``/NAME``, ``extra`` paths (model
    bytes), the WebSocket at ``/stream``, and ``?token=`` required on every request (403
    otherwise, counted in ``refused``). On connect a client gets ``{"type": "status",
    "sender": "waiting"}``; the test then ``send``s to every client and may ``drop`` them."""

    def __init__(self, token: str, extra: dict[str, tuple[str, bytes]] | None = None) -> None:
        self.token, self.extra = token, dict(extra or {})
        self.clients: list[Any] = []
        self.connections = 0
        self.refused: list[str] = []
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self._thread.start()

        async def start() -> Any:
            return await serve(self._handler, "127.0.0.1", 0, process_request=self._request)

        self._server = self._run(start())
        self.url = f"http://127.0.0.1:{self._server.sockets[0].getsockname()[1]}"

    def _run(self, coroutine: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop).result(timeout=10)

    def _request(self, connection: Any, request: Any) -> Response | None:
        path, _, query = request.path.partition("?")
        if parse_qs(query).get("token") != [self.token]:
            self.refused.append(request.path)
            return connection.respond(HTTPStatus.FORBIDDEN, "token\n")
        if path == "/stream":
            return None
        if path in self.extra:
            kind, body = self.extra[path]
        else:
            file = web_dir() / ("index.html" if path == "/" else path.lstrip("/"))
            if "/" in path.lstrip("/") or not file.is_file():
                return connection.respond(HTTPStatus.NOT_FOUND, "not found\n")
            kind, body = TYPES.get(file.suffix, "application/octet-stream"), file.read_bytes()
        return Response(200, "OK", Headers({"Content-Type": kind,
                                            "Content-Length": str(len(body))}), body)

    async def _handler(self, client: Any) -> None:
        self.clients.append(client)
        self.connections += 1
        await client.send(json.dumps({"type": "status", "sender": "waiting",
                                      "text": "waiting for the sender at tcp://127.0.0.1:5555"}))
        await client.wait_closed()
        self.clients.remove(client)

    def send(self, *messages: str | bytes) -> None:
        async def send_all() -> None:
            for client in list(self.clients):
                for message in messages:
                    await client.send(message)
        self._run(send_all())

    def drop(self) -> None:
        async def close_all() -> None:
            await asyncio.gather(*(client.close() for client in list(self.clients)))
        self._run(close_all())

    def close(self) -> None:
        self._server.close()
        self._run(self._server.wait_closed())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join()


def hello_json(hello: Hello, **changes: Any) -> str:
    return json.dumps({"type": "hello", **asdict(hello), **changes})


def wait_for(browser: DevTools, session: str, expression: str, timeout: float = 10.0) -> Any:
    """The value of ``expression`` once it is truthy in the page."""
    deadline = time.monotonic() + timeout
    while not (value := browser.evaluate(session, expression)):
        assert time.monotonic() < deadline, f"still false after {timeout} s: {expression}"
        time.sleep(0.05)
    return value


def test_the_page_waits_plays_through_loss_counts_and_reconnects(browser: DevTools,
                                                                  log: Path) -> None:
    """The page on a server of the gateway's contract, with a token: it says it waits for the
    sender; given a Hello and a real log's packets at the stream's rate with 30 % dropped and
    corrupt ones mixed in, it plays every slot (the lost ones concealed), counts the corrupt
    packets by Python's reasons, shows kbit/s and loss; it ignores junk text, refuses a Hello
    of another packet table and says so; when the socket closes it says so and reconnects."""
    recorded = read_log(log)
    rate = recorded.hello.rate_hz
    rng = np.random.default_rng(30)
    keep = rng.random(len(recorded.packets)) >= 0.3
    keep[[0, -1]] = True
    fields = random_fields(rng, 2)
    fields[0, 0] = 3  # another protocol version, CRC right
    fields[1, 1] |= 0xC0  # the reserved flag bits, CRC right
    corrupt = [b"\x20" * 10, recorded.packets[5].tobytes() + b"\x00"] + \
        [p.tobytes() for p in pack(fields)]
    corrupt.append(bytes(recorded.packets[9] ^ np.eye(1, 43, 20, dtype=np.uint8)[0]))
    server = ContractServer("s3cret")
    try:
        tab = open_tab(browser, f"{server.url}/?token=s3cret",
                       "window.facewire !== undefined && "
                       "window.facewire.status.includes('waiting for the sender')")
        server.send("not json", json.dumps({"type": "bogus"}),
                    hello_json(recorded.hello, quantisers=[]))
        wait_for(browser, tab, "window.facewire.status.includes('sender refused: "
                               "hello.quantisers')")
        server.send(json.dumps({"type": "status", "sender": "connected",
                                "text": "sender tcp://127.0.0.1:5555"}),
                    hello_json(recorded.hello))
        wait_for(browser, tab, "window.facewire.hello !== null")
        sent = kbps = 0
        start = time.monotonic()
        for k, packet in enumerate(recorded.packets):
            if k % 10 == 5 and k // 10 < len(corrupt):
                server.send(corrupt[k // 10])
                sent += 1
            if keep[k]:
                server.send(packet.tobytes())
                sent += 1
            if k == 60:
                kbps = browser.evaluate(tab, "window.facewire.stats.kbps")
                panel = browser.evaluate(tab, "document.getElementById('kbps').textContent")
            time.sleep(max(0.0, start + (k + 1) / rate - time.monotonic()))
        wait_for(browser, tab, "(({counts: c, playout: p}) => c.statuses.received + p.late + "
                               f"p.discarded === {keep.sum()})(window.facewire)")
        counts, playout, status, loss = browser.evaluate(tab, """[window.facewire.counts,
            window.facewire.playout, window.facewire.status,
            document.getElementById('loss').textContent]""")

        assert counts["packets"] == sent and counts["junk"] == 2 and counts["ignored"] == 0
        assert counts["corrupt"] == {"size": 2, "version": 1, "crc": 1, "reserved": 1,
                                     "type": 0}
        assert Counter(python_reason(c) for c in corrupt) == Counter(
            {r: n for r, n in counts["corrupt"].items() if n})
        assert counts["decoded"] == playout["received"] == int(keep.sum())
        # every packet played (a few may come too late on a loaded machine: they are counted
        # late), the missing ones concealed, and the slots after the last packet once they are
        # due (the sender is gone)
        assert counts["statuses"]["received"] >= 0.9 * keep.sum(), (counts, playout)
        assert playout["concealed"] >= len(keep) - keep.sum() and counts["statuses"]["held"] > 0
        want = 43 * 8 * rate * keep.mean() / 1000
        assert 0.5 * want < kbps < 2 * want and float(panel) == pytest.approx(kbps, abs=1.5)
        assert "%" in loss and "sender tcp://127.0.0.1:5555" in status
        assert "sender refused" not in status

        server.drop()
        wait_for(browser, tab, "window.facewire.status.includes('reconnecting in')")
        wait_for(browser, tab, "window.facewire.connected && "
                               "window.facewire.status.includes('waiting for the sender')")
        assert server.connections == 2 and not server.refused
    finally:
        server.close()


def test_the_page_draws_the_model_and_keeps_it_when_another_is_corrupt(
        browser: DevTools, log: Path, person_model: Path) -> None:
    """With the rendering half (model.js, render.js, views.js) and the model's browser bytes
    (``models.webmodel``): the page loads a real model, draws nearly every slot of a real log
    at its rate, and when told of a corrupt model, then of a corrupt update, refuses each with
    a visible line, keeps the last good version on screen and keeps drawing; the same model
    announced again starts its versions anew."""
    model = load_model(person_model)
    sha, bad = model.sha256, "0" * 64
    extra = {f"/model/{sha}.glb": ("model/gltf-binary", webmodel.model_glb(model)),
             f"/model/{sha}.rig": ("application/octet-stream", webmodel.rig_bin(model)),
             f"/model/{bad}.glb": ("model/gltf-binary", b"glTF" + bytes(range(256)) * 4),
             f"/model/{bad}.rig": ("application/octet-stream", webmodel.rig_bin(model)),
             f"/model/{sha}/1.upd": ("application/octet-stream", b"FWUP" + b"\xff" * 64),
             f"/model/{sha}/11.upd": ("application/octet-stream", webmodel.update_bin(
                 model, apply_update(model, learned_update(model, "mouth", 1, sha))))}
    recorded = read_log(log)
    rate = recorded.hello.rate_hz
    server = ContractServer("k", extra)
    try:
        tab = open_tab(browser, f"{server.url}/?token=k",
                       "window.facewire !== undefined && window.facewire.connected")
        server.send(hello_json(recorded.hello), json.dumps(
            {"type": "model", "sha256": sha, "glb": f"/model/{sha}.glb",
             "rig": f"/model/{sha}.rig", "bytes": len(extra[f"/model/{sha}.glb"][1])}))
        wait_for(browser, tab, f"window.facewire.model.sha256 === '{sha}'", timeout=30)
        start = time.monotonic()
        for k, packet in enumerate(recorded.packets):
            server.send(packet.tobytes())
            if k == 20:
                server.send(json.dumps({"type": "model", "sha256": bad,
                                        "glb": f"/model/{bad}.glb",
                                        "rig": f"/model/{bad}.rig", "bytes": 1028}))
            if k == 45:
                refused_model = browser.evaluate(tab, "window.facewire.status")
                server.send(json.dumps({"type": "update", "serial": 1,
                                        "url": f"/model/{sha}/1.upd", "bytes": 68}))
            time.sleep(max(0.0, start + (k + 1) / rate - time.monotonic()))
        n = len(recorded.packets)  # each played, or dropped late or at a restart
        wait_for(browser, tab, "(({counts: c, playout: p}) => c.statuses.received + p.late + "
                               f"p.discarded === {n})(window.facewire)")
        stats, status, counts, playout = browser.evaluate(tab, """[window.facewire.stats,
            window.facewire.status, window.facewire.counts, window.facewire.playout]""")

        assert "model refused: " in refused_model and \
            "showing the last good one (version 0)" in refused_model
        assert "model update 1 refused: " in status and "showing the last good one" in status
        assert browser.evaluate(tab, "window.facewire.model") == {"sha256": sha, "held": 1,
                                                                  "shown": 0}
        print(f"page drawing a real log at {rate:g} Hz: {stats}; {playout}")
        assert counts["statuses"]["received"] > 0.75 * len(recorded.packets), (counts, playout)
        assert stats["frames"] > 0.25 * len(recorded.packets), stats
        assert stats["render_ms"] > 0 and stats["latency_ms"] is not None

        # another Hello (a sender restarted with another camera): a new playout, and a new
        # renderer on the same canvas (the old one's GPU objects released) draws on
        camera = {**asdict(recorded.hello.camera), "fx": 600.0, "fy": 600.0}
        server.send(hello_json(recorded.hello, camera=camera))
        wait_for(browser, tab, "window.facewire.hello.camera.fx === 600")
        start = time.monotonic()
        for k, packet in enumerate(recorded.packets[:30]):
            server.send(packet.tobytes())
            time.sleep(max(0.0, start + (k + 1) / rate - time.monotonic()))
        wait_for(browser, tab, "window.facewire.playout.received === 30")
        again = browser.evaluate(tab, "window.facewire.stats.frames")
        assert again > stats["frames"] + 5
        status = browser.evaluate(tab, "window.facewire.status")
        assert "error" not in status and "cannot" not in status, status

        # a good update 1 is taken; the same model announced again (a new session of it, as
        # after a sender's restart) takes the page back to version 0, and that session's own
        # update 1 is taken again
        good = json.dumps({"type": "update", "serial": 1, "url": f"/model/{sha}/11.upd",
                           "bytes": len(extra[f"/model/{sha}/11.upd"][1])})
        server.send(good)
        wait_for(browser, tab, "window.facewire.model.held === 2", timeout=30)
        server.send(json.dumps({"type": "model", "sha256": sha, "glb": f"/model/{sha}.glb",
                                "rig": f"/model/{sha}.rig", "bytes": 1}))
        wait_for(browser, tab, "window.facewire.model.held === 1", timeout=30)
        server.send(good)
        wait_for(browser, tab, "window.facewire.model.held === 2", timeout=30)
    finally:
        server.close()
