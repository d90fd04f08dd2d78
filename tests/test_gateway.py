"""``facewire web``: the browser gateway between a real sender and WebSocket pages, on loopback.

The sender side is a real sender's sockets (``PacketPublisher``, and the control thread
``sender.responder.Responder`` with an ``UpdateStore``) publishing a real log: lp_d0 encoded
by the real sender pipeline with the conftest's model of that person. The gateway runs on a
thread (``serve_gateway``) as ``facewire web`` runs it; the pages are ``websockets`` clients
(and one raw socket that never reads), the HTTP requests ``urllib``'s.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import dataclasses
import gzip
import json
import os
import shutil
import signal
import socket
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import cv2
import numpy as np
import pytest
from conftest import free_endpoint, start
from logsender import encoded_log, hello_for
from sessionlog import session_updates
from webpage import web_dir
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import ClientConnection, connect

from facewire.cli import main
from facewire.models import webmodel
from facewire.models.modelfile import load_model
from facewire.protocol.control import Hello, model_chunks
from facewire.protocol.keys import CurveServer, generate_keys, server_keys
from facewire.protocol.packet import decode, encode
from facewire.protocol.shaper import UpdateShaper
from facewire.protocol.transport import ControlServer, PacketPublisher, control_endpoint
from facewire.receiver.gateway import parse_http, remote_warning, serve_gateway
from facewire.sender.responder import Responder
from facewire.sender.updates import UpdateStore

FAST = (10**9, 1.1, (1e9, 1e9))  # a shaper that holds nothing: the tests are not about rate
TOKEN = "s3cret-T0ken-of-22ch"


class _Sender:
    """A real sender's sockets on ``endpoint``: packets published by ``send``, and the control
    thread answering the Hello, the model's chunks and the updates' (``store``)."""

    def __init__(self, endpoint: str, model_path: Path, hello: Hello,
                 curve: CurveServer | None = None) -> None:
        data = model_path.read_bytes()
        self.store = UpdateStore(hello.model_sha256)
        self.pub = PacketPublisher(endpoint, curve)
        self.server = ControlServer(control_endpoint(endpoint), curve)
        self.responder = Responder(self.server, hello, model_chunks(data, hello.model_sha256),
                                   self.store, UpdateShaper(*FAST))
        self.responder.start()

    def send(self, packets: list[bytes], rate_hz: float = 200.0,
             between: Callable[[int], None] | None = None, batch: int = 1) -> None:
        """Publish ``packets`` at ``rate_hz``, ``batch`` at a time."""
        for i, packet in enumerate(packets):
            self.pub.send(packet)
            if between is not None:
                between(i)
            if (i + 1) % batch == 0:
                time.sleep(batch / rate_hz)

    def close(self) -> None:
        self.responder.stop()
        self.server.close()
        self.pub.close()


class _Page(threading.Thread):
    """A page's WebSocket: every message it gets, in order (``texts`` decoded, ``packets``)."""

    def __init__(self, url: str, **kwargs: Any) -> None:
        super().__init__(daemon=True)
        self.ws: ClientConnection = connect(url.replace("http://", "ws://"), legacy=True,
                                            **kwargs)
        self.messages: list[str | bytes] = []
        self.closed: ConnectionClosed | None = None
        self.start()

    def run(self) -> None:
        try:
            for message in self.ws:
                self.messages.append(message)
        except ConnectionClosed as exc:
            self.closed = exc

    @property
    def texts(self) -> list[dict[str, Any]]:
        return [json.loads(m) for m in list(self.messages) if isinstance(m, str)]

    @property
    def packets(self) -> list[bytes]:
        return [m for m in list(self.messages) if isinstance(m, bytes)]

    def status(self) -> str:
        """The sender's state the last status message gave."""
        return [t for t in self.texts if t["type"] == "status"][-1]["sender"]

    def kinds(self) -> list[str]:
        return [json.loads(m)["type"] if isinstance(m, str) else "packet"
                for m in list(self.messages)]


