"""Bad control messages (issue 8, reliability item 4), to a real receiver and a real sender.

Receiver side: ``receiver.receiver.receive`` runs in a thread against ``FakeSender``, a
malicious sender of test code (an XPUB for packets, a ROUTER with ``ControlServer``'s
framing for control) that answers requests from a script of faults before it answers them
honestly: malformed msgpack, wrong types, sizes declared far beyond the data, a frame over
the control channel's limit, an ``Error`` carrying terminal escape sequences, replies of the
wrong kind, a late reply, chunks of the wrong index, total or model, chunks whose data do
not match their hash, and a whole transfer whose chunks do not hash to the announced sha256.
Each is refused and counted (``control_errors``; ``control_timeouts`` for a reply that never
comes in time, ``receiver.acquire.ControlChannel``'s "lazy pirate" rule), no status line
carries a raw control character, and once the fake sender answers honestly the receiver
fetches the right model and plays every packet. A model whose chunks never hash right ends
``receive`` with ``ReceiveError`` after ``MODEL_ATTEMPTS`` transfers, and nothing is cached.
Chunks that never match the Hello (another size) end it too, after ``MODEL_ATTEMPTS``
attempts.

Sender side: ``sender.sender.send`` runs in a thread on a short grey clip, looping; a raw
DEALER sends garbage, random bytes, huge declared lengths, wrong types, indices out of range,
a wrong sha256, messages that are no requests, a flood; each gets an ``Error`` reply (counted
in the sender's ``control.errors``). Requests with broken framing are dropped unanswered
(``ControlServer.recv``), a frame over ``protocol.transport.MAX_REQUEST_FRAME`` (sent, or only
declared by a raw TCP peer) ends that peer's connection at the frame's header; the sender
keeps streaming and answers a good HelloRequest and every chunk afterwards.
"""

from __future__ import annotations

import dataclasses
import hashlib
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zmq
from conftest import free_endpoint, start
from rawzmtp import connect_as_dealer, declare_a_gigabyte

from facewire.protocol.control import (
    CHUNK_BYTES,
    Camera,
    Error,
    Hello,
    HelloRequest,
    Message,
    ModelChunk,
    ModelRequest,
    TimeRequest,
    decode_message,
    encode_message,
    model_chunks,
)
from facewire.protocol.packet import Flag, Frame, decode, encode
from facewire.protocol.transport import (
    MAX_CONTROL_FRAME,
    MAX_REQUEST_FRAME,
    ControlServer,
    PacketSubscriber,
    control_endpoint,
)
from facewire.receiver.acquire import CHUNK_ATTEMPTS, MODEL_ATTEMPTS
from facewire.receiver.receiver import ReceiveError, receive
from facewire.sender.sender import send

RATE_HZ = 30.0
PACKETS = 30
SIZE = (64, 48)
ESCAPES = "\x1b[2J\x1b]0;owned\x07\r"


def packb(body: object) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def body_of(message: Message, **over: object) -> dict[str, Any]:
    """A message as its msgpack map, with fields replaced or added."""
    body = msgpack.unpackb(encode_message(message), raw=False)
    body.update(over)
    return body


def declared_data(chunk: dict[str, Any]) -> bytes:
    """A model_chunk map whose last field, data, declares 4 GiB of bytes and holds none."""
    items = [(key, value) for key, value in chunk.items() if key != "data"]
    head = bytes([0x80 | len(items) + 1]) + b"".join(packb(k) + packb(v) for k, v in items)
    return head + packb("data") + b"\xc6\xff\xff\xff\xff"


Reply = list[tuple[float, bytes]]  # (delay s, reply bytes), in order
Fault = Callable[["FakeSender", Message], Reply]


def raw(payload: bytes) -> Fault:
    return lambda sender, request: [(0.0, payload)]


def late(seconds: float) -> Fault:
    """The honest reply, after the receiver has given up waiting for it."""
    return lambda sender, request: [(seconds, sender.honest(request))]


class FakeSender(threading.Thread):
    """A malicious sender on ``endpoint`` (packets) and port + 1 (control).

    Each HelloRequest takes the next of ``hello_faults``, each ModelRequest the next of
    ``chunk_faults``; without one left, a request is answered honestly, except that the first
    ``bad_transfers`` whole transfers are of a model whose chunks are each right but whose
    bytes do not hash to the announced sha256 (a byte changed). Once the receiver has
    subscribed and every chunk of the real model has been served, it publishes ``packets``
    valid packets at once (they wait in the receiver's queue while it sets up, so that no
    deadline of its live playout depends on this thread, which shares its process).
    """

    def __init__(self, endpoint: str, hello: Hello, model: bytes,
                 hello_faults: tuple[Fault, ...] = (), chunk_faults: tuple[Fault, ...] = (),
                 bad_transfers: int = 0, packets: int = 0) -> None:
        super().__init__(daemon=True)
        self.endpoint, self.hello, self.packets = endpoint, hello, packets
        self.chunks = model_chunks(model, hello.model_sha256)
        tampered = bytearray(model)
        tampered[len(tampered) // 2] ^= 0x01
        self.bad_chunks = model_chunks(bytes(tampered), hello.model_sha256)
        self.hello_faults, self.chunk_faults = deque(hello_faults), deque(chunk_faults)
        self.bad_transfers = bad_transfers
        self.requests: Counter[str] = Counter()
        self.faults = 0
        self.served: set[int] = set()
        self.sent = 0
        self.halt = threading.Event()
        self.bound = threading.Event()
        self.start()
        assert self.bound.wait(10), "the fake sender could not bind"

    def honest(self, request: Message) -> bytes:
        if isinstance(request, HelloRequest):
            return encode_message(self.hello)
        assert isinstance(request, ModelRequest)
        if self.bad_transfers:
            if request.index == len(self.chunks) - 1:
                self.bad_transfers -= 1
            return encode_message(self.bad_chunks[request.index])
        self.served.add(request.index)
        return encode_message(self.chunks[request.index])

    def run(self) -> None:
        context = zmq.Context()
        pub = context.socket(zmq.XPUB)
        pub.linger, pub.sndhwm = 0, 0
        pub.bind(self.endpoint)
        server = ControlServer(control_endpoint(self.endpoint))
        self.bound.set()
        pending: list[tuple[float, tuple[bytes, ...], bytes]] = []
        subscribed = False
        try:
            while not self.halt.is_set():
                now = time.monotonic()
                if pub.poll(0) and pub.recv() == b"\x01":
                    subscribed = True
                if subscribed and len(self.served) == len(self.chunks):
                    while self.sent < self.packets:
                        pub.send(encode(Frame(seq=self.sent, flags=Flag.FACE_PRESENT)))
                        self.sent += 1
                for item in [p for p in pending if p[0] <= now]:
                    pending.remove(item)
                    server.socket.send_multipart([*item[1], b"", item[2]])
                request = server.recv(2)
                if request is not None:
                    peer, data = request
                    message = decode_message(data)  # the real receiver asks nothing else
                    if isinstance(message, TimeRequest):  # refused, as an older sender does
                        pending.append((now, peer, encode_message(Error("unknown request"))))
                        continue
                    self.requests[message.TYPE] += 1
                    faults = self.hello_faults if isinstance(message, HelloRequest) \
                        else self.chunk_faults
                    if faults:
                        self.faults += 1
                        reply = faults.popleft()(self, message)
                    else:
                        reply = [(0.0, self.honest(message))]
                    pending += [(now + delay, peer, payload) for delay, payload in reply]
        finally:
            server.close()
            pub.close()
            context.term()

    def stop(self) -> None:
        self.halt.set()
        self.join(10)


def hello_for(data: bytes) -> Hello:
    return Hello(hashlib.sha256(data).hexdigest(), len(data), RATE_HZ,
                 Camera(640.0, 640.0, 319.5, 239.5, 640, 480), ())


def test_the_receiver_refuses_each_bad_reply_and_then_fetches_and_plays(
        generic_model: Path, tmp_path: Path) -> None:
    data = generic_model.read_bytes()
    hello = hello_for(data)
    sha = hello.model_sha256
    assert len(model_chunks(data, sha)) == 2  # the chunk faults below are laid out for two
    other = b"another model" * 1000
    other_chunk = model_chunks(other, hashlib.sha256(other).hexdigest())[0]
    first = data[:CHUNK_BYTES]
    chunk0 = body_of(model_chunks(data, sha)[0])
    hello_errors = (  # each is one control error
        raw(b"\xc1 not msgpack"),
        raw(b""),
        raw(packb([1, 2])),
        raw(packb({1: 2})),
        raw(packb(msgpack.ExtType(5, b"x"))),
        raw(b"\xdb\xff\xff\xff\xffabc"),  # a str declaring 4 GiB
        raw(b"\xdf\xff\xff\xff\xff"),  # a map declaring 4 G entries
        raw(packb(body_of(hello, rate_hz="fast"))),
        raw(packb(body_of(hello, camera=[640, 480]))),
        raw(packb(body_of(hello, model_bytes=2**40))),
        raw(packb(body_of(hello, rate_hz=1e-300))),
        raw(packb(body_of(hello, camera={**body_of(hello)["camera"], "fx": float("nan")}))),
        raw(packb({"type": "hello2"})),
        raw(packb({"type": "error", "message": ESCAPES + "go away"})),
        raw(encode_message(model_chunks(data, sha)[1])),  # a reply of the wrong kind
        raw(encode_message(HelloRequest())),
        raw(packb(body_of(hello, **{ESCAPES: 1}))),
        raw(packb(body_of(hello, regions=["mouth" + ESCAPES]))),
    )
    hello_timeouts = (
        raw(b"\x00" * (MAX_CONTROL_FRAME + 1)),  # over the limit: the connection drops
        late(3.0),  # the receiver gives up after HELLO_TIMEOUT_S (1 s)
    )
    chunk_errors = (  # chunk 0 fails CHUNK_ATTEMPTS times: the receiver asks the Hello again
        raw(encode_message(model_chunks(data, sha)[1])),  # not the index asked for
        raw(encode_message(other_chunk)),  # another model's
        raw(encode_message(ModelChunk(sha, 0, 3, 3 * CHUNK_BYTES, first,
                                      hashlib.sha256(first).hexdigest()))),  # another total
        raw(packb({**chunk0, "data": b"X" + first[1:]})),  # data not matching its hash
        raw(packb({**chunk0, "index": 7})),  # an index beyond the count
        raw(encode_message(Error("no model for you"))),
        raw(encode_message(hello)),
        raw(packb({**chunk0, "data": first[:100]})),  # too short for its index and total
        raw(declared_data(chunk0)),  # data declaring 4 GiB
    )
    endpoint = free_endpoint()
    sender = FakeSender(endpoint, hello, data, hello_faults=hello_errors + hello_timeouts,
                        chunk_faults=chunk_errors, bad_transfers=1, packets=PACKETS)
    lines: list[str] = []
    try:
        thread, _, result = start(receive, connect=endpoint, cache_dir=tmp_path / "cache",
                                  size=SIZE, status=lines.append, max_frames=PACKETS,
                                  idle_timeout_s=10.0)
        thread.join(120)
    finally:
        sender.stop()
    assert not thread.is_alive() and "error" not in result, result.get("error")
    assert sender.faults == len(hello_errors) + len(hello_timeouts) + len(chunk_errors)
    assert not sender.hello_faults and not sender.chunk_faults and not sender.bad_transfers
    assert result["control_errors"] == len(hello_errors) + len(chunk_errors), result
    assert result["control_timeouts"] == len(hello_timeouts), result
    assert result["model_source"] == "fetched" and result["model_sha256"] == sha
    assert (tmp_path / "cache" / f"{sha}.fwm").read_bytes() == data
    assert result["ended"] == "max_frames" and result["frames"] == PACKETS, result
    assert result["received"] == PACKETS and result["corrupt"] == result["lost"] == 0
    # 5 attempts at chunk 0, then a whole transfer that fails its sha256, then the good one
    assert sender.requests["model_request"] == len(chunk_errors) + 2 * 2
    assert any("do not hash to the announced sha256" in line for line in lines), lines
    assert any("chunk 0 failed 5 times" in line for line in lines), lines
    assert any("the sender says: \\x1b[2J" in line for line in lines), lines
    assert all(line.isprintable() for line in lines), lines  # no escape reached a status


def test_a_model_whose_chunks_never_hash_right_ends_the_receive(generic_model: Path,
                                                                 tmp_path: Path) -> None:
    data = generic_model.read_bytes()
    hello = hello_for(data)
    sender = FakeSender(free_endpoint(), hello, data, bad_transfers=10**6)
    lines: list[str] = []
    try:
        thread, _, result = start(receive, connect=sender.endpoint,
                                  cache_dir=tmp_path / "cache", size=SIZE,
                                  status=lines.append, idle_timeout_s=10.0)
        thread.join(60)
    finally:
        sender.stop()
    assert not thread.is_alive()
    error = result.get("error")
    assert isinstance(error, ReceiveError), result
    assert f"failed its sha256 {MODEL_ATTEMPTS} times" in str(error)
    assert hello.model_sha256[:16] in str(error)
    assert sender.requests["model_request"] == MODEL_ATTEMPTS * len(sender.chunks)
    assert not list((tmp_path / "cache").glob("*.fwm")), "a bad model was cached"
    assert sum("do not hash" in line for line in lines) == MODEL_ATTEMPTS


def test_chunks_that_never_match_the_hello_do_not_keep_the_receiver_busy(
        generic_model: Path, tmp_path: Path) -> None:
    """A sender whose Hello announces one byte more than its chunks hold: every chunk is
    refused. The receive ends with a ``ReceiveError`` after ``MODEL_ATTEMPTS`` attempts rather
    than ask the Hello and chunk 0 again and again (about 100 rounds a second, before the
    fix)."""
    data = generic_model.read_bytes()
    hello = dataclasses.replace(hello_for(data), model_bytes=len(data) + 1)
    sender = FakeSender(free_endpoint(), hello, data)  # its chunks: the file's real size
    try:
        thread, stop, result = start(receive, connect=sender.endpoint,
                                     cache_dir=tmp_path / "cache", size=SIZE,
                                     idle_timeout_s=1.0)
        thread.join(3)
        busy = thread.is_alive()
        stop.set()
        thread.join(10)
    finally:
        sender.stop()
    assert not busy, f"still fetching after 3 s: {dict(sender.requests)}"
    assert sender.requests["model_request"] == MODEL_ATTEMPTS * CHUNK_ATTEMPTS, result
    assert isinstance(result.get("error"), ReceiveError), result
    assert "not the ones asked for" in str(result["error"])


# -- the sender ------------------------------------------------------------------------------

TIMEOUT_MS = 30_000  # the first Hello waits for the sender to load the model and the tracker


class Dealer:
    """A raw DEALER on the sender's control port: any frames out, the reply's last frame in."""

    def __init__(self, endpoint: str) -> None:
        self.socket = zmq.Context.instance().socket(zmq.DEALER)
        self.socket.linger = 0
        self.socket.connect(endpoint)

    def ask(self, body: bytes, timeout_ms: int = 5000) -> Message | None:
        """Send ``body`` as a request (after the empty delimiter); the decoded reply."""
        return self.frames(b"", body, timeout_ms=timeout_ms)

    def frames(self, *frames: bytes, timeout_ms: int = 5000) -> Message | None:
        """Send these frames as they are; the decoded reply, None when none comes."""
        self.socket.send_multipart(list(frames))
        if not self.socket.poll(timeout_ms, zmq.POLLIN):
            return None
        return decode_message(self.socket.recv_multipart()[-1])

    def close(self) -> None:
        self.socket.close(linger=0)


def test_the_sender_answers_every_bad_request_with_an_error_and_keeps_streaming(
        generic_model: Path, grey_video: Callable[..., Path]) -> None:
    endpoint = free_endpoint()
    control = control_endpoint(endpoint)
    data = generic_model.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    count = len(model_chunks(data, sha))
    dealer = Dealer(control)
    with PacketSubscriber(endpoint) as sub:
        thread, stop, result = start(send, model_path=generic_model,
                                     source=str(grey_video("grey.mp4", frames=6)),
                                     bind=endpoint, loop=True)
        try:
            hello = dealer.ask(encode_message(HelloRequest()), timeout_ms=TIMEOUT_MS)
            assert isinstance(hello, Hello) and hello.model_sha256 == sha, result
            assert sub.recv(5000) is not None
            errors = _ask_bad_requests(dealer, hello, data, np.random.default_rng(8))
            _send_broken_frames(dealer, hello, int(control.rsplit(":", 1)[1]))
            # the sender still answers, serves the whole model, and streams
            assert _unclocked(dealer.ask(encode_message(HelloRequest()))) == _unclocked(hello)
            fetched = b""
            for index in range(count):
                chunk = dealer.ask(encode_message(ModelRequest(sha, index)))
                assert isinstance(chunk, ModelChunk) and chunk.index == index
                fetched += chunk.data
            assert fetched == data
            while sub.recv(0) is not None:  # what was queued during the abuse
                pass
            packets = [sub.recv(10_000) for _ in range(5)]
            assert None not in packets, "the sender stopped streaming"
            seqs = [decode(p).seq for p in packets]
            assert np.all(np.diff(seqs) % 65536 > 0), seqs  # one stream (sender.slots)
            assert thread.is_alive()
        finally:
            stop.set()
            thread.join(20)
            dealer.close()
    assert not thread.is_alive() and "error" not in result, result.get("error")
    assert result["stopped"] == "stop"
    assert result["control"] == {"hello_requests": 4, "chunk_requests": count,
                                 "update_requests": 0, "update_bytes": 0,
                                 "time_requests": 0, "errors": errors}, \
        (result["control"], errors)


def _ask_bad_requests(dealer: Dealer, hello: Hello, data: bytes,
                      rng: np.random.Generator) -> int:
    """Bad requests of every kind, and a flood of them, each answered with an ``Error``
    that says why in printable text; returns how many were sent."""
    sha = hello.model_sha256
    count = len(model_chunks(data, sha))
    errors = 0

    def refused(body: bytes, *words: str) -> None:
        nonlocal errors
        reply = dealer.ask(body)
        assert isinstance(reply, Error), (body[:40], reply)
        assert all(w in reply.message for w in words), (reply.message, words)
        assert reply.message.isprintable()
        errors += 1

    refused(b"\xc1 not msgpack", "bad request", "not valid msgpack")
    refused(b"", "bad request")
    for header in (b"\xdb", b"\xc6", b"\xdd", b"\xdf", b"\xc9"):  # 4 GiB declared
        refused(header + b"\xff\xff\xff\xff", "bad request")
    refused(packb({"type": "model_request", "sha256": 5, "index": "0"}), "wrong type")
    refused(packb({"type": "model_request", "sha256": sha, "index": True}), "wrong type")
    refused(packb({"type": 7}), "unknown control message type")
    refused(packb([1, 2]), "not a map")
    refused(packb({"type": "hello_request", ESCAPES: 1}), "unknown field", "\\x1b")
    refused(packb(msgpack.ExtType(1, b"x")), "extension")
    refused(encode_message(ModelRequest(sha, count)), "out of range")
    for index in (-1, 2**40):
        refused(packb({"type": "model_request", "sha256": sha, "index": index}), "index")
    refused(encode_message(ModelRequest("0" * 64, 0)), sha)
    refused(encode_message(hello), "not a request")
    refused(encode_message(model_chunks(data[:100], sha)[0]), "not a request")
    refused(encode_message(Error(ESCAPES)), "not a request")
    for size in rng.integers(0, 300, 200):  # random bytes: almost never msgpack maps
        refused(rng.bytes(int(size)) or b"\xc1", "bad request")
    # a flood, read back afterwards: every request answered
    for _ in range(300):
        dealer.socket.send_multipart([b"", b"\xc1"])
    for _ in range(300):
        assert dealer.socket.poll(5000)
        assert isinstance(decode_message(dealer.socket.recv_multipart()[-1]), Error)
    return errors + 300


def _unclocked(hello: object) -> object:
    """A Hello but for its clock, which the sender announces from its first frame on."""
    return dataclasses.replace(hello, clock_origin_s=None) if isinstance(hello, Hello) \
        else hello


def _send_broken_frames(dealer: Dealer, hello: Hello, port: int) -> None:
    """Requests with broken framing are dropped unanswered (and uncounted); a frame over the
    limit ends the DEALER's connection (it connects again); a raw peer on the control
    ``port`` that only declares a frame of 1 GiB is cut off at the header."""
    request = encode_message(HelloRequest())
    assert dealer.frames(request, timeout_ms=300) is None  # no delimiter
    assert dealer.frames(b"", b"", request, timeout_ms=300) is None
    assert dealer.frames(*[b"hop"] * 8, b"", request,
                         timeout_ms=300) is None  # 9 hops: more than MAX_HOPS
    relayed = dealer.frames(*[b"hop"] * 6, b"", request)
    assert _unclocked(relayed) == _unclocked(hello)  # 7 hops: answered along its envelope
    assert dealer.ask(b"\x00" * (MAX_REQUEST_FRAME + 1), timeout_ms=500) is None
    assert _unclocked(dealer.ask(encode_message(HelloRequest()))) == _unclocked(hello)
    with connect_as_dealer(port) as conn:
        assert declare_a_gigabyte(conn) < 5


@pytest.mark.parametrize("rate", [0.5, 1e-300, float("nan"), 1001.0])
def test_the_sender_refuses_a_rate_no_hello_may_announce(generic_model: Path,
                                                          rate: float) -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        send(generic_model, "camera:0", bind=free_endpoint(), rate_hz=rate)
