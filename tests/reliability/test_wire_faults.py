"""Bad packets on the wire (issue 8, reliability item 2): corrupt packets between good ones
reach a real ``receiver.receiver.receive`` over ZeroMQ on 127.0.0.1 and are counted and
skipped; a raw TCP peer (``rawzmtp``) declaring a frame of 1 GiB is cut off at the frame's
header, by a receiver's packet socket and by the relay's upstream socket, and a receiver so
cut off connects again. The packets and the garbage come from ``packetoracle``, seeded as the
fuzz tests are (``fuzzbudget``).
"""

from __future__ import annotations

import hashlib
import socket
import threading
from pathlib import Path

import numpy as np
import pytest
import zmq
from conftest import free_endpoint, start
from fuzzbudget import rng_for
from packetoracle import Garbage, pack, random_fields
from rawzmtp import accept_as_pub, declare_a_gigabyte

from facewire.protocol.control import Camera, Error, Hello, HelloRequest, decode_message
from facewire.protocol.relay import relay
from facewire.protocol.transport import ControlServer, PacketSubscriber, control_endpoint
from facewire.receiver import receiver as receiver_module
from facewire.receiver.receiver import receive


class _WireSender(threading.Thread):
    """A fake sender of test code: an XPUB for packets (it sees the receiver subscribe) and
    the real ``ControlServer`` answering the Hello. Once the receiver has subscribed it
    publishes ``messages`` at once, with no limit on its queue: they wait in the receiver's
    queue while it sets up, so that no deadline of the live playout depends on this thread's
    timing (it shares the receiver's process and GIL: a pause of either, a garbage
    collection say, would otherwise make a packet late on a link that loses nothing)."""

    def __init__(self, endpoint: str, hello: Hello, messages: list[bytes]) -> None:
        super().__init__(daemon=True)
        self.endpoint, self.hello, self.messages = endpoint, hello, messages
        self.sent = 0
        self.halt = threading.Event()
        self.bound = threading.Event()
        self.start()
        assert self.bound.wait(10)

    def run(self) -> None:
        context = zmq.Context()
        pub = context.socket(zmq.XPUB)
        pub.linger, pub.sndhwm = 0, 0  # no limit: nothing is dropped on this side
        pub.bind(self.endpoint)
        server = ControlServer(control_endpoint(self.endpoint))
        self.bound.set()
        try:
            while not self.halt.is_set():
                if pub.poll(0) and pub.recv() == b"\x01" and not self.sent:  # subscribed
                    for message in self.messages:
                        pub.send(message)
                        self.sent += 1
                request = server.recv(2)
                if request is not None:
                    peer, raw = request
                    reply = self.hello if isinstance(decode_message(raw), HelloRequest) \
                        else Error("this sender only says hello")
                    server.reply(peer, reply)
        finally:
            server.close()
            pub.close()
            context.term()


