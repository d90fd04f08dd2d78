"""The sender's control thread: the Hello, the model's chunks and the updates' chunks, shaped.

Requests (``protocol.control``) arrive at the sender's ROUTER socket
(``protocol.transport.ControlServer``) and each gets one reply (``answer_request``):

- ``hello_request``: the stream's Hello, its ``model_serial`` the newest update issued
  (``sender.updates.UpdateStore``);
- ``model_request(sha256, index)``: chunk ``index`` of the model file, split once from the
  bytes the model was loaded from (``protocol.control.model_chunks``);
- ``update_request(model_sha256, serial, index)``: chunk ``index`` of update ``serial``;
- ``time_request(t1)``: ``time_reply(t1, t2, t3)``, ``t2`` the sender's clock when the request
  was read, ``t3`` when answered (``protocol.clock``; never held);
- anything malformed, another model, an update not issued, an index out of range, or a
  message that is no request: an ``Error`` naming the field (counted: ``errors``).

Update chunks are shaped per receiver (``protocol.shaper.UpdateShaper``: at most 32 kbit/s
over any 1 s and 8 kbit/s over any 60 s): a reply is held until its time and then sent; the
thread waits on the socket only until the next held reply is due, so Hellos and model chunks
are never held behind it. A receiver is its routing envelope (one per DEALER socket, one more
identity per relay), so receivers behind a relay are shaped each on its own; a receiver that
opens its control socket again (``receiver.acquire.ControlChannel`` does after a timeout,
``receiver.updates.CHUNK_TIMEOUT_S``, longer than any hold) is a new one, shaped afresh:
a lost reply can let a receiver's traffic exceed the limits (by a window, or the bucket's
depth). At most ``MAX_HELD_PER_PEER`` replies are held for one receiver (a receiver asks for
one chunk at a time) and ``MAX_HELD`` in all; a request beyond that gets an ``Error`` at once.

A routing envelope is what its sender says it is, but its first identity is the TCP
connection's (libzmq's ROUTER puts it there; only a relay adds more), so a peer that forges
relay hops on one connection is bounded per connection too: at most
``MAX_RECEIVERS_PER_CONNECTION`` receivers of one connection are shaped at once (a receiver
stays shaped until its window is empty and its bucket full again, ``protocol.shaper``), and
at most ``MAX_HELD_PER_CONNECTION`` replies are held for one connection; a request beyond
either gets an ``Error`` at once. A connection's update traffic is so at most that many
receivers' (a relay serving more is slowed, not refused for long).

Model chunks are encoded once and sent zero-copy (``ControlServer.reply``): a peer that asks
for chunks and never reads holds at most ``protocol.transport.CONTROL_HWM`` replies, each
sharing the chunk's bytes.

The frame loop never waits for this thread: it runs on its own, with its own socket, and the
packets go out on the PUB socket; held replies delay only the update traffic.

Two kinds of request get no reply and are not counted: one with broken framing (dropped by
``ControlServer.recv``), and a frame over ``protocol.transport.MAX_CONTROL_FRAME``, which ends
that peer's connection at the frame's header (libzmq's own limit).
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import threading
import time
from collections import Counter
from collections.abc import Callable

from facewire.protocol.control import (
    ControlError,
    Error,
    Hello,
    HelloRequest,
    Message,
    ModelChunk,
    ModelRequest,
    TimeReply,
    TimeRequest,
    UpdateChunk,
    UpdateRequest,
    decode_message,
    encode_message,
)
from facewire.protocol.shaper import UpdateShaper
from facewire.protocol.transport import ControlServer
from facewire.sender.updates import UpdateStore

POLL_MS = 100
MAX_HELD_PER_PEER = 4
MAX_HELD = 1024
MAX_HELD_PER_CONNECTION = 64
MAX_RECEIVERS_PER_CONNECTION = 16

Peer = tuple[bytes, ...]


def answer_request(raw: bytes, hello: Hello, chunks: list[ModelChunk],
                   updates: UpdateStore | None = None,
                   clock: Callable[[], float] = time.monotonic) -> Message:
    """The reply to one raw control request (module docstring).

    Args:
        raw: the request's bytes as received.
        hello: this stream's Hello (its ``model_serial`` is replaced by the updates').
        chunks: the model file's chunks (``protocol.control.model_chunks``), index order.
        updates: the session's updates, or None (no updates: every ``update_request`` is
            refused).
        clock: the sender's clock (``protocol.clock``).
    """
    received = clock()
    try:
        request = decode_message(raw)
    except ControlError as exc:
        return Error(f"bad request: {exc}")
    if isinstance(request, HelloRequest):
        serial = updates.serial if updates is not None else 0
        return hello if hello.model_serial == serial else \
            dataclasses.replace(hello, model_serial=serial)
    if isinstance(request, ModelRequest):
        if request.sha256 != hello.model_sha256:
            return Error(f"model_request.sha256: this sender serves model "
                         f"{hello.model_sha256}, not {request.sha256}")
        if request.index >= len(chunks):
            return Error(f"model_request.index: {request.index} is out of range (the model "
                         f"has {len(chunks)} chunks)")
        return chunks[request.index]
    if isinstance(request, TimeRequest):
        return TimeReply(request.t1, received, clock())
    if isinstance(request, UpdateRequest):
        if updates is None:
            return Error("update_request: this sender issues no updates")
        try:
            return updates.chunk(request)
        except ControlError as exc:
            return Error(str(exc))
    return Error(f"{request.TYPE} is not a request")


class Responder:
    """Answers control requests on its own thread until ``stop`` (module docstring).

    Args:
        server: the bound control socket (used by this thread only).
        hello: the stream's Hello.
        chunks: the model file's chunks.
        updates: the session's updates (published from any thread).
        shaper: the update traffic shaper (``protocol.shaper``'s limits by default).
        clock: the sender's clock (``protocol.clock``).

    Attributes:
        hello: the Hello answered (``announce``).
        counts: ``hello_requests``, ``chunk_requests``, ``update_requests`` (update chunks
            sent), ``update_bytes`` (their message bytes), ``time_requests``, ``errors``.
    """

    def __init__(self, server: ControlServer, hello: Hello, chunks: list[ModelChunk],
                 updates: UpdateStore, shaper: UpdateShaper | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.server, self.hello, self.chunks, self.updates = server, hello, chunks, updates
        self.clock = clock
        self.shaper = shaper if shaper is not None else UpdateShaper()
        self.counts = dict.fromkeys(("hello_requests", "chunk_requests", "update_requests",
                                     "update_bytes", "time_requests", "errors"), 0)
        self._held: list[tuple[float, int, Peer, UpdateChunk, int]] = []
        self._held_by: Counter[Peer] = Counter()
        self._held_on: Counter[bytes] = Counter()  # held replies per connection
        self._encoded = {chunk.index: encode_message(chunk) for chunk in chunks}
        self._order = itertools.count()
        self._done = threading.Event()
        self.thread = threading.Thread(target=self._run, name="facewire-control", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def announce(self, hello: Hello) -> None:
        """Answer Hello requests with ``hello`` from now on (from any thread)."""
        self.hello = hello

    def stop(self) -> None:
        self._done.set()
        self.thread.join()

    def _run(self) -> None:
        while not self._done.is_set():
            self._send_due()
            wait = POLL_MS
            if self._held:
                wait = max(0, min(wait, round((self._held[0][0] - time.monotonic()) * 1000)))
            request = self.server.recv(wait)
            if request is not None:
                self._answer(*request)

    def _answer(self, peer: Peer, raw: bytes) -> None:
        reply = answer_request(raw, self.hello, self.chunks, self.updates, self.clock)
        if isinstance(reply, UpdateChunk):
            refusal = self._refusal(peer)
            if refusal is None:
                size = len(encode_message(reply))
                due = self.shaper.schedule(peer, size, time.monotonic())
                heapq.heappush(self._held, (due, next(self._order), peer, reply, size))
                self._held_by[peer] += 1
                self._held_on[peer[0]] += 1
                return
            reply = Error(f"update_request: {refusal}; ask one at a time")
        key = {Hello: "hello_requests", ModelChunk: "chunk_requests",
               TimeReply: "time_requests"}.get(type(reply), "errors")
        self.counts[key] += 1
        self.server.reply(peer, self._encoded[reply.index] if isinstance(reply, ModelChunk)
                          else reply)

    def _refusal(self, peer: Peer) -> str | None:
        """Why an update reply for ``peer`` may not be held now (module docstring), or None."""
        connection = peer[0]
        if self._held_by[peer] >= MAX_HELD_PER_PEER or len(self._held) >= MAX_HELD:
            return (f"{self._held_by[peer]} of this receiver's requests (and "
                    f"{len(self._held)} in all) are waiting")
        if self._held_on[connection] >= MAX_HELD_PER_CONNECTION:
            return f"{self._held_on[connection]} requests of this connection are waiting"
        self.shaper.forget(time.monotonic())
        if not self.shaper.shaped(peer) and \
                self.shaper.peers(connection) >= MAX_RECEIVERS_PER_CONNECTION:
            return (f"{MAX_RECEIVERS_PER_CONNECTION} receivers of this connection are being "
                    f"shaped")
        return None

    def _send_due(self) -> None:
        now = time.monotonic()
        while self._held and self._held[0][0] <= now:
            _, _, peer, reply, size = heapq.heappop(self._held)
            self._held_by[peer] -= 1
            if not self._held_by[peer]:
                del self._held_by[peer]
            self._held_on[peer[0]] -= 1
            if not self._held_on[peer[0]]:
                del self._held_on[peer[0]]
            self.server.reply(peer, reply)
            self.counts["update_requests"] += 1
            self.counts["update_bytes"] += size
