"""ZeroMQ transport over real sockets on 127.0.0.1: PUB/SUB, ROUTER/DEALER, CURVE, framing."""

from __future__ import annotations

import shutil
import socket
import threading
import time
from pathlib import Path

import pytest

from facewire.protocol.control import Error, HelloRequest, decode_message
from facewire.protocol.keys import KeyFileError, client_keys, generate_keys, server_keys
from facewire.protocol.packet import PACKET_BYTES, Frame, decode, encode
from facewire.protocol.transport import (
    WIRE_OVERHEAD,
    ControlClient,
    ControlServer,
    PacketPublisher,
    PacketSubscriber,
    TransportError,
    control_endpoint,
    free_loopback_endpoint,
)

ANY_PORT = "tcp://127.0.0.1:*"


def _wait_joined(pub: PacketPublisher, sub: PacketSubscriber, timeout: float = 5.0) -> bool:
    """Publish probes until the subscriber gets one (PUB/SUB joins asynchronously)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        pub.send(encode(Frame(seq=0)))
        if sub.recv(50) is not None:
            while sub.recv(50) is not None:
                pass
            return True
    return False


def test_pub_sub_delivers_every_packet_in_order() -> None:
    with PacketPublisher(ANY_PORT) as pub, PacketSubscriber(pub.endpoint) as sub:
        assert _wait_joined(pub, sub)
        for i in range(1, 61):
            pub.send(encode(Frame(seq=i)))
        got = [decode(p).seq for p in iter(lambda: sub.recv(500), None)]
        assert got == list(range(1, 61))


def test_subscriber_without_sender_times_out() -> None:
    with PacketSubscriber("tcp://127.0.0.1:1") as sub:
        assert sub.recv(100) is None


def test_router_dealer_request_reply() -> None:
    with ControlServer(ANY_PORT) as server, ControlClient(server.endpoint) as client:
        def answer() -> None:
            request = server.recv(5000)
            assert request is not None
            server.reply(request[0], Error(f"got {decode_message(request[1])!r}"))

        thread = threading.Thread(target=answer)
        thread.start()
        reply = client.request(HelloRequest(), 5000)
        thread.join()
        assert reply == Error("got HelloRequest()")


def test_control_endpoint_is_port_plus_one() -> None:
    assert control_endpoint("tcp://10.0.0.2:5555") == "tcp://10.0.0.2:5556"
    assert control_endpoint("tcp://*:7000") == "tcp://*:7001"
    with pytest.raises(TransportError):
        control_endpoint("udp://host:1")


def test_port_in_use_is_a_clear_error() -> None:
    with PacketPublisher(ANY_PORT) as pub:
        with pytest.raises(TransportError, match="cannot bind"):
            PacketPublisher(pub.endpoint)


@pytest.fixture()
def keys(tmp_path: Path) -> Path:
    """Sender keys trusting 'good'; 'good' and 'stranger' both trust the sender."""
    for name in ("sender", "good", "stranger", "impostor"):
        generate_keys(tmp_path / name)
    shutil.copy(tmp_path / "good/id.key", tmp_path / "sender/authorized/good.key")
    for name in ("good", "stranger"):
        shutil.copy(tmp_path / "sender/id.key", tmp_path / f"{name}/authorized/sender.key")
    # 'impostor' is authorised by the sender but expects another server key.
    shutil.copy(tmp_path / "impostor/id.key", tmp_path / "sender/authorized/impostor.key")
    shutil.copy(tmp_path / "stranger/id.key", tmp_path / "impostor/authorized/wrong.key")
    return tmp_path


def test_curve_admits_only_authorised_clients(keys: Path) -> None:
    with PacketPublisher(ANY_PORT, server_keys(keys / "sender")) as pub, \
            PacketSubscriber(pub.endpoint, client_keys(keys / "good")) as good, \
            PacketSubscriber(pub.endpoint, client_keys(keys / "stranger")) as stranger, \
            PacketSubscriber(pub.endpoint, client_keys(keys / "impostor")) as impostor:
        assert _wait_joined(pub, good)
        time.sleep(0.3)
        for i in range(1, 11):
            pub.send(encode(Frame(seq=i)))
        assert [decode(p).seq for p in iter(lambda: good.recv(500), None)] == list(range(1, 11))
        assert stranger.recv(300) is None  # unknown client key: refused
        assert impostor.recv(300) is None  # wrong server key: handshake fails


def test_curve_control_channel(keys: Path) -> None:
    with ControlServer(ANY_PORT, server_keys(keys / "sender")) as server, \
            ControlClient(server.endpoint, client_keys(keys / "good")) as good, \
            ControlClient(server.endpoint, client_keys(keys / "stranger")) as stranger:
        def answer() -> None:
            request = server.recv(5000)
            if request is not None:
                server.reply(request[0], Error("welcome"))

        thread = threading.Thread(target=answer)
        thread.start()
        assert good.request(HelloRequest(), 5000) == Error("welcome")
        thread.join()
        assert stranger.request(HelloRequest(), 500) is None


@pytest.mark.parametrize("mode", ["plain", "curve"])
def test_a_closed_server_frees_its_address_at_once(mode: str, keys: Path) -> None:
    """Servers opened on the same ports right after they closed bind, while receivers stay
    connected (a sender restarted), and with CURVE a packet and a control server, each with its
    own authenticator, live side by side: libzmq closes a socket later, on its reaper thread,
    and ending the socket's context waits for that."""
    server_curve = server_keys(keys / "sender") if mode == "curve" else None
    client_curve = client_keys(keys / "good") if mode == "curve" else None
    endpoint = free_loopback_endpoint()
    with PacketSubscriber(endpoint, client_curve), \
            ControlClient(control_endpoint(endpoint), client_curve):
        for _ in range(30):
            with PacketPublisher(endpoint, server_curve) as pub, \
                    ControlServer(control_endpoint(endpoint), server_curve):
                for _ in range(5):
                    pub.send(encode(Frame(seq=0)))
                    time.sleep(0.002)


def test_keys_refuse_overwrite_and_missing(tmp_path: Path) -> None:
    generate_keys(tmp_path / "k")
    with pytest.raises(KeyFileError, match="already exists"):
        generate_keys(tmp_path / "k")
    with pytest.raises(KeyFileError, match="exactly one sender public key"):
        client_keys(tmp_path / "k")
    with pytest.raises(KeyFileError, match="missing"):
        server_keys(tmp_path / "nothing")


def _counting_relay(target_port: int, counter: dict[str, int]) -> int:
    """A TCP relay on loopback counting the bytes sent toward the subscriber."""
    listener = socket.create_server(("127.0.0.1", 0))

    def pump(src: socket.socket, dst: socket.socket, key: str | None) -> None:
        while data := _recv(src):
            if key:
                counter[key] += len(data)
            try:
                dst.sendall(data)
            except OSError:
                return

    def serve() -> None:
        conn, _ = listener.accept()
        upstream = socket.create_connection(("127.0.0.1", target_port))
        threading.Thread(target=pump, args=(upstream, conn, "down"), daemon=True).start()
        threading.Thread(target=pump, args=(conn, upstream, None), daemon=True).start()

    threading.Thread(target=serve, daemon=True).start()
    return listener.getsockname()[1]


def _recv(s: socket.socket) -> bytes:
    try:
        return s.recv(65536)
    except OSError:
        return b""


@pytest.mark.parametrize("mode", ["plain", "curve"])
def test_wire_overhead_per_packet_is_measured(mode: str, keys: Path) -> None:
    counter = {"down": 0}
    server = server_keys(keys / "sender") if mode == "curve" else None
    client = client_keys(keys / "good") if mode == "curve" else None
    with PacketPublisher(ANY_PORT, server) as pub:
        port = _counting_relay(int(pub.endpoint.rsplit(":", 1)[1]), counter)
        with PacketSubscriber(f"tcp://127.0.0.1:{port}", client) as sub:
            assert _wait_joined(pub, sub)
            time.sleep(0.2)
            before = counter["down"]
            n = 200
            for i in range(n):  # one at a time: the count includes no batching effects
                pub.send(encode(Frame(seq=i)))
                assert sub.recv(2000) is not None
            time.sleep(0.1)
            per_packet = (counter["down"] - before) / n
    assert per_packet == PACKET_BYTES + WIRE_OVERHEAD[mode]
