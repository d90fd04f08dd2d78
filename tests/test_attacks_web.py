"""Attacks on ``facewire web`` and ``facewire receive --view``, run as real processes on
loopback, fed by a real sender (bench fanout's ``LogSender``: lp_d0 encoded by the real
pipeline, the real Responder), attacked from raw sockets (``webattacks``).

Each attack holds its connections for a few seconds while a normal client checks that it is
still served (packets keep coming to a WebSocket viewer, or MJPEG parts to a stream reader,
and the page loads), then leaves. The attacked process must not grow by more than
``MAX_RISE_MB`` nor gain more than ``MAX_THREADS`` threads, must give its memory back within
``webattacks.GIVE_BACK_S`` and must print no traceback.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import resource
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from conftest import free_endpoint
from logsender import encoded_log
from webattacks import (
    KEPT_MB,
    Cost,
    get,
    guess_tokens,
    header_flood,
    idle,
    leave_early,
    measure,
    raw_request,
    reset_mid_request,
    settle,
    tracebacks,
    wait_serving,
)
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from facewire.bench.fanout import LogSender

MAX_RISE_MB = 32.0
MAX_THREADS = 4
TOKEN = "attack-suite-token-0123456789abcdef"


class _Process:
    """``python -m facewire.cli ARGS`` with its stderr in a file; SIGINT at the end."""

    def __init__(self, args: list[str], err: Path, env: dict[str, str] | None = None,
                 open_files: int | None = None) -> None:
        self.err = err

        def limit() -> None:
            if open_files is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (open_files, open_files))

        with open(err, "w") as stderr:
            self.popen = subprocess.Popen(
                [sys.executable, "-m", "facewire.cli", *args], stdout=subprocess.PIPE,
                stderr=stderr, stdin=subprocess.DEVNULL, preexec_fn=limit,
                env={**os.environ, "OPENBLAS_NUM_THREADS": "1", **(env or {})})
        self.pid = self.popen.pid

    def stop(self) -> str:
        """Stop it (SIGINT); its stdout."""
        self.popen.send_signal(2)
        try:
            out, _ = self.popen.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            out, _ = self.popen.communicate()
        return out.decode()


class _Viewer(threading.Thread):
    """A normal page's WebSocket, counting the packets it gets and keeping the newest model
    version announced (``update`` messages)."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        self.ws = connect(url.replace("http://", "ws://"))
        self.packets = 0
        self.serial = 0
        self.start()

    def run(self) -> None:
        with contextlib.suppress(ConnectionClosed):
            for message in self.ws:
                self.packets += isinstance(message, bytes)
                if isinstance(message, str) and (text := json.loads(message))["type"] == \
                        "update":
                    self.serial = max(self.serial, text["serial"])


class _Stream(threading.Thread):
    """A normal browser's ``/stream.mjpg``, counting its bytes."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=30)
        self.sock.sendall(f"GET /stream.mjpg HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n"
                          .encode())
        self.received = 0
        self.start()

    def run(self) -> None:
        with contextlib.suppress(OSError):
            while chunk := self.sock.recv(65536):
                self.received += len(chunk)


def _keeps_coming(count: Callable[[], int], what: str) -> None:
    before = count()
    deadline = time.monotonic() + 5
    while count() <= before:
        assert time.monotonic() < deadline, f"{what} stopped coming during the attack"
        time.sleep(0.05)


def _port() -> int:
    return int(free_endpoint().rsplit(":", 1)[1])


def _judge(cost: Cost, err: Path, name: str) -> None:
    print(cost.line(name))
    assert cost.rss_rise <= MAX_RISE_MB, cost.line(name)
    assert cost.thread_rise <= MAX_THREADS, cost.line(name)
    assert cost.rss_after <= cost.rss_before + KEPT_MB, cost.line(name)
    assert tracebacks(err) == 0, err.read_text(errors="replace")[-3000:]


def _holds_updates(serial: Callable[[], int], person_model: Path, shared_data: Path) -> None:
    """Wait until ``serial()`` (the model version a gateway announced, or a receiver holds)
    is the newest of the sender's log: the versions are the session's memory, not an
    attack's (the log's healing patches take some 50 MB on their way in, which a window that
    met them counted)."""
    newest = max((u.serial for u in encoded_log(person_model, shared_data / "video" /
                                                "lp_d0.mp4").updates), default=0)
    deadline = time.monotonic() + 60
    while (held := serial()) < newest:
        assert time.monotonic() < deadline, f"updates: {held} of {newest} held"
        time.sleep(0.1)


def _fetched_serial(err: Path) -> int:
    """The newest model update a receiver has said it fetched (its status lines in ``err``),
    0 before any."""
    found = re.findall(r"model update (\d+) fetched", err.read_text(errors="replace"))
    return max(map(int, found), default=0)


@pytest.fixture(scope="module")
def sender(person_model: Path, shared_data: Path) -> Iterator[LogSender]:
    log = encoded_log(person_model, shared_data / "video" / "lp_d0.mp4")
    sending = LogSender(log, person_model.read_bytes())
    sending.start()
    yield sending
    sending.stop()


@pytest.fixture(scope="module")
def gateway(sender: LogSender, person_model: Path, shared_data: Path,
            tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[_Process, str, _Viewer]]:
    """``facewire web`` with its token in the environment, and a viewer getting packets,
    measured from once it holds the session's model updates (``_holds_updates``)."""
    folder = tmp_path_factory.mktemp("web")
    port = _port()
    process = _Process(["web", "--connect", sender.endpoint, "--http", f"127.0.0.1:{port}",
                        "--json"], folder / "web.err",
                       env={"FACEWIRE_TOKEN": TOKEN, "FACEWIRE_CACHE": str(folder)})
    url = f"http://127.0.0.1:{port}/?token={TOKEN}"
    wait_serving(url, process.popen, process.err)
    viewer = _Viewer(url.replace("/?", "/stream?"))
    _keeps_coming(lambda: viewer.packets, "packets")
    _holds_updates(lambda: viewer.serial, person_model, shared_data)
    settle(process.pid)
    yield process, url, viewer
    summary = json.loads(process.stop().strip().splitlines()[-1])
    assert TOKEN not in json.dumps(summary)


