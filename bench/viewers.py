"""The fan-out bench's viewers: N lightweight clients in one process, each recording arrivals.

``python -m facewire.bench.viewers {websocket|zmq} TARGET N OUT.npz`` opens N clients:

- ``websocket``: N WebSocket clients of ``TARGET`` (``ws://HOST:PORT/stream``, the gateway's
  stream), opened ``OPEN_AT_ONCE`` at a time: the ``websockets`` library's own protocol
  (``ClientProtocol``, its sans-I/O core: handshake, framing, pings, close; no compression
  offered) on plain asyncio connections, without a task or a queue per client. A binary
  frame is one packet; text frames (status, hello, model) are ignored.
- ``zmq``: N ``protocol.transport.PacketSubscriber`` sockets (the receiver's SUB socket)
  connected to ``TARGET`` (``tcp://HOST:PORT``, a relay's out), read by one poll loop.

Per packet a client does nothing but append its arrival time and the message itself to its
lists. The arrival time is when the process's poll (epoll under asyncio, ``zmq_poll``)
returned with the socket readable (``time.monotonic()``, the system-wide monotonic clock, so
comparable with the sender's stamps in another process): a packet reaches all of a process's
clients at once, and stamping each when its turn comes would add the process's own work on
the others before it, which is not delivery. The delay of the process itself getting a core
stays in. the sequence numbers are decoded afterwards, all at once,
by ``protocol.packet.decode_frames`` (the packet layout's one definition; a message that is
not a valid packet gets seq -1).

The parent talks over stdio, one line each way: this process prints ``ready`` once every
client has received a packet (``error: ...`` and exits 1 when it cannot), then reads ``stop
SEQ S`` from stdin, waits until every client still connected has packet ``SEQ`` or a later
one (at most S seconds: what has not come by then is lost), writes ``OUT.npz`` and prints
``done``. ``OUT.npz`` holds, for every packet
received (M of them), in client order: ``viewer`` (M,) int32 client index, ``seq`` (M,)
int32, ``arrival`` (M,) float64 seconds; ``closed`` (N,) bool, the clients whose
connection ended before ``stop``; ``retries`` (N,) int32, the WebSocket handshakes a client
made again because one timed out (``OPEN_TIMEOUT_S``) or was refused, as a browser would.

File descriptors: each client holds one TCP connection (a ZeroMQ socket also an eventfd), so
the soft ``RLIMIT_NOFILE`` is raised to the hard limit (``raise_fd_limit``).
"""

from __future__ import annotations

import asyncio
import functools
import resource
import selectors
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zmq
from websockets.client import ClientProtocol
from websockets.frames import Frame, Opcode
from websockets.protocol import State
from websockets.uri import WebSocketURI, parse_uri

from facewire.protocol.packet import PACKET_BYTES, SEQ_MODULO, decode_frames
from facewire.protocol.transport import PacketSubscriber

OPEN_AT_ONCE = 20  # handshakes in flight per process: two stay below a listen backlog of 100
OPEN_TIMEOUT_S = 20.0
CLOSE_S = 1.0  # for the server's answers to the close frames
JOIN_TIMEOUT_S = 100.0  # every client has a packet by then, or the process gives up
READY_POLL_S = 0.1
POLL_MS = 100
KINDS = ("websocket", "zmq")


def raise_fd_limit() -> int:
    """Raise the soft limit of open files to the hard limit (inherited by children); the
    new soft limit."""
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    return hard


class _Recorder:
    """Each client's arrival times and messages, and the stop signal from stdin."""

    def __init__(self, n: int) -> None:
        self.arrivals: list[list[float]] = [[] for _ in range(n)]
        self.messages: list[list[bytes | bytearray | memoryview]] = [[] for _ in range(n)]
        self.closed = np.zeros(n, bool)
        self.retries = np.zeros(n, np.int32)
        self.stop = threading.Event()

    def all_joined(self) -> bool:
        return all(self.arrivals)

    def caught_up(self, last: int) -> bool:
        """Whether every client still connected has received packet ``last`` (a 16-bit seq)
        or a later one."""
        newest = [m[-1] for m, closed in zip(self.messages, self.closed)
                  if m and not closed and len(m[-1]) == PACKET_BYTES]
        if len(newest) < int((~self.closed).sum()):
            return False
        frames, errors = decode_frames(np.frombuffer(b"".join(newest), np.uint8)
                                       .reshape(-1, PACKET_BYTES))
        behind = (frames["seq"].astype(np.int64) - last) % SEQ_MODULO >= SEQ_MODULO // 2
        return not behind.any() and all(e is None for e in errors)

    def joined(self) -> int:
        """How many clients have received a packet."""
        return sum(1 for a in self.arrivals if a)

    def save(self, path: Path) -> None:
        """Decode every message's seq and write ``path`` (module docstring)."""
        counts = [len(a) for a in self.arrivals]
        viewer = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
        flat = [m for ms in self.messages for m in ms]
        seq = np.full(len(flat), -1, np.int32)
        whole = np.array([len(m) == PACKET_BYTES for m in flat], bool)
        if whole.any():
            rows = np.frombuffer(b"".join(m for m, w in zip(flat, whole) if w), np.uint8)
            frames, errors = decode_frames(rows.reshape(-1, PACKET_BYTES))
            valid = np.array([e is None for e in errors], bool)
            seq[np.flatnonzero(whole)[valid]] = frames["seq"][valid]
        arrival = np.fromiter((t for a in self.arrivals for t in a), np.float64, len(flat))
        np.savez(path, viewer=viewer, seq=seq, arrival=arrival, closed=self.closed,
                 retries=self.retries)


class _StampingSelector(selectors.DefaultSelector):
    """The event loop's selector, remembering when its last ``select`` returned."""

    ready_at = 0.0

    def select(self, timeout: float | None = None) -> list:
        ready = super().select(timeout)
        self.ready_at = time.monotonic()
        return ready


class _WebSocketViewer(asyncio.Protocol):
    """One WebSocket client: the library's protocol (``websockets.client.ClientProtocol``)
    over an asyncio connection, each binary frame recorded with the time the loop's poll saw
    its bytes."""

    def __init__(self, uri: WebSocketURI, i: int, rec: _Recorder,
                 selector: _StampingSelector) -> None:
        self.ws = ClientProtocol(uri)
        self.selector = selector
        self.i, self.rec = i, rec
        self.arrivals, self.messages = rec.arrivals[i], rec.messages[i]
        self.transport: asyncio.Transport | None = None
        self.opened: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        self.ws.send_request(self.ws.connect())
        self.flush()

    def data_received(self, data: bytes) -> None:
        now = self.selector.ready_at
        self.ws.receive_data(data)
        if not self.opened.done() and self.ws.state is not State.CONNECTING:
            self.opened.set_result(None)
        for event in self.ws.events_received():
            if type(event) is Frame and event.opcode is Opcode.BINARY:
                self.arrivals.append(now)
                self.messages.append(event.data)
        self.flush()

    def flush(self) -> None:
        assert self.transport is not None
        for chunk in self.ws.data_to_send():
            if chunk:
                self.transport.write(chunk)
            else:  # the protocol asks to close the connection
                self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.opened.done():
            self.opened.set_result(None)
        if not self.rec.stop.is_set():
            self.rec.closed[self.i] = True