def test_corrupt_packets_on_the_wire_are_counted_and_skipped(generic_model: Path) -> None:
    """A real receiver behind real ZeroMQ: 90 valid packets, each after up to 8 pieces of
    garbage (random bytes of 0..100 bytes, mutants of the packets around it, CRC-
    right packets with a bad version or reserved bits). The summary counts every piece as
    corrupt (the face's or, by its first nibble, the voice's) and plays every valid packet:
    one frame each, none lost."""
    rng = rng_for("wire")
    data = generic_model.read_bytes()
    hello = Hello(hashlib.sha256(data).hexdigest(), len(data), 60.0,
                  Camera(640.0, 640.0, 319.5, 239.5, 640, 480), ())
    fields = random_fields(rng, 90, seq=np.arange(90) + 40_000, extremes=0.0)
    fields[:, 1] = 1
    stream = [p.tobytes() for p in pack(fields)]
    messages, garbage, make = [], 0, Garbage(rng)
    for i, packet in enumerate(stream):
        junk: list[bytes] = []
        want = make.r.randrange(9)
        while len(junk) < want:
            item = make(stream[max(0, i - 2):i + 3])
            if isinstance(item, (bytes, bytearray)):  # what a socket can carry
                junk.append(bytes(item))
        garbage += len(junk)
        messages += [*junk, packet]
    endpoint = free_endpoint()
    sender = _WireSender(endpoint, hello, messages)
    try:
        thread, _, result = start(receive, connect=endpoint, model_path=generic_model,
                                  size=(64, 48), max_frames=90, idle_timeout_s=5.0)
        thread.join(60)
    finally:
        sender.halt.set()
        sender.join(10)
    assert not thread.is_alive() and "error" not in result, result.get("error")
    assert sender.sent == 90 + garbage
    counts = {k: result[k] for k in ("ended", "frames", "received", "corrupt", "lost", "late",
                                     "duplicates", "stray", "discarded", "restarts")}
    # garbage whose first nibble is the voice's kind goes to the voice: a corrupt voice packet
    # there, or (a CRC-right mutant of a face packet with version 10) a well-formed one, which
    # alone never fills the voice's buffer: none of it is played as sound
    counts["corrupt"] += result["voice_corrupt"] + result["voice_received"]
    assert result["voice_played"] == result["voice_recovered"] == 0
    assert counts == {"ended": "max_frames", "frames": 90, "received": 90, "corrupt": garbage,
                      "lost": 0, "late": 0, "duplicates": 0, "stray": 0, "discarded": 0,
                      "restarts": 0}, counts


def test_a_frame_declaring_a_gigabyte_ends_the_connection_at_its_header() -> None:
    """A raw TCP peer posing as a sender (a ZMTP handshake as a PUB) sends one packet, then
    a frame header declaring 1 GiB. The receiver's packet socket takes the packet and drops
    the connection at the header (``protocol.transport.MAX_PACKET_FRAME``), without waiting
    for the gigabyte it would otherwise have allocated."""
    endpoint = free_endpoint()
    port = int(endpoint.rsplit(":", 1)[1])
    with socket.create_server(("127.0.0.1", port)) as server:
        server.settimeout(10)
        with PacketSubscriber(endpoint) as sub:
            conn = accept_as_pub(server)
            with conn:
                conn.sendall(b"\x00\x03abc")  # a short message: a corrupt packet
                assert sub.recv(5000) == b"abc"
                assert declare_a_gigabyte(conn) < 5  # read: the subscription, then the end


def test_a_receiver_cut_off_by_a_bad_frame_connects_again(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """libzmq does not reconnect a connecting socket after a protocol error; a real
    ``receive`` opens its packet socket anew after ``REOPEN_S`` without packets (1 s here)
    and connects again by itself."""
    monkeypatch.setattr(receiver_module, "REOPEN_S", 1.0)
    endpoint = free_endpoint()
    port = int(endpoint.rsplit(":", 1)[1])
    with socket.create_server(("127.0.0.1", port)) as server:
        server.settimeout(10)
        thread, stop, result = start(receive, connect=endpoint, cache_dir=tmp_path / "cache")
        try:
            conn = accept_as_pub(server)
            with conn:
                declare_a_gigabyte(conn)
            again = accept_as_pub(server)  # a new socket, a new handshake
            again.close()
        finally:
            stop.set()
            thread.join(10)
    assert result.get("ended") == "stop", result


def test_the_relay_drops_a_sender_declaring_a_gigabyte_and_goes_on() -> None:
    """The same frame header from the relay's upstream side: its packet socket drops that
    connection at the header (``protocol.relay`` sets the transport's limits) and the relay
    keeps running. (libzmq does not reconnect a connecting socket after such a protocol
    error, so that upstream stays cut off until the relay restarts: only the hostile peer
    loses.)"""
    upstream, downstream = free_endpoint(), free_endpoint()
    port = int(upstream.rsplit(":", 1)[1])
    with socket.create_server(("127.0.0.1", port)) as server:
        server.settimeout(10)
        thread, stop, result = start(relay, inp=upstream, out=downstream)
        try:
            conn = accept_as_pub(server)
            with conn:
                assert declare_a_gigabyte(conn) < 5
            assert thread.is_alive()
        finally:
            stop.set()
            thread.join(10)
    assert "error" not in result, result
