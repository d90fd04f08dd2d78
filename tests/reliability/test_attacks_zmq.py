"""Attacks on the ZeroMQ ports of real ``facewire send`` and ``facewire relay`` processes by a
peer that is not authenticated (issue 26, items 1 to 5 and 13; docs/DESIGN.md, the threat
model).

The attacked processes are real (``cliprocess.Facewire``) on loopback: a sender looping a grey
clip with a 3 MB model (12 chunks), one under CURVE, and a relay in front of the plain one.
The attackers are real sockets: pyzmq's own, or raw TCP speaking ZMTP by hand (``rawzmtp``)
to send what libzmq never would (a frame header declaring 1 GiB, one message of endless
frames, requests from a peer that never reads its replies).

Each attack (``Attack.run``) first reads the process's resident memory and thread count (the
most over ``BASELINE_S``), then runs with a normal client (a ``PacketSubscriber``) receiving
packets alongside (for at least ``CLIENT_S``), sampling both every 20 ms; once the attacking
peer has left, it waits up to ``GIVE_BACK_S`` for the memory to come back within ``BACK_MB``
of where it was. It asserts that the memory rose by at most ``MAX_RISE_MB``, the threads by
at most ``MAX_THREADS``, that the memory was given back, that the client kept receiving
packets, and (at the end of the module, ``Facewire.summary``) that the process printed no
traceback and stopped cleanly. Each attack's figures are printed (``pytest -s`` shows them).
Under CURVE a peer that has not finished its handshake costs at most
``CURVE_PER_CONNECTION_MB`` per connection.

What libzmq cannot bound without CURVE (one message of endless frames, distinct
subscriptions: ``protocol.transport``) is attacked only before a CURVE handshake here: a
sender or relay that would listen without CURVE beyond loopback stops with one line unless
``--insecure`` is given (``test_plaintext_beyond_loopback_needs_insecure``).
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
from cliprocess import Facewire
from conftest import free_endpoint, write_video
from rawzmtp import GIGABYTE, connect_as_dealer, connect_raw, frame, handshake, ready, stream

from facewire.bench.procfs import rss_mb, thread_count
from facewire.protocol.control import HelloRequest, ModelRequest
from facewire.protocol.keys import client_keys, generate_keys
from facewire.protocol.transport import ControlClient, PacketSubscriber, control_endpoint

MAX_RISE_MB = 32.0
MAX_THREADS = 4
GIVE_BACK_S = 5.0
BACK_MB = 8.0
CURVE_PER_CONNECTION_MB = 1.0
ATTACK_S = 4.0  # the longest an attacking peer stays connected
SAMPLE_S = 0.02
BASELINE_S = 1.5  # longer than one pass of the clip
CLIENT_S = 2.0  # the client counts packets for at least this long from the attack's start


def _port(endpoint: str) -> int:
    return int(endpoint.rsplit(":", 1)[1])


class Attack:
    """The measure of one attack on one process (module docstring)."""

    def __init__(self, name: str, process: Facewire, client_at: str,
                 client_curve: Path | None = None) -> None:
        self.name, self.process, self.pid = name, process, process.process.pid
        self.client_at, self.client_curve = client_at, client_curve
        self.rise_mb = self.left_mb = 0.0
        self.threads = self.packets = 0

    def run(self, attack: Callable[[], None]) -> Attack:
        """Run ``attack`` (it returns once its peer has left) and measure (module docstring)."""
        curve = client_keys(self.client_curve) if self.client_curve is not None else None
        base_rss, base_threads = self._baseline()
        peak = [base_rss, base_threads]
        done = threading.Event()
        packets = [0]

        def watch() -> None:
            with PacketSubscriber(self.client_at, curve) as client:
                while not done.is_set():
                    peak[0] = max(peak[0], rss_mb(self.pid))
                    peak[1] = max(peak[1], thread_count(self.pid))
                    packets[0] += client.recv(round(SAMPLE_S * 1000)) is not None

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        time.sleep(0.5)  # the client joins
        joined, began = packets[0], time.monotonic()
        try:
            attack()
            time.sleep(max(0.0, began + CLIENT_S - time.monotonic()))
        finally:
            done.set()
            watcher.join()
        deadline = time.monotonic() + GIVE_BACK_S
        while rss_mb(self.pid) > base_rss + BACK_MB and time.monotonic() < deadline:
            time.sleep(0.1)
        self.rise_mb, self.threads = peak[0] - base_rss, peak[1] - base_threads
        self.left_mb, self.packets = rss_mb(self.pid) - base_rss, packets[0] - joined
        print(f"\nattack {self.name}: rss +{self.rise_mb:.1f} MB at most, +{self.left_mb:.1f} MB "
              f"{GIVE_BACK_S:g} s after; threads +{self.threads}; client packets "
              f"{self.packets}")
        return self

    def _baseline(self) -> tuple[float, int]:
        """The most memory and threads over ``BASELINE_S`` (the clip's decoding threads come
        and go with each pass)."""
        rss, threads = 0.0, 0
        deadline = time.monotonic() + BASELINE_S
        while time.monotonic() < deadline:
            rss, threads = max(rss, rss_mb(self.pid)), max(threads, thread_count(self.pid))
            time.sleep(SAMPLE_S)
        return rss, threads

    def check(self) -> None:
        assert self.process.process.poll() is None, self.process.text()[-2000:]
        assert self.rise_mb <= MAX_RISE_MB, f"{self.name}: +{self.rise_mb:.1f} MB"
        assert self.threads <= MAX_THREADS, f"{self.name}: +{self.threads} threads"
        assert self.left_mb <= BACK_MB, f"{self.name}: {self.left_mb:.1f} MB kept"
        assert self.packets >= 10, f"{self.name}: the client got {self.packets} packets"


# -- the attacked processes --------------------------------------------------------------------

@pytest.fixture(scope="module")
def material(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 MB model (the generic head, a noise texture: 12 chunks), a grey clip, and keys:
    ``sender`` admits ``good``; ``good`` and ``stranger`` trust the sender."""
    from facewire.models.geometry import Intrinsics
    from facewire.models.head import generic_head
    from facewire.models.manifest import ModelInfo
    from facewire.models.modelfile import PersonModel, save_model

    folder = tmp_path_factory.mktemp("attacks")
    noise = np.random.default_rng(26).integers(0, 256, (1024, 1024, 3), np.uint8)
    save_model(PersonModel(mesh=generic_head(), texture=noise,
                           camera=Intrinsics(640.0, 640.0, 319.5, 239.5, 640, 480),
                           info=ModelInfo(name="noise")), folder / "big.fwm")
    write_video(folder / "grey.mp4", [np.full((120, 160, 3), 128, np.uint8)] * 30)
    for name in ("sender", "good", "stranger"):
        generate_keys(folder / name)
    shutil.copy(folder / "good/id.key", folder / "sender/authorized/good.key")
    for name in ("good", "stranger"):
        shutil.copy(folder / "sender/id.key", folder / f"{name}/authorized/sender.key")
    return folder


