"""The packet socket's own thread: packets in, stamped with their arrival time, queued.

Shared by the live receiver (``receiver.receiver``) and the browser gateway
(``receiver.gateway``). A thread owns the SUB socket (``protocol.transport.PacketSubscriber``)
and, for each message, stamps it on ``time.monotonic()``, appends ``(bytes, arrival)`` to a
queue of at most ``capacity`` (beyond that the message is dropped and counted: ``overflow``),
sets ``arrived`` and calls ``notify`` (from the reader's thread: e.g. to wake an event loop).
The consumer takes packets in arrival order with ``take``. Messages are not parsed here:
corrupt ones are queued like the others, for the consumer to count. A ``divert`` callback
sees each message first, on the reader's thread, and keeps the ones it takes out of the queue
(the voice: ``receiver.voiceplayer``, whose packets must not wait behind the face's).

After ``reopen_s`` without a message the socket is opened anew: libzmq does not reconnect a
socket whose peer broke the protocol (e.g. sent a frame over
``protocol.transport.MAX_PACKET_FRAME``), and a fresh one costs nothing.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

from facewire.protocol.errors import FacewireError
from facewire.protocol.transport import PacketSubscriber

POLL_MS = 50


class PacketReaderError(FacewireError, RuntimeError):
    """The packet socket failed on its thread; the message says how."""


class PacketReader:
    """Reads a packet socket on its own thread (module docstring).

    Args:
        open_socket: makes a connected packet socket (called again to reopen it).
        capacity: the most packets queued; more are dropped (``overflow``).
        reopen_s: seconds without a message after which the socket is opened anew.
        notify: called (on the reader's thread) after each packet queued, or None.
        divert: called (on the reader's thread) with each message and its arrival; a message
            for which it returns True is not queued. None: every message is queued.

    Attributes:
        arrived: set on each packet queued (the consumer clears it before taking).
        overflow: packets dropped for a full queue.
        last_arrival: ``time.monotonic()`` of the last message, or None.
    """

    def __init__(self, open_socket: Callable[[], PacketSubscriber], capacity: int,
                 reopen_s: float, notify: Callable[[], None] | None = None,
                 divert: Callable[[bytes, float], bool] | None = None) -> None:
        self._open = open_socket
        self._sub = open_socket()
        self._capacity, self._reopen_s, self._notify = capacity, reopen_s, notify
        self._divert = divert
        self._queue: deque[tuple[bytes, float]] = deque()
        self._closing = threading.Event()
        self.arrived = threading.Event()
        self.overflow = 0
        self.last_arrival: float | None = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="facewire packets",
                                        daemon=True)
        self._thread.start()

    def _run(self) -> None:
        quiet_since = time.monotonic()
        try:
            while not self._closing.is_set():
                data = self._sub.recv(POLL_MS)
                if data is None:
                    if time.monotonic() - quiet_since > self._reopen_s:
                        self._sub.close()
                        self._sub = self._open()
                        quiet_since = time.monotonic()
                    continue
                now = quiet_since = time.monotonic()
                self.last_arrival = now
                if self._divert is not None and self._divert(data, now):
                    continue
                if len(self._queue) >= self._capacity:
                    self.overflow += 1
                    continue
                self._queue.append((data, now))
                self.arrived.set()
                if self._notify is not None:
                    self._notify()
        except Exception as exc:  # noqa: BLE001 - reported by take()
            self.error = exc
        finally:
            self._sub.close()

    def take(self) -> tuple[bytes, float] | None:
        """The oldest queued packet and its arrival time, out of the queue; None if empty.

        Raises:
            PacketReaderError: the socket failed on the reader's thread.
        """
        if self.error is not None:
            raise PacketReaderError(f"packet socket failed: {self.error}") from self.error
        try:
            return self._queue.popleft()
        except IndexError:
            return None

    def discard(self) -> int:
        """Empty the queue; how many packets were in it."""
        count = 0
        while self.take() is not None:
            count += 1
        return count

    def queued(self) -> int:
        return len(self._queue)

    def close(self) -> None:
        """Stop the thread and close the socket (what is queued can still be taken)."""
        self._closing.set()
        self._thread.join()