@pytest.fixture(scope="module")
def view(sender: LogSender, person_model: Path, shared_data: Path,
         tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[_Process, int, _Stream]]:
    """``facewire receive --view``, and a stream reader getting its frames, measured from
    once it holds the session's model updates (``_holds_updates``)."""
    folder = tmp_path_factory.mktemp("view")
    port = _port()
    process = _Process(["receive", "--connect", sender.endpoint, "--view", "--view-port",
                        str(port), "--size", "320x240"], folder / "view.err",
                       env={"FACEWIRE_CACHE": str(folder)})
    wait_serving(f"http://127.0.0.1:{port}/", process.popen, process.err)
    stream = _Stream(port)
    _keeps_coming(lambda: stream.received, "MJPEG parts")
    _holds_updates(lambda: _fetched_serial(process.err), person_model, shared_data)
    settle(process.pid)
    yield process, port, stream
    process.stop()


# --- facewire web ---


def test_web_header_flood_before_the_token_is_bounded(
        gateway: tuple[_Process, str, _Viewer]) -> None:
    process, url, viewer = gateway
    port = int(url.split(":")[2].split("/")[0])

    def meanwhile() -> None:
        _keeps_coming(lambda: viewer.packets, "packets")
        assert get(url)[0] == 200

    cost = measure(process.pid, header_flood(port, "/stream", 300, 126, 8192, 3.0), meanwhile)
    _judge(cost, process.err, "web: 300 x 126 headers of 8 KB")


def test_web_token_guessing_is_throttled_and_the_token_shown_nowhere(
        gateway: tuple[_Process, str, _Viewer]) -> None:
    process, url, viewer = gateway
    base = url.partition("?")[0]
    cost = measure(process.pid, lambda meanwhile: (guess_tokens(base, 4.0), meanwhile()),
                   lambda: (_keeps_coming(lambda: viewer.packets, "packets"),
                            get(url)[0] == 200))
    _judge(cost, process.err, "web: token guessing")
    answered = guess_tokens(base, 3.0)
    assert answered <= 8 * 3 / 1.0 + 8, answered  # each worker waits a second or more
    assert get(url)[0] == 200  # the right token: answered at once whatever the score
    assert TOKEN not in Path(f"/proc/{process.pid}/cmdline").read_text()
    assert TOKEN[:8] not in process.err.read_text()


def test_web_slowloris_path_traversal_token_and_origin_still_hold(
        gateway: tuple[_Process, str, _Viewer]) -> None:
    process, url, viewer = gateway
    port = int(url.split(":")[2].split("/")[0])
    base = url.partition("?")[0]
    for path in ("../etc/passwd", "%2e%2e/%2e%2e/etc/passwd", "model/..%2f..%2fetc%2fpasswd",
                 "web/index.html"):
        assert get(f"{base}{path}?token={TOKEN}")[0] == 404
    assert raw_request(port, f"GET /../../etc/passwd?token={TOKEN} HTTP/1.1\r\nHost: "
                       f"127.0.0.1:{port}\r\n\r\n".encode()).startswith(b"HTTP/1.1 404")
    assert get(base)[0] == 403 and get(f"{base}?token={TOKEN[:-1]}")[0] == 403
    stream = url.replace("http://", "ws://").replace("/?", "/stream?")
    with pytest.raises(InvalidStatus, match="403"):
        connect(stream, origin="http://evil.example")  # type: ignore[arg-type]
    with socket.create_connection(("127.0.0.1", port), timeout=10) as slow:
        start = time.monotonic()
        slow.sendall(b"GET / HT")  # and nothing more: the handshake times out
        assert slow.recv(100) in (b"", b"HTTP/1.1 ")
        assert time.monotonic() - start < 8
    _keeps_coming(lambda: viewer.packets, "packets")
    assert tracebacks(process.err) == 0