def _sender(material: Path, *extra: str) -> Iterator[tuple[Facewire, str]]:
    at = free_endpoint()
    process = Facewire("send", "--model", str(material / "big.fwm"), "--source",
                       str(material / "grey.mp4"), "--loop", "--no-learn", "--bind", at,
                       *extra, "--json", cache=material / "cache")
    try:
        process.wait_for("publishing on")
        time.sleep(1.0)  # settled: the model split, the first frames sent
        yield process, at
        process.interrupt()
        process.summary()  # exit 0, no traceback
    finally:
        process.close()


@pytest.fixture(scope="module")
def sender(material: Path) -> Iterator[tuple[Facewire, str]]:
    yield from _sender(material)


@pytest.fixture(scope="module")
def curve_sender(material: Path) -> Iterator[tuple[Facewire, str]]:
    yield from _sender(material, "--curve-dir", str(material / "sender"))


@pytest.fixture(scope="module")
def relay(material: Path, sender: tuple[Facewire, str]) -> Iterator[tuple[Facewire, str]]:
    at = free_endpoint()
    process = Facewire("relay", "--in", sender[1], "--out", at, "--json",
                       cache=material / "cache")
    try:
        process.wait_for("facewire relay:")
        time.sleep(1.0)
        yield process, at
        process.interrupt()
        process.summary()
    finally:
        process.close()


# -- the attacks -------------------------------------------------------------------------------

def gigabyte_frame(port: int, mechanism: bytes = b"NULL", socket_type: bytes = b"SUB"
                   ) -> Callable[[], None]:
    """A frame header declaring 1 GiB, then up to 300 MiB of it (after the handshake, or with
    CURVE right after the greeting)."""
    def attack() -> None:
        if mechanism == b"NULL":
            conn = socket.create_connection(("127.0.0.1", port), timeout=10)
            handshake(conn, socket_type, as_server=False)
        else:
            conn = connect_raw(port, mechanism)
        with conn:
            conn.sendall(b"\x02" + GIGABYTE.to_bytes(8, "big"))
            stream(conn, bytes(1 << 20), 300 << 20, ATTACK_S)
    return attack


def endless_message(port: int, mechanism: bytes) -> Callable[[], None]:
    """One message of endless 1000-byte frames (MORE set on each: each under every frame
    limit), up to 300 MiB."""
    def attack() -> None:
        with connect_raw(port, mechanism) as conn:
            if mechanism == b"NULL":
                conn.sendall(ready(b"DEALER"))
            stream(conn, frame(bytes(1000), more=True) * 1000, 300 << 20, ATTACK_S)
    return attack


def subscriptions(port: int, topics: list[bytes]) -> Callable[[], None]:
    """A raw SUB peer subscribing to ``topics`` (ZMTP 3.0: a message of 1 and the topic),
    connected for 2 s (raw: libzmq's own SUB builds a trie of a long topic recursively)."""
    def attack() -> None:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:
            handshake(conn, b"SUB", as_server=False)
            stream(conn, b"".join(frame(b"\x01" + topic) for topic in topics), 1, ATTACK_S)
            time.sleep(2.0)
    return attack