class _Gateway:
    """``serve_gateway`` on a thread, on 127.0.0.1 and a free port; ``summary`` once
    closed."""

    def __init__(self, connect: str, cache: Path, **kwargs: Any) -> None:
        self.ready = threading.Event()
        self.url = ""
        self.thread, self.stop, self.result = start(
            serve_gateway, connect=connect, http="127.0.0.1:0", cache_dir=str(cache),
            ready=self._ready, **kwargs)
        _until(lambda: self.ready.is_set() or "error" in self.result, "the gateway serves")
        assert "error" not in self.result, self.result

    def _ready(self, url: str) -> None:
        self.url = url
        self.ready.set()

    def at(self, path: str) -> str:
        base, _, query = self.url.partition("?")
        return base.rstrip("/") + path + (f"?{query}" if query else "")

    def page(self, path: str = "/stream", **kwargs: Any) -> _Page:
        return _Page(self.at(path), **kwargs)

    def close(self) -> dict[str, Any]:
        self.stop.set()
        self.thread.join(20)
        assert not self.thread.is_alive() and "error" not in self.result, self.result
        return self.result


def _until(condition: Callable[[], bool], what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting until {what}"
        time.sleep(0.02)


def _get(url: str, headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    request = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=10) as answer:
            return answer.status, dict(answer.headers), answer.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


@pytest.fixture(scope="module")
def stream(person_model: Path, shared_data: Path) -> tuple[Hello, list[bytes]]:
    """The Hello of the conftest's model and lp_d0's packets encoded with it."""
    log = encoded_log(person_model, shared_data / "video" / "lp_d0.mp4")
    return hello_for(person_model, log.hello), [p.tobytes() for p in log.packets]


def _corrupt(packet: bytes) -> list[bytes]:
    """A bad CRC, a wrong size and another protocol version (with its CRC right)."""
    crc = bytearray(packet)
    crc[5] ^= 0x10
    version = bytearray(packet)
    version[0] = (version[0] & 0x0F) | 0x30
    version[-2:] = binascii.crc_hqx(bytes(version[:-2]), 0xFFFF).to_bytes(2, "big")
    return [bytes(crc), packet[:40], bytes(version)]


def test_pages_get_the_model_first_then_every_packet_unchanged_and_in_order(
        person_model: Path, stream: tuple[Hello, list[bytes]], tmp_path: Path) -> None:
    hello, packets = stream
    model = load_model(person_model)
    endpoint = free_endpoint()
    gateway = _Gateway(endpoint, tmp_path / "cache")
    sender = None
    try:
        a = gateway.page()  # before any sender: told so
        _until(lambda: bool(a.texts), "the page is told the status")
        assert a.texts == [{"type": "status", "sender": "waiting",
                            "text": "waiting for the sender"}]
        sender = _Sender(endpoint, person_model, hello)
        b = gateway.page()
        connected = {"type": "status", "sender": "connected", "text": "the sender is connected"}
        _until(lambda: "model" in a.kinds() and "model" in b.kinds() and connected in a.texts,
               "the model is announced and the sender said connected")
        texts = [t for t in a.texts if t["type"] != "clock"]  # clock messages come any time
        assert texts.index(connected) > 0  # after the first status, which said it waits
        assert a.kinds().index("hello") < a.kinds().index("model")
        sent_hello = next(t for t in texts if t["type"] == "hello")
        fields = dataclasses.asdict(hello)
        del fields["clock_origin_s"], fields["voice_origin_s"]  # both go in clock messages
        assert sent_hello == {"type": "hello", **json.loads(json.dumps(fields))}
        announced = next(t for t in texts if t["type"] == "model")
        sha = model.sha256
        assert announced["sha256"] == sha and announced["glb"] == f"/model/{sha}.glb"
        glb, rig = webmodel.model_glb(model), webmodel.rig_bin(model)
        assert announced["bytes"] == len(glb) + len(rig)
        for path, expected in ((announced["glb"], glb), (announced["rig"], rig)):
            status, headers, body = _get(gateway.at(path))
            assert status == 200 and body == expected and "immutable" in headers["Cache-Control"]
            status, headers, body = _get(gateway.at(path), {"Accept-Encoding": "gzip"})
            assert status == 200
            assert (gzip.decompress(body) if headers.get("Content-Encoding") == "gzip"
                    else body) == expected

        # every packet that decodes, as it was sent, in order, to every page; a page that
        # joins midway gets the status, the Hello and the model before its first packet
        late: list[_Page] = []
        bad = _corrupt(packets[10])

        def between(i: int) -> None:
            if i == 10:
                for junk in bad:
                    sender.pub.send(junk)
            if i == 40:
                late.append(gateway.page())

        sender.send(packets, between=between)
        _until(lambda: len(a.packets) >= len(packets) and len(b.packets) >= len(packets)
               and late[0].packets[-1:] == packets[-1:], "every packet arrived")
        assert a.packets == b.packets == packets
        kinds = late[0].kinds()
        assert kinds[:1] == ["status"] and kinds.index("hello") < kinds.index("model") < \
            kinds.index("packet")
        joined = late[0].packets
        assert joined == packets[len(packets) - len(joined):] and len(joined) < len(packets)

        # a model update: announced to the pages, its bytes served under its URL
        data, versions = session_updates(model, 1, regions=("mouth",))
        sender.store.publish_update(1, data[0])
        later = [encode(dataclasses.replace(decode(p), serial=1)) for p in packets[:20]]
        sender.send(later, rate_hz=30)
        _until(lambda: any(t["type"] == "update" for t in a.texts), "the update is announced")
        update = next(t for t in a.texts if t["type"] == "update")
        assert update["serial"] == 1 and update["url"] == f"/model/{sha}/1.upd"
        expected = webmodel.update_bin(versions[0], versions[1])
        status, _, body = _get(gateway.at(update["url"]))
        assert status == 200 and body == expected == webmodel.update_bin(model, versions[1])
        assert update["bytes"] == len(expected)
        c = gateway.page()
        _until(lambda: "update" in c.kinds(), "a new page is told of the update")
        assert c.kinds().index("model") < c.kinds().index("update")
        _until(lambda: len(a.packets) == len(packets) + len(later), "the later packets")
        assert a.packets[len(packets):] == later

        # the sender goes: the pages are told; it comes back, a new session of the same
        # model: the pages are told to start again from the model file
        sender.close()
        sender = None
        _until(lambda: a.status() == "waiting", "the pages are told the sender went")
        told = len(a.messages)
        sender = _Sender(endpoint, person_model, hello)
        _until(lambda: a.kinds()[told:][-1:] == ["status"] and "model" in a.kinds()[told:],
               "the pages are told it is back, with the model to start again from")
        assert a.kinds()[told:] == ["status", "hello", "model", "status"]
        assert a.status() == "connected"
    finally:
        summary = gateway.close()
        if sender is not None:
            sender.close()
    assert summary["forwarded"] == len(packets) + len(later)
    assert summary["corrupt"] == 3 and summary["corrupt_crc"] == summary["corrupt_size"] == \
        summary["corrupt_version"] == 1
    assert summary["model_sha256"] == sha and summary["model_serial"] == 0  # a new session
    assert summary["dropped_junk"] == summary["dropped_slow"] == 0


def _stalled_page(url: str) -> socket.socket:
    """A WebSocket opened by hand that never reads after its handshake (a small receive
    buffer, so that the gateway's side fills soon)."""
    split = urlsplit(url)
    port = split.port
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.sendall(f"GET /stream?{split.query} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                 f"Upgrade: websocket\r\n"
                 f"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                 f"Sec-WebSocket-Version: 13\r\n\r\n".encode())
    assert sock.recv(12) == b"HTTP/1.1 101"
    return sock


def test_pages_that_send_junk_or_do_not_read_are_dropped_and_the_others_get_everything(
        person_model: Path, stream: tuple[Hello, list[bytes]], tmp_path: Path) -> None:
    hello, packets = stream
    endpoint = free_endpoint()
    sender = _Sender(endpoint, person_model, hello)
    gateway = _Gateway(endpoint, tmp_path / "cache")
    try:
        good = gateway.page()
        _until(lambda: "model" in good.kinds(), "the model is announced")
        big, chatty = gateway.page(), gateway.page()
        stalled = _stalled_page(gateway.url)
        big.ws.send(b"x" * 1000)
        with contextlib.suppress(ConnectionClosed):  # dropped at its first message
            for _ in range(10):
                chatty.ws.send("hi")
        # 3000 packets (135 kB of frames) fill the stalled page's buffers, and the good
        # page still gets every one, in order
        burst = [encode(dataclasses.replace(decode(packets[i % len(packets)]), seq=i))
                 for i in range(3000)]
        sender.send(burst, rate_hz=4000, batch=20)
        _until(lambda: len(good.packets) >= len(burst), "the good page has every packet",
               timeout=60)
        assert good.packets == burst
        big.join(10)
        chatty.join(10)
        assert big.closed is not None and big.closed.rcvd is not None and \
            big.closed.rcvd.code == 1009
        assert chatty.closed is not None and chatty.closed.rcvd is not None and \
            chatty.closed.rcvd.code == 1008
        stalled.settimeout(10)  # cut off: it reads to the end, and lacks what was not sent
        got = 0
        with contextlib.suppress(ConnectionResetError):
            while chunk := stalled.recv(65536):
                got += len(chunk)
        assert got < len(b"".join(burst))
        assert good.closed is None
    finally:
        summary = gateway.close()
        sender.close()
    assert summary["dropped_junk"] == 2 and summary["dropped_slow"] == 1
    assert summary["forwarded"] == len(burst)


def test_no_sender_means_waiting_and_every_request_needs_the_token_and_a_loopback_host(
        tmp_path: Path) -> None:
    gateway = _Gateway(free_endpoint(), tmp_path / "cache", token=TOKEN)
    try:
        assert gateway.url.endswith(f"/?token={TOKEN}")
        page = gateway.page()
        _until(lambda: bool(page.texts), "the page is told the status")
        assert page.texts[0] == {"type": "status", "sender": "waiting",
                                 "text": "waiting for the sender"}
        base = gateway.url.partition("?")[0]
        stream = base.replace("http://", "ws://") + "stream"
        for url in (stream, f"{stream}?token=wrong", f"{stream}?token={TOKEN}x",
                    f"{stream}?token={TOKEN[:-1]}"):
            with pytest.raises(InvalidStatus, match="403"):
                connect(url)
        with pytest.raises(InvalidStatus, match="403"):  # another site's page
            connect(f"{stream}?token={TOKEN}", origin="http://evil.example")
        assert _get(base)[0] == 403
        assert _get(f"{base}model/{'0' * 64}.glb?token=wrong")[0] == 403
        assert _get(f"{base}model/{'0' * 64}.glb?token={TOKEN}")[0] == 404
        assert _get(f"{base}../etc/passwd?token={TOKEN}")[0] == 404
        status, _, body = _get(f"{base}?token={TOKEN}", {"Host": "rebound.example:80"})
        assert status == 403 and b"loopback" in body
        index = web_dir() / "index.html"
        status, headers, body = _get(f"{base}?token={TOKEN}")
        if index.is_file():
            assert status == 200 and body == index.read_bytes()
            assert headers["Content-Type"].startswith("text/html")
        else:
            assert status == 404  # the page's files are not installed in this checkout
    finally:
        summary = gateway.close()
    assert summary["forwarded"] == 0 and summary["model_sha256"] is None
    assert summary["http_refused"] >= 10
    assert summary["url"].endswith("?token=s3cr...") and TOKEN not in json.dumps(summary)


def test_another_model_holds_the_packets_back_until_the_pages_are_told_of_it(
        person_model: Path, generic_model: Path, stream: tuple[Hello, list[bytes]],
        tmp_path: Path) -> None:
    hello, packets = stream
    endpoint = free_endpoint()
    gateway = _Gateway(endpoint, tmp_path / "cache")
    sender = _Sender(endpoint, generic_model, hello_for(generic_model, hello))
    try:
        page = gateway.page()
        _until(lambda: "model" in page.kinds(), "the first model is announced")
        sender.send(packets[:10])
        _until(lambda: len(page.packets) == 10, "the first sender's packets")
        told = len(page.messages)
        sender.close()
        sender = _Sender(endpoint, person_model, hello)  # a restarted sender, another model
        time.sleep(0.3)  # the gateway's packet socket connects again (every 0.1 s)
        sender.send(packets[:10])  # numbered from 0 again: the gateway asks for the Hello
        _until(lambda: page.kinds().count("model") == 2, "the second model is announced")
        sender.send(packets[10:])
        _until(lambda: page.packets[-1:] == packets[-1:], "the second sender's packets")
        models = [t for t in page.texts if t["type"] == "model"]
        assert [m["sha256"] for m in models] == [load_model(generic_model).sha256,
                                                 load_model(person_model).sha256]
        after = page.kinds()[told:]
        model_at = after.index("model")
        assert after.index("hello") < model_at and "packet" not in after[:model_at]
        assert page.packets[-(len(packets) - 10):] == packets[10:]  # all sent after it
    finally:
        summary = gateway.close()
        sender.close()
    # the new sender's first packets: held until its Hello said whose they are (or lost
    # while the gateway's socket connected to the new sender)
    assert 10 + len(packets) - 10 <= summary["forwarded"] + summary["held"] <= 10 + len(packets)


def test_with_keys_the_gateway_gets_the_stream_and_the_model_over_curve(
        person_model: Path, stream: tuple[Hello, list[bytes]], tmp_path: Path) -> None:
    hello, packets = stream
    for name in ("sender", "gateway"):
        generate_keys(tmp_path / name)
    shutil.copy(tmp_path / "gateway/id.key", tmp_path / "sender/authorized/gateway.key")
    shutil.copy(tmp_path / "sender/id.key", tmp_path / "gateway/authorized/sender.key")
    endpoint = free_endpoint()
    sender = _Sender(endpoint, person_model, hello, server_keys(tmp_path / "sender"))
    gateway = _Gateway(endpoint, tmp_path / "cache", curve_dir=str(tmp_path / "gateway"))
    try:
        page = gateway.page()
        _until(lambda: "model" in page.kinds(), "the model is announced")
        sender.send(packets[:10])
        _until(lambda: len(page.packets) == 10, "the packets")
        assert page.packets == packets[:10]
    finally:
        gateway.close()
        sender.close()


def test_the_real_page_in_chromium_plays_what_the_gateway_forwards(
        person_model: Path, stream: tuple[Hello, list[bytes]], tmp_path: Path) -> None:
    """The page (receiver/web) in headless Chromium with WebGL2, behind a token, fed by the
    gateway: it loads the model the gateway serves, decodes every packet forwarded (none of
    the corrupt ones reach it) and draws a face."""
    from browser import WEBGL_FLAGS, DevTools, find_chromium
    from webpage import open_tab

    hello, packets = stream
    endpoint = free_endpoint()
    sender = _Sender(endpoint, person_model, hello)
    gateway = _Gateway(endpoint, tmp_path / "cache", token=TOKEN)
    browser = DevTools(find_chromium(), tmp_path / "profile", tmp_path / "chromium.log",
                       WEBGL_FLAGS)
    try:
        tab = open_tab(browser, gateway.url, "window.facewire !== undefined && "
                       "window.facewire.model.held === 1", timeout=60)
        bad = _corrupt(packets[5])
        sender.send(packets[:40], rate_hz=30,
                    between=lambda i: [sender.pub.send(b) for b in bad] if i == 5 else None)
        counts = "window.facewire.counts"
        _until(lambda: browser.evaluate(tab, f"{counts}.decoded") == 40, "the page decoded all",
               timeout=30)
        assert sum(browser.evaluate(tab, f"{counts}.corrupt").values()) == 0
        shot = browser.call("Page.captureScreenshot", {"format": "png"}, session=tab)["data"]
        image = cv2.imdecode(np.frombuffer(base64.b64decode(shot), np.uint8), cv2.IMREAD_COLOR)
        rect = browser.evaluate(tab, "JSON.stringify(document.querySelector('canvas')"
                                ".getBoundingClientRect())")
        box = json.loads(rect)
        x, y, w, h = (round(box[k]) for k in ("x", "y", "width", "height"))
        middle = image[y + h // 4:y + 3 * h // 4, x + w // 3:x + 2 * w // 3].astype(int)
        assert middle.std() > 10 and middle.mean() > 40  # a textured face, not an empty canvas
    finally:
        browser.close()
        summary = gateway.close()
        sender.close()
    assert summary["forwarded"] == 40 and summary["corrupt"] == 3
    assert summary["http_served"] >= 3  # the page, its modules, the model


def test_the_command_refuses_a_remote_address_unless_asked_and_stops_on_sigterm(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FACEWIRE_CACHE", str(tmp_path / "cache"))
    endpoint = free_endpoint()
    assert main(["web", "--connect", endpoint, "--http", "0.0.0.0:0"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "--allow-remote" in err
    assert main(["web", "--connect", endpoint, "--token", "no spaces"]) == 2
    assert "--token" in capsys.readouterr().err
    monkeypatch.setenv("FACEWIRE_TOKEN", "15-characters--")  # under 16: refused
    assert main(["web", "--connect", endpoint]) == 2
    assert "FACEWIRE_TOKEN: expected 16 to 256" in capsys.readouterr().err
    monkeypatch.delenv("FACEWIRE_TOKEN")
    (tmp_path / "short").write_text("a\n")
    assert main(["web", "--connect", endpoint, "--token-file", str(tmp_path / "short")]) == 2
    assert "short: expected 16 to 256" in capsys.readouterr().err
    assert main(["web", "--connect", endpoint, "--host", "watch.example"]) == 2
    assert "--host: only with --allow-remote" in capsys.readouterr().err
    assert parse_http("0.0.0.0:8080", allow_remote=True) == ("0.0.0.0", 8080)
    assert parse_http("[::1]:0", allow_remote=False) == ("::1", 0)
    warning = remote_warning("0.0.0.0")
    assert warning is not None and "unencrypted" in warning and "token" in warning
    assert remote_warning("localhost") is None
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        assert main(["web", "--connect", endpoint, "--http", f"127.0.0.1:{port}"]) == 2
    assert f"127.0.0.1:{port}: cannot serve there" in capsys.readouterr().err
    timer = threading.Timer(1.5, os.kill, (os.getpid(), signal.SIGTERM))
    timer.start()
    assert main(["web", "--connect", endpoint, "--http", "127.0.0.1:0", "--json"]) == 0
    out, err = capsys.readouterr()
    assert "open file://" in err and "waiting for a sender" in err
    opener = Path(err.split("open file://", 1)[1].split(" ", 1)[0])
    assert not opener.exists()  # removed at the end: its token was for that run only
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["forwarded"] == 0 and summary["seconds"] < 10
    assert summary["url"].startswith("http://127.0.0.1:") and summary["url"].endswith("...")