async def _websocket_viewers(url: str, n: int, rec: _Recorder,
                             selector: _StampingSelector) -> None:
    uri = parse_uri(url)
    loop = asyncio.get_running_loop()
    viewers = [_WebSocketViewer(uri, i, rec, selector) for i in range(n)]  # in the loop
    gate = asyncio.Semaphore(OPEN_AT_ONCE)

    async def open_one(i: int) -> None:
        """Open viewer i, again (counted in ``retries``) while its handshake times out or is
        refused, as a browser would, until the join deadline."""
        while not rec.stop.is_set():
            viewer = viewers[i]
            async with gate:  # held until the handshake's answer: the server is not flooded
                try:
                    async with asyncio.timeout(OPEN_TIMEOUT_S):
                        await loop.create_connection(functools.partial(_same, viewer), uri.host,
                                                     uri.port)
                        await viewer.opened
                except (OSError, TimeoutError):
                    pass
            if viewer.ws.state is State.OPEN:
                return
            if viewer.transport is not None:
                viewer.transport.abort()
            rec.retries[i] += 1
            rec.closed[i] = False
            viewers[i] = _WebSocketViewer(uri, i, rec, selector)

    start = time.monotonic()
    opening = asyncio.gather(*(open_one(i) for i in range(n)))
    ready = False
    while not rec.stop.is_set():
        if not ready and rec.all_joined():
            ready = True
            _say("ready")
        elif not ready and time.monotonic() - start > JOIN_TIMEOUT_S:
            _say(f"error: of {n} WebSocket clients of {url}, {rec.joined()} had a packet in "
                 f"{time.monotonic() - start:.0f} s ({int(rec.retries.sum())} handshakes "
                 f"timed out or refused)")
            sys.exit(1)
        await asyncio.sleep(READY_POLL_S)
    opening.cancel()
    for viewer in viewers:  # a close frame, as a browser leaving sends, then the TCP close
        if viewer.transport is not None and viewer.ws.state is State.OPEN:
            viewer.ws.send_close()
            viewer.flush()
    await asyncio.sleep(CLOSE_S)
    for viewer in viewers:
        if viewer.transport is not None:
            viewer.transport.abort()


def _zmq_viewers(endpoint: str, n: int, rec: _Recorder) -> None:
    zmq.Context.instance().set(zmq.MAX_SOCKETS, 2 * n + 64)
    subs = [PacketSubscriber(endpoint) for _ in range(n)]
    index = {sub.socket: i for i, sub in enumerate(subs)}
    poller = zmq.Poller()
    for sub in subs:
        poller.register(sub.socket, zmq.POLLIN)
    joined = False
    start = time.monotonic()
    try:
        while not rec.stop.is_set():
            ready = poller.poll(POLL_MS)
            now = time.monotonic()
            for socket, _ in ready:  # level-triggered: one message each, the rest next time
                i = index[socket]
                rec.messages[i].append(socket.recv(zmq.NOBLOCK))
                rec.arrivals[i].append(now)
            if not joined and rec.all_joined():
                joined = True
                _say("ready")
            elif not joined and time.monotonic() - start > JOIN_TIMEOUT_S:
                _say(f"error: of {n} ZeroMQ subscribers of {endpoint}, {rec.joined()} had a "
                     f"packet in {time.monotonic() - start:.0f} s")
                sys.exit(1)
    finally:
        for sub in subs:
            sub.close()


def _same(viewer: _WebSocketViewer) -> _WebSocketViewer:
    """The protocol factory's result: the viewer made beforehand."""
    return viewer


def _say(line: str) -> None:
    print(line, flush=True)


def _wait_for_stop(rec: _Recorder) -> None:
    """Read ``stop SEQ S`` from stdin, then stop once every open client's newest packet is
    ``SEQ`` or later (packets come in order on each connection), or after S seconds."""
    for line in sys.stdin:
        words = line.split()
        if len(words) == 3 and words[0] == "stop":
            last, deadline = int(words[1]), time.monotonic() + float(words[2])
            while not rec.caught_up(last) and time.monotonic() < deadline:
                time.sleep(READY_POLL_S)
            break
    rec.stop.set()


def main(argv: list[str]) -> int:
    """Run the viewers (module docstring); the exit status."""
    if len(argv) != 4 or argv[0] not in KINDS:
        print("usage: python -m facewire.bench.viewers {websocket|zmq} TARGET N OUT.npz",
              file=sys.stderr)
        return 2
    kind, target, n, out = argv[0], argv[1], int(argv[2]), Path(argv[3])
    raise_fd_limit()
    rec = _Recorder(n)
    threading.Thread(target=_wait_for_stop, args=(rec,), daemon=True).start()
    if kind == "websocket":
        selector = _StampingSelector()
        loop = asyncio.SelectorEventLoop(selector)
        try:
            loop.run_until_complete(_websocket_viewers(target, n, rec, selector))
        finally:
            loop.close()
    else:
        _zmq_viewers(target, n, rec)
    rec.save(out)
    _say("done")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