def test_web_at_the_open_files_limit_answers_the_page_and_logs_one_line(
        sender: LogSender, person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    """Under ``ulimit -n 128``, with --allow-remote and --host: 200 idle connections, then
    DNS rebinding and duplicate headers."""
    port = _port()
    process = _Process(["web", "--connect", sender.endpoint, "--http", f"127.0.0.1:{port}",
                        "--allow-remote", "--host", "watch.example"], tmp_path / "web.err",
                       env={"FACEWIRE_TOKEN": TOKEN, "FACEWIRE_CACHE": str(tmp_path)},
                       open_files=128)
    url = f"http://127.0.0.1:{port}/?token={TOKEN}"
    try:
        wait_serving(url, process.popen, process.err)
        viewer = _Viewer(url.replace("/?", "/stream?"))
        _keeps_coming(lambda: viewer.packets, "packets")
        _holds_updates(lambda: viewer.serial, person_model, shared_data)
        settle(process.pid)
        cost = measure(process.pid, idle(port, 200, 3.0), lambda: (get(url)[0] == 200
                                                                   or pytest.fail("no page")))
        _judge(cost, process.err, "web (ulimit -n 128): 200 idle connections")
        errors = [line for line in process.err.read_text().splitlines()
                  if "connections:" in line]
        assert len(errors) <= 1, errors  # at most one line per 10 s, none here
        evil = {"Host": f"evil.example:{port}", "Origin": f"http://evil.example:{port}"}
        assert get(url, evil)[0] == 403
        upgrade = raw_request(port, f"GET /stream?token={TOKEN} HTTP/1.1\r\nHost: evil.example:"
                              f"{port}\r\nOrigin: http://evil.example:{port}\r\nUpgrade: "
                              f"websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: "
                              f"dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
                              .encode())
        assert upgrade.startswith(b"HTTP/1.1 403"), upgrade[:100]
        assert get(url, {"Host": f"watch.example:{port}"})[0] == 200
        for twice in ("Host: a.example\r\n", "Origin: http://a.example\r\n" * 2):
            answer = raw_request(port, f"GET /stream?token={TOKEN} HTTP/1.1\r\nHost: 127.0.0.1:"
                                 f"{port}\r\n{twice}\r\n".encode())
            assert answer.startswith(b"HTTP/1.1 400"), answer[:100]
        assert tracebacks(process.err) == 0
    finally:
        process.stop()


# --- facewire receive --view ---


def test_view_slowloris_with_big_headers_is_bounded(
        view: tuple[_Process, int, _Stream]) -> None:
    process, port, stream = view

    def meanwhile() -> None:
        _keeps_coming(lambda: stream.received, "MJPEG parts")
        assert get(f"http://127.0.0.1:{port}/")[0] == 200

    cost = measure(process.pid, header_flood(port, "/", 40, 99, 65536, 3.0), meanwhile)
    _judge(cost, process.err, "view: 40 x 99 headers of 64 KiB, trickled")


def test_view_clients_that_leave_at_once_hold_nothing(
        view: tuple[_Process, int, _Stream]) -> None:
    process, port, stream = view

    def meanwhile() -> None:
        _keeps_coming(lambda: stream.received, "MJPEG parts")
        assert get(f"http://127.0.0.1:{port}/stats.json")[0] == 200

    cost = measure(process.pid, leave_early(port, "/stream.mjpg", 300), meanwhile)
    _judge(cost, process.err, "view: 300 stream clients leaving at once")
    assert cost.threads_after <= cost.threads_before


def test_view_resets_mid_request_print_nothing_and_the_checks_hold(
        view: tuple[_Process, int, _Stream]) -> None:
    process, port, stream = view
    cost = measure(process.pid, reset_mid_request(port, 100),
                   lambda: _keeps_coming(lambda: stream.received, "MJPEG parts"))
    _judge(cost, process.err, "view: 100 resets mid-request")
    base = f"http://127.0.0.1:{port}"
    assert get(f"{base}/", {"Host": f"evil.example:{port}"})[0] == 403
    assert get(f"{base}/../etc/passwd")[0] == 404
    assert raw_request(port, b"GET /../../etc/passwd HTTP/1.0\r\n\r\n").startswith(
        b"HTTP/1.0 403")  # no Host: not a loopback name
    assert raw_request(port, f"GET /%2e%2e/etc/passwd HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n"
                       f"\r\n".encode()).startswith(b"HTTP/1.0 404")
    assert raw_request(port, b"GET / HTTP/1.0\r\nHost: 127.0.0.1\r\nHost: evil.example\r\n"
                       b"\r\n").startswith(b"HTTP/1.0 400")
