"""A sender that issues model updates mid-stream, made of the real sender's parts.

``UpdateSender`` binds the real sockets on ``tcp://127.0.0.1:port`` (and port + 1): the real
``PacketPublisher``, and the real control thread (``sender.responder.Responder`` with its
``sender.updates.UpdateStore`` and ``protocol.shaper.UpdateShaper``) answering the Hello, the
model's chunks and the updates' chunks. Once ``go`` is set (at once when None) it publishes
``count`` packets at the Hello's rate: a real log's packets in order, cycling, numbered from
0, each carrying the newest update serial published before it (``Frame.serial``: what a
sender's pipeline does once it classifies with the new version). ``issue[i]`` (bytes) is
published as the next update just before packet ``i``; ``publish`` does the same from any
thread. Only the packets' content and pacing are the test's.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Mapping

import numpy as np

from facewire.protocol.control import Hello, model_chunks
from facewire.protocol.packet import decode, encode
from facewire.protocol.shaper import UpdateShaper
from facewire.protocol.transport import ControlServer, PacketPublisher
from facewire.sender.responder import Responder
from facewire.sender.updates import UpdateStore


class UpdateSender(threading.Thread):
    """The test sender (module docstring); ``stop()`` ends it and closes its sockets.

    Attributes:
        store: the session's updates.
        responder: the real control thread (its ``counts``).
        sent: packets published so far; ``serials[i]``: the serial packet ``i`` carried.
        done: set once ``count`` packets are out.
    """

    def __init__(self, port: int, hello: Hello, model: bytes, packets: np.ndarray,
                 count: int, issue: Mapping[int, bytes] | None = None,
                 go: threading.Event | None = None, shaper: UpdateShaper | None = None
                 ) -> None:
        super().__init__(daemon=True, name="update sender")
        self.hello, self.count, self.go = hello, count, go
        self.issue = dict(issue or {})
        self.frames = [decode(p.tobytes()) for p in packets]
        self.store = UpdateStore(hello.model_sha256)
        self.publisher = PacketPublisher(f"tcp://127.0.0.1:{port}")
        self.server = ControlServer(f"tcp://127.0.0.1:{port + 1}")
        self.responder = Responder(self.server, hello, model_chunks(model, hello.model_sha256),
                                   self.store, shaper)
        self.responder.start()
        self.sent = 0
        self.serials: list[int] = []
        self.done = threading.Event()
        self._halt = threading.Event()
        self._lock = threading.Lock()
        self.start()

    def publish(self, data: bytes) -> int:
        """Issue the next update now; its serial."""
        with self._lock:
            self.store.publish_update(self.store.serial + 1, data)
            return self.store.serial

    def run(self) -> None:
        while self.go is not None and not self.go.wait(0.01):
            if self._halt.is_set():
                return
        period = 1.0 / self.hello.rate_hz
        next_t = time.monotonic()
        while not self._halt.is_set() and self.sent < self.count:
            if self.sent in self.issue:
                self.publish(self.issue[self.sent])
            frame = self.frames[self.sent % len(self.frames)]
            serial = self.store.serial
            self.publisher.send(encode(dataclasses.replace(frame, seq=self.sent % 65536,
                                                           serial=serial)))
            self.serials.append(serial)
            self.sent += 1
            next_t += period
            self._halt.wait(max(0.0, next_t - time.monotonic()))
        self.done.set()

    def stop(self) -> None:
        self._halt.set()
        if self.is_alive():
            self.join(10)
        self.responder.stop()
        self.server.close()
        self.publisher.close()