def unread_chunks(port: int, sha256: str, connections: int = 3, requests: int = 1000
                  ) -> Callable[[], None]:
    """``connections`` raw DEALERs each asking ``requests`` model chunks, never reading a
    reply, for ``ATTACK_S``."""
    def attack() -> None:
        conns = [connect_as_dealer(port) for _ in range(connections)]
        try:
            for conn in conns:
                conn.setblocking(False)
                ask = b"".join(frame(b"", more=True) + frame(msgpack.packb(
                    {"type": ModelRequest.TYPE, "sha256": sha256, "index": i % 12}))
                    for i in range(requests))
                try:
                    conn.sendall(ask)
                except BlockingIOError:
                    pass  # the sender reads no further: it holds what it took
            time.sleep(ATTACK_S)
        finally:
            for conn in conns:
                conn.close()
    return attack


def handshakes(ports: list[int], connections: int) -> Callable[[], None]:
    """``connections`` raw TCP peers per port, each with a CURVE greeting and no more."""
    def attack() -> None:
        conns = [connect_raw(port, b"CURVE") for port in ports for _ in range(connections)]
        time.sleep(2.0)
        for conn in conns:
            conn.close()
    return attack


def _model_sha256(at: str) -> str:
    with ControlClient(control_endpoint(at)) as client:
        hello = client.request(HelloRequest(), 5000)
    assert hello is not None
    return hello.model_sha256  # type: ignore[union-attr]


def test_a_gigabyte_frame_to_the_packet_port(sender: tuple[Facewire, str]) -> None:
    process, at = sender
    Attack("1 GiB frame, packet port", process, at).run(gigabyte_frame(_port(at))).check()


def test_a_gigabyte_frame_to_the_packet_port_before_the_curve_handshake(
        curve_sender: tuple[Facewire, str], material: Path) -> None:
    process, at = curve_sender
    for port in (_port(at), _port(at) + 1):
        Attack(f"1 GiB frame before CURVE, port {port - _port(at)}", process, at,
               material / "good").run(gigabyte_frame(port, b"CURVE")).check()


def test_one_endless_message_before_the_curve_handshake(
        curve_sender: tuple[Facewire, str], material: Path) -> None:
    process, at = curve_sender
    for port in (_port(at), _port(at) + 1):
        Attack(f"endless message before CURVE, port {port - _port(at)}", process, at,
               material / "good").run(endless_message(port, b"CURVE")).check()


def test_curve_handshakes_cost_little(curve_sender: tuple[Facewire, str],
                                      material: Path) -> None:
    process, at = curve_sender
    per_port = 100
    attack = Attack("200 CURVE greetings", process, at, material / "good")
    attack.run(handshakes([_port(at), _port(at) + 1], per_port)).check()
    assert attack.rise_mb <= 2 * per_port * CURVE_PER_CONNECTION_MB


def test_a_long_subscription(sender: tuple[Facewire, str]) -> None:
    process, at = sender
    Attack("2 MiB subscription", process, at).run(
        subscriptions(_port(at), [b"x" * (2 << 20)])).check()


def test_model_chunks_never_read(sender: tuple[Facewire, str]) -> None:
    process, at = sender
    Attack("3 peers x 1000 chunk requests, unread", process, at).run(
        unread_chunks(_port(at) + 1, _model_sha256(at))).check()


def test_the_relay_a_gigabyte_frame(relay: tuple[Facewire, str]) -> None:
    process, at = relay
    Attack("relay: 1 GiB frame, packet port", process, at).run(
        gigabyte_frame(_port(at))).check()
    Attack("relay: 1 GiB frame, control port", process, at).run(
        gigabyte_frame(_port(at) + 1, socket_type=b"DEALER")).check()


def test_subscriptions_at_the_relay_never_reach_the_sender(
        sender: tuple[Facewire, str], relay: tuple[Facewire, str]) -> None:
    """The relay keeps its peers' subscriptions (libzmq does) but sends the sender only its
    own: 2000 distinct ones at the relay cost the sender nothing."""
    topics = [i.to_bytes(4, "big") * 250 for i in range(2000)]
    Attack("relay: 2000 subscriptions, the sender measured", sender[0], relay[1]).run(
        subscriptions(_port(relay[1]), topics)).check()


def test_the_relay_model_chunks_never_read(relay: tuple[Facewire, str]) -> None:
    process, at = relay
    Attack("relay: 3 peers x 1000 chunk requests, unread", process, at).run(
        unread_chunks(_port(at) + 1, _model_sha256(at))).check()


# -- refused starts ----------------------------------------------------------------------------

@pytest.mark.parametrize("command", [
    ["send", "--model", "m.fwm", "--source", "v.mp4", "--bind", "tcp://0.0.0.0:{port}"],
    ["relay", "--in", "tcp://127.0.0.1:{port}", "--out", "tcp://0.0.0.0:{port}"],
])
def test_plaintext_beyond_loopback_needs_insecure(command: list[str]) -> None:
    port = str(_port(free_endpoint()))
    args = [a.replace("{port}", port) for a in command]
    result = subprocess.run([sys.executable, "-m", "facewire.cli", *args], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert "--insecure" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr

