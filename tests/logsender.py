"""A fake sender for the receiver's tests, made of the real transport, and its helpers.

``LogSender`` is the real ``PacketPublisher`` and ``ControlServer`` answering the real control
messages (Hello, model chunks), publishing a real log's packets renumbered and paced at the
Hello's rate; only the pacing and the scripted faults (junk, dropped packets, wrong control
replies) are the test's. Shared by ``tests/test_receiver.py`` and ``tests/reliability/``,
as is ``encoded_log``: a real video encoded by the real sender pipeline, once per session.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np
from conftest import free_endpoint

from facewire.models.modelfile import load_model
from facewire.protocol.control import (
    Error,
    Hello,
    HelloRequest,
    ModelRequest,
    TimeRequest,
    decode_message,
    model_chunks,
)
from facewire.protocol.keys import CurveServer
from facewire.protocol.log import PacketLog, read_log
from facewire.protocol.packet import PACKET_BYTES, decode, encode
from facewire.protocol.transport import ControlServer, PacketPublisher
from facewire.sender.pipeline import encode_video


@functools.cache
def encoded_log(model: Path, video: Path) -> PacketLog:
    """``video`` encoded with ``model`` (``sender.pipeline.encode_video``), read back; the log
    is written beside the model (a session's temporary folder) and made once per session.
    Its arrays are shared: do not write into them."""
    path = model.with_name(f"{video.stem}.fwlog")
    encode_video(model, video, path)
    return read_log(path)


def free_port_pair() -> int:
    """A port P with P and P + 1 free on 127.0.0.1, below the ephemeral range
    (``conftest.free_endpoint``)."""
    return int(free_endpoint().rsplit(":", 1)[1])


class LogSender(threading.Thread):
    """A sender on ``tcp://127.0.0.1:port`` (and port + 1) made of the real sockets.

    It answers Hello and model requests (counting them) and, once ``go`` is set (at once
    when None), publishes ``count`` packets at the Hello's rate: the log's packets in order,
    cycling, numbered ``first_seq``, ``first_seq + 1``, ...; after every ``junk_every``-th
    packet it also publishes three corrupt messages, and every ``drop_every``-th packet is
    numbered and timed but not sent (lost). ``faulty`` lists the control requests (1 for
    the first) answered wrongly: garbage bytes, then a chunk other than the one asked for.
    ``stop()`` closes the sockets.
    """

    def __init__(self, port: int, hello: Hello, model: bytes, packets: np.ndarray,
                 count: int, go: threading.Event | None = None, first_seq: int = 0,
                 junk_every: int = 0, drop_every: int = 0, faulty: tuple[int, ...] = (),
                 curve: CurveServer | None = None) -> None:
        super().__init__(daemon=True)
        self.port, self.hello, self.count, self.go = port, hello, count, go
        self.chunks = {c.index: c for c in model_chunks(model, hello.model_sha256)}
        self.frames = [decode(p.tobytes()) for p in packets]
        self.first_seq = first_seq
        self.junk_every, self.drop_every, self.faulty = junk_every, drop_every, faulty
        self.dropped = 0
        self.curve = curve
        self.requests: Counter[str] = Counter()
        self.time_requests = 0  # refused, and not among ``requests``
        self.sent = 0
        self.junk = 0
        self.bound = threading.Event()
        self.done = threading.Event()
        self._halt = threading.Event()
        self.start()
        assert self.bound.wait(10), "the test sender could not bind"

    def run(self) -> None:
        endpoint = f"tcp://127.0.0.1:{self.port}"
        pub = PacketPublisher(endpoint, self.curve)  # free as soon as a sender before closed
        ctl = ControlServer(f"tcp://127.0.0.1:{self.port + 1}", self.curve)
        self.bound.set()
        period = 1.0 / self.hello.rate_hz
        rng = np.random.default_rng(3)
        next_t = None
        try:
            while not self._halt.is_set():
                now = time.monotonic()
                if next_t is None and (self.go is None or self.go.is_set()):
                    next_t = now
                if next_t is not None and self.sent < self.count and now >= next_t:
                    frame = self.frames[self.sent % len(self.frames)]
                    packet = encode(dataclasses.replace(
                        frame, seq=(self.first_seq + self.sent) % 65536))
                    if self.drop_every and (self.sent + 1) % self.drop_every == 0:
                        self.dropped += 1
                    else:
                        pub.send(packet)
                    self.sent += 1
                    next_t += period
                    if self.junk_every and self.sent % self.junk_every == 0:
                        bad = bytearray(packet)
                        bad[5] ^= 0x10
                        for junk in (rng.bytes(PACKET_BYTES), b"abc", bytes(bad)):
                            pub.send(junk)
                            self.junk += 1
                    if self.sent == self.count:
                        self.done.set()
                wait = 10 if next_t is None or self.sent == self.count else \
                    max(0, round((next_t - time.monotonic()) * 1000))
                request = ctl.recv(wait)
                if request is not None:
                    self._answer(ctl, *request)
        finally:
            pub.close()
            ctl.close()

    def _answer(self, ctl: ControlServer, peer: tuple[bytes, ...], raw: bytes) -> None:
        message = decode_message(raw)
        if isinstance(message, TimeRequest):  # a sender without a clock, as before it had one
            self.time_requests += 1
            ctl.reply(peer, Error("unknown request"))
            return
        self.requests[message.TYPE] += 1
        n = self.requests.total()
        if n in self.faulty:
            if self.faulty.index(n) % 2 == 0:
                ctl.socket.send_multipart([*peer, b"", b"\xc1 not msgpack"])
            else:
                ctl.reply(peer, self.chunks[len(self.chunks) - 1])
        elif isinstance(message, HelloRequest):
            ctl.reply(peer, self.hello)
        elif isinstance(message, ModelRequest) and message.sha256 == self.hello.model_sha256 \
                and message.index in self.chunks:
            ctl.reply(peer, self.chunks[message.index])
        else:
            ctl.reply(peer, Error("unknown request"))

    def stop(self) -> None:
        self._halt.set()
        self.join(10)


def hello_for(model_path: Path, hello: Hello) -> Hello:
    """``hello`` announcing the model file at ``model_path`` (its sha256, size and
    regions)."""
    data = model_path.read_bytes()
    return dataclasses.replace(hello, model_sha256=hashlib.sha256(data).hexdigest(),
                               model_bytes=len(data),
                               regions=tuple(r.name for r in load_model(model_path).regions))


def ready(go: threading.Event, lines: list[str]) -> Callable[[str], None]:
    """A status callback that records the lines and sets ``go`` once the loop plays."""
    def status(line: str) -> None:
        lines.append(line)
        if "waiting for packets" in line:
            go.set()
    return status
