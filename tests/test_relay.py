"""The relay over real ZeroMQ sockets on 127.0.0.1: fan-out of packets, control through it."""

from __future__ import annotations

import hashlib
import threading
import time
from pathlib import Path

from conftest import free_endpoint, start

from facewire.protocol.control import (
    Camera,
    ChunkAssembler,
    Hello,
    HelloRequest,
    ModelChunk,
    ModelRequest,
    decode_message,
)
from facewire.protocol.log import read_log
from facewire.protocol.packet import Frame, decode, encode
from facewire.protocol.relay import relay
from facewire.protocol.transport import (
    ControlClient,
    ControlServer,
    PacketPublisher,
    PacketSubscriber,
    control_endpoint,
)
from facewire.sender.sender import send

SETTLE_S = 5.0


def settle(pub: PacketPublisher, subs: list[PacketSubscriber]) -> None:
    """Publish probes (seq 0) until every subscriber has one, then drain them all."""
    end = time.monotonic() + SETTLE_S
    joined = [False] * len(subs)
    while not all(joined) and time.monotonic() < end:
        pub.send(encode(Frame(seq=0)))
        for i, sub in enumerate(subs):
            joined[i] = joined[i] or sub.recv(20) is not None
    assert all(joined), "subscriptions did not reach the sender through the relay"
    time.sleep(0.2)
    for sub in subs:
        while sub.recv(50) is not None:
            pass


HELLO = Hello(model_sha256="ab" * 32, model_bytes=1000, rate_hz=30.0,
              camera=Camera(640.0, 640.0, 319.5, 239.5, 640, 480), regions=("mouth",))


def test_three_receivers_through_a_relay_get_every_packet_and_the_hello() -> None:
    sender, out = free_endpoint(), free_endpoint()
    with PacketPublisher(sender) as pub, ControlServer(control_endpoint(sender)) as server:
        answered = threading.Event()

        def answer() -> None:  # the sender's control side: a Hello for every request
            while not answered.is_set():
                request = server.recv(50)
                if request is not None:
                    assert isinstance(decode_message(request[1]), HelloRequest)
                    server.reply(request[0], HELLO)

        responder = threading.Thread(target=answer, daemon=True)
        responder.start()
        thread, stop, result = start(relay, inp=sender, out=out)
        subs = [PacketSubscriber(out) for _ in range(3)]
        clients = [ControlClient(control_endpoint(out)) for _ in range(3)]
        try:
            settle(pub, subs)
            for seq in range(1, 151):
                pub.send(encode(Frame(seq=seq)))
                time.sleep(0.002)
            for sub in subs:
                got = [decode(p).seq for p in iter(lambda: sub.recv(500), None)]  # noqa: B023
                assert got == list(range(1, 151))
            replies = [None] * 3

            def ask(i: int) -> None:
                replies[i] = clients[i].request(HelloRequest(), 5000)

            askers = [threading.Thread(target=ask, args=(i,)) for i in range(3)]
            for t in askers:
                t.start()
            for t in askers:
                t.join()
            assert replies == [HELLO] * 3  # each reply found its way back
        finally:
            for s in subs + clients:
                s.close()
            stop.set()
            thread.join(10)
            answered.set()
            responder.join()
    assert not thread.is_alive() and "error" not in result, result.get("error")
    assert result["stopped"] == "stop"
    assert result["request_parts"] == result["reply_parts"] == 3 * 3  # id, delimiter, body
    assert result["packets"] >= 150
    with PacketPublisher(out), ControlServer(control_endpoint(out)):
        pass  # the relay closed its sockets: both ports are free again


def test_a_receiver_behind_a_relay_fetches_the_model_and_the_stream(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    """The real sender (lp_d0.mp4) behind a relay: Hello, model by chunks, packets."""
    sender, out = free_endpoint(), free_endpoint()
    log_path = tmp_path / "sent.fwlog"
    relay_thread, relay_stop, relayed = start(relay, inp=sender, out=out)
    with PacketSubscriber(out) as sub, ControlClient(control_endpoint(out)) as client:
        send_thread, _, sent = start(send, model_path=person_model,
                                     source=str(shared_data / "video" / "lp_d0.mp4"),
                                     bind=sender, record=log_path)
        hello = client.request(HelloRequest(), 30_000)
        assert isinstance(hello, Hello), sent
        assembler = ChunkAssembler(hello.model_sha256, hello.model_bytes)
        for index in assembler.missing():
            chunk = client.request(ModelRequest(hello.model_sha256, index), 5000)
            assert isinstance(chunk, ModelChunk), chunk
            assembler.add(chunk)
        data = assembler.result()
        assert hashlib.sha256(data).hexdigest() == hello.model_sha256
        assert data == person_model.read_bytes()
        received = []
        while send_thread.is_alive():
            if (packet := sub.recv(20)) is not None:
                received.append(packet)
        while (packet := sub.recv(300)) is not None:
            received.append(packet)
    relay_stop.set()
    relay_thread.join(10)
    assert "error" not in sent and "error" not in relayed, (sent, relayed)
    published = [p.tobytes() for p in read_log(log_path).packets]
    assert len(published) == sent["packets"] == 78
    assert len(received) >= 60 and received == published[-len(received):]
    assert sent["receivers_max"] == 1  # the relay is the sender's one peer
    assert relayed["request_parts"] == relayed["reply_parts"] == 3 * (1 + assembler.count)
    assert relayed["reply_bytes"] > len(data)  # the model went through the relay
    assert relayed["packets"] >= len(received)
