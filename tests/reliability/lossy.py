"""A lossy relay for the reliability tests: a bad network of our own, on loopback.

``LossyRelay`` sits between a sender and its receivers the way ``facewire relay`` does, and
damages the packet stream on purpose:

- packets: a SUB socket connected to the sender's packet endpoint ``inp``, a PUB socket
  bound at ``out``; every message the SUB receives is one *arrival*, numbered 0, 1, 2, ...
  (its ordinal);
- control: a ROUTER bound at ``control_endpoint(out)`` and a DEALER connected to
  ``control_endpoint(inp)``, passing requests and replies through unchanged (the Hello and
  the model always get through: only the packets are damaged), unless ``replies`` is given:
  each reply's frames (routing identity, empty delimiter, body) pass through it, and what it
  returns is forwarded (None: the reply is lost).

Random faults, drawn from ``numpy.random.default_rng(seed)``: each ``Faults`` applies to the
arrivals whose ordinal lies in ``[start, stop)``, drawing one uniform ``u`` per arrival (so a
run is repeatable up to thread timing):

- loss: ``u < loss``, the packet is dropped;
- reordering: ``loss <= u < loss + reorder``, the packet is held back and forwarded right
  after the ``k``-th arrival after it has been dealt with, ``k`` drawn from ``reorder_by``: it
  comes ``k`` packet periods late, behind its successor (held back by 1, it comes right
  after it);
- duplicates: ``loss + reorder <= u < loss + reorder + duplicate``, the packet is forwarded
  twice in a row.

Pauses:

- ``pause(s, keep)`` from any thread stops forwarding now for ``s`` seconds; what
  arrives meanwhile is dropped (``keep=False``: a link that goes dead) or held and forwarded
  at once when the pause ends (``keep=True``: a stalled link that delivers its backlog late);
- ``bursts[n] = s`` pauses for ``s`` seconds at arrival ``n``, dropping
  (a burst of loss); ``stalls[n] = s`` the same, keeping.

Packets held back for reordering are forwarded anyway once no packet has arrived for
``flush_s`` (the end of a stream). ``record()`` returns exactly what was forwarded, in
order, with each packet's sequence number (None for a message that is no valid packet) and
the time it was forwarded, and what was dropped.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import zmq

from facewire.protocol.packet import PacketError, decode
from facewire.protocol.transport import control_endpoint

POLL_MS = 5


@dataclass(frozen=True)
class Faults:
    """Random faults for the arrivals ``start <= ordinal < stop`` (module docstring)."""

    start: int
    stop: int
    loss: float = 0.0
    reorder: float = 0.0
    duplicate: float = 0.0
    reorder_by: tuple[int, ...] = (1, 2)

    def __post_init__(self) -> None:
        rates = (self.loss, self.reorder, self.duplicate)
        if not all(0.0 <= r <= 1.0 for r in rates) or sum(rates) > 1.0:
            raise ValueError(f"loss, reorder, duplicate: probabilities summing to <= 1, "
                             f"got {rates}")
        if not self.reorder_by or min(self.reorder_by) < 1:
            raise ValueError(f"reorder_by: counts >= 1, got {self.reorder_by}")


@dataclass(frozen=True)
class Record:
    """What a ``LossyRelay`` did so far.

    Attributes:
        arrived: messages received from the sender.
        forwarded: (seq, time) of every message forwarded, in order: seq of the packet (None
            when it is no valid packet), time on ``time.monotonic``.
        dropped: seq of every message dropped (by loss, a burst or a pause), in order.
        kept: seq of every message held by a pause that keeps (a stall), in order; each is
            forwarded when the pause ends.
    """

    arrived: int
    forwarded: tuple[tuple[int | None, float], ...]
    dropped: tuple[int | None, ...]
    kept: tuple[int | None, ...]

    @property
    def seqs(self) -> list[int | None]:
        """The sequence numbers forwarded, in order (a duplicate appears twice)."""
        return [seq for seq, _ in self.forwarded]

    @property
    def duplicates(self) -> int:
        """Packets forwarded more than once: each copy after the first counts one."""
        return len(self.forwarded) - len(set(self.seqs))


class LossyRelay(threading.Thread):
    """The relay (module docstring); it runs from construction until ``stop()``.

    Args:
        inp: the sender's packet endpoint ``tcp://HOST:PORT`` (its control on PORT + 1).
        out: the endpoint to bind for receivers, ``tcp://HOST:PORT`` (control on PORT + 1).
        seed: the random generator's seed.
        faults: the random faults, by range of arrivals (the first that covers one applies).
        bursts: arrival ordinal -> seconds of dropping everything from that arrival on.
        stalls: arrival ordinal -> seconds of holding everything from that arrival on.
        flush_s: forward the packets held for reordering after this long without arrivals.
        replies: the control replies' fault (module docstring), or None.
    """

    def __init__(self, inp: str, out: str, seed: int = 0, faults: Sequence[Faults] = (),
                 bursts: Mapping[int, float] | None = None,
                 stalls: Mapping[int, float] | None = None, flush_s: float = 0.1,
                 replies: Callable[[list[bytes]], list[bytes] | None] | None = None) -> None:
        super().__init__(daemon=True, name="lossy relay")
        self.inp, self.out = inp, out
        self.faults = tuple(faults)
        self.pauses = {n: (s, False) for n, s in (bursts or {}).items()}
        self.pauses.update({n: (s, True) for n, s in (stalls or {}).items()})
        self.flush_s = flush_s
        self.replies = replies
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._arrived = 0
        self._forwarded: list[tuple[int | None, float]] = []
        self._dropped: list[int | None] = []
        self._kept: list[int | None] = []
        self._held: list[list] = []  # [arrivals still to wait for, bytes]
        self._backlog: list[bytes] = []  # what arrived during a pause with keep=True
        self._pause_until = -math.inf
        self._keep = False
        self._last_arrival = -math.inf
        self._halt = threading.Event()
        self._bound = threading.Event()
        self._error: BaseException | None = None
        self.start()
        if not self._bound.wait(10) or self._error is not None:
            raise RuntimeError(f"the lossy relay could not start: {self._error}")

    def pause(self, seconds: float, keep: bool = False) -> None:
        """Stop forwarding now for ``seconds``; drop what arrives meanwhile, or keep it and
        forward it when the pause ends."""
        with self._lock:
            self._pause_until = time.monotonic() + seconds
            self._keep = keep

    @property
    def holding(self) -> bool:
        """True while paused, or while packets wait to be forwarded (held or kept)."""
        with self._lock:
            return time.monotonic() < self._pause_until or bool(self._held or self._backlog)

    def record(self) -> Record:
        with self._lock:
            return Record(self._arrived, tuple(self._forwarded), tuple(self._dropped),
                          tuple(self._kept))

    def stop(self) -> Record:
        """Stop the relay and close its sockets; what it did."""
        self._halt.set()
        self.join(10)
        if self._error is not None:
            raise RuntimeError(f"the lossy relay failed: {self._error}") from self._error
        return self.record()

    # -- the relay thread ------------------------------------------------------------------

    def run(self) -> None:
        context = zmq.Context()
        sockets = []

        def socket(kind: int) -> zmq.Socket:
            s = context.socket(kind)
            s.linger = 0
            s.sndhwm = s.rcvhwm = 10_000
            sockets.append(s)
            return s

        try:
            sub, pub = socket(zmq.SUB), socket(zmq.PUB)
            router, dealer = socket(zmq.ROUTER), socket(zmq.DEALER)
            sub.setsockopt(zmq.SUBSCRIBE, b"")
            pub.bind(self.out)
            router.bind(control_endpoint(self.out))
            sub.connect(self.inp)
            dealer.connect(control_endpoint(self.inp))
            self._pub = pub
            poller = zmq.Poller()
            for s in (sub, router, dealer):
                poller.register(s, zmq.POLLIN)
            self._bound.set()
            while not self._halt.is_set():
                ready = dict(poller.poll(POLL_MS))
                if router in ready:
                    dealer.send_multipart(router.recv_multipart())
                if dealer in ready:
                    reply: list[bytes] | None = dealer.recv_multipart()
                    if self.replies is not None:
                        reply = self.replies(reply)
                    if reply is not None:
                        router.send_multipart(reply)
                if sub in ready:
                    self._arrive(sub.recv())
                self._timers()
        except Exception as exc:  # noqa: BLE001 - reported by stop()
            self._error = exc
            self._bound.set()
        finally:
            for s in sockets:
                s.close(linger=0)
            context.term()

    def _arrive(self, data: bytes) -> None:
        now = time.monotonic()
        with self._lock:
            n = self._arrived
            self._arrived += 1
            self._last_arrival = now
            if n in self.pauses:
                seconds, self._keep = self.pauses[n]
                self._pause_until = now + seconds
            if now < self._pause_until:
                if self._keep:
                    self._backlog.append(data)
                    self._kept.append(_seq(data))
                else:
                    self._dropped.append(_seq(data))
                return
            self._release_backlog()
            held = self._held[:]  # those waiting for this arrival
            copies = 1
            f = next((f for f in self.faults if f.start <= n < f.stop), None)
            if f is not None:
                u = self._rng.random()
                if u < f.loss:
                    self._dropped.append(_seq(data))
                    copies = 0
                elif u < f.loss + f.reorder:
                    self._held.append([int(self._rng.choice(f.reorder_by)), data])
                    copies = 0
                elif u < f.loss + f.reorder + f.duplicate:
                    copies = 2
            for _ in range(copies):
                self._forward(data)
            for item in held:  # one more arrival dealt with: release those whose wait is over
                item[0] -= 1
                if item[0] == 0:
                    self._forward(item[1])
            self._held = [item for item in self._held if item[0] > 0]

    def _timers(self) -> None:
        now = time.monotonic()
        with self._lock:
            if now >= self._pause_until:
                self._release_backlog()
            if self._held and now - self._last_arrival > self.flush_s:
                for _, data in self._held:
                    self._forward(data)
                self._held.clear()

    def _release_backlog(self) -> None:
        for data in self._backlog:
            self._forward(data)
        self._backlog.clear()

    def _forward(self, data: bytes) -> None:
        self._pub.send(data)
        self._forwarded.append((_seq(data), time.monotonic()))


def _seq(data: bytes) -> int | None:
    try:
        return decode(data).seq
    except PacketError:
        return None
