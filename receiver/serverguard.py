"""What the receiver's HTTP servers (``facewire web``, the live view) bound before anyone is
known: connections, open files, error lines and failed tokens.

Connections (``Admission``). A connection is *pending* from its accept until it is admitted
as a viewer (its request read and answered, or its WebSocket open), *open* after. At most
``pending_cap`` are pending and ``total_cap`` are held in all. A new connection beyond either
evicts the oldest pending one if that one has been pending for ``evict_after_s`` or more
(a client that trickles its request holds a slot for at most that long once others come),
and is refused (closed at once) otherwise. The new connection is never the one evicted: a
normal client's request takes milliseconds, so it gets through unless
``pending_cap`` others arrive within that time. A request cut short leaves what was read of
it in reference cycles (the parser's exception, its traceback, the frames' locals) that only
the cyclic garbage collector frees: ``tidy`` runs it once ``TIDY_AFTER`` connections have
ended since the last run, so that what attackers sent is freed within moments of their
leaving, not at the collector's next full pass; then glibc's ``malloc_trim(0)`` hands the
freed pages back to the system (glibc keeps them otherwise, between the packets' buffers).

Open files (``open_file_caps``). A connection is one file descriptor. The caps come from the
soft ``RLIMIT_NOFILE`` (read, never raised) less the descriptors open when the server starts
and ``FD_SPARE`` kept for the process's other work (sockets reopened, files read):
``backlog = clamp(spare // 4, 1, 100)`` (the listen backlog, also the connections asyncio
accepts in one go before any is refused) and ``total = min(wanted, spare - backlog)``, so
``accept`` does not meet ``EMFILE`` while the caps hold.

Errors (``QuietErrors``). An asyncio exception handler: every error the loop reports (an
``accept`` that failed, a callback that raised) is counted, and one line, without a
traceback, is said at most every ``every_s`` seconds with the count since the last line.

Failed tokens (``FailureThrottle``). Each client address (an IPv6 one by its /64) has a
score: +1 per failed token, minus 1 per second since (never below 0). A request from an
address whose score is over ``FREE_FAILURES`` is answered after
``min(MAX_DELAY_S, BASE_DELAY_S * 2 ** (score - FREE_FAILURES))`` seconds; a right token is
answered at once whatever the score. At most ``MAX_ADDRESSES`` scores are kept (the lowest
dropped first).
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import gc
import ipaddress
import os
import resource
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

FD_SPARE = 32
FREE_FAILURES = 5
BASE_DELAY_S = 0.05
MAX_DELAY_S = 3.0
MAX_ADDRESSES = 4096
TIDY_AFTER = 32


def _glibc() -> ctypes.CDLL | None:
    """The C library when it is glibc (it has ``malloc_trim``), else None."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
        return libc
    except (OSError, AttributeError, TypeError):
        return None


_LIBC = _glibc()


def open_file_caps(wanted: int) -> tuple[int, int]:
    """(total connections, listen backlog) below the open-files limit (module docstring).

    Args:
        wanted: the cap the server would have with no such limit.
    """
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return wanted, 100
    try:
        in_use = len(os.listdir("/proc/self/fd"))
    except OSError:
        in_use = 64
    spare = max(2, soft - in_use - FD_SPARE)
    backlog = min(100, max(1, spare // 4))
    return max(1, min(wanted, spare - backlog)), backlog


class Admission:
    """The pending and open connections of one server (module docstring); the event loop's
    thread only.

    Args:
        total_cap: connections held at most, pending and open.
        pending_cap: connections pending at most.
        evict_after_s: a pending connection this old may be evicted for a new one.
    """

    def __init__(self, total_cap: int, pending_cap: int, evict_after_s: float) -> None:
        self.total_cap, self.pending_cap = total_cap, max(1, min(pending_cap, total_cap))
        self.evict_after_s = evict_after_s
        self._pending: OrderedDict[asyncio.WriteTransport, float] = OrderedDict()
        self._open: set[asyncio.WriteTransport] = set()
        self.evicted = 0
        self.refused = 0
        self._ended = 0

    def __len__(self) -> int:
        return len(self._pending) + len(self._open)

    def admit(self, transport: asyncio.WriteTransport) -> bool:
        """A new connection: True if it is held (pending), False if refused (the caller
        closes it). May abort the oldest pending connection to make room."""
        if len(self._pending) >= self.pending_cap or len(self) >= self.total_cap:
            oldest = next(iter(self._pending.items()), None)
            if oldest is None or time.monotonic() - oldest[1] < self.evict_after_s:
                self.refused += 1
                return False
            del self._pending[oldest[0]]
            oldest[0].abort()
            self.evicted += 1
        self._pending[transport] = time.monotonic()
        return True

    def promote(self, transport: asyncio.WriteTransport) -> None:
        """A pending connection is now a viewer: it is never evicted."""
        if self._pending.pop(transport, None) is not None:
            self._open.add(transport)

    def release(self, transport: asyncio.WriteTransport) -> None:
        """A connection has ended."""
        self._pending.pop(transport, None)
        self._open.discard(transport)
        self._ended += 1

    def tidy(self) -> None:
        """Collect the garbage of the connections that ended, once ``TIDY_AFTER`` have
        (module docstring)."""
        if self._ended >= TIDY_AFTER:
            self._ended = 0
            gc.collect()
            if _LIBC is not None:
                _LIBC.malloc_trim(0)

    def close_all(self) -> None:
        """Close every connection held (each flushes what it has to send first)."""
        for transport in [*self._pending, *self._open]:
            transport.close()


class QuietErrors:
    """An event loop's exception handler that says one line per ``every_s`` (module
    docstring).

    Args:
        say: called with the line.
        what: the line's start, e.g. ``"connections"``.
        every_s: the least time between two lines.
    """

    def __init__(self, say: Callable[[str], None], what: str, every_s: float = 10.0) -> None:
        self.say, self.what, self.every_s = say, what, every_s
        self.count = 0
        self._unsaid = 0
        self._next = 0.0

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        self.count += 1
        self._unsaid += 1
        now = time.monotonic()
        if now < self._next:
            return
        exc = context.get("exception")
        text = str(context.get("message", "error"))
        if exc is not None:
            text += f": {type(exc).__name__}: {exc}"
        more = f" ({self._unsaid - 1} more errors in the last {self.every_s:g} s)" \
            if self._unsaid > 1 else ""
        self.say(f"{self.what}: {text}{more}")
        self._unsaid, self._next = 0, now + self.every_s


class FailureThrottle:
    """Scores of failed tokens per client address, and the delay they earn (module
    docstring)."""

    def __init__(self) -> None:
        self._scores: dict[str, tuple[float, float]] = {}  # address: (score, at)

    def delay(self, address: str | None) -> float:
        """The seconds to wait before answering a request from ``address``."""
        score = self._score(_key(address), time.monotonic())
        if score <= FREE_FAILURES:
            return 0.0
        return min(MAX_DELAY_S, BASE_DELAY_S * 2 ** (score - FREE_FAILURES))

    def failed(self, address: str | None) -> None:
        """A request from ``address`` carried a wrong or no token."""
        key, now = _key(address), time.monotonic()
        self._scores[key] = (self._score(key, now) + 1, now)
        if len(self._scores) > MAX_ADDRESSES:
            lowest = sorted(self._scores, key=lambda k: self._score(k, now))
            for gone in lowest[:len(self._scores) - MAX_ADDRESSES]:
                del self._scores[gone]

    def _score(self, key: str, now: float) -> float:
        score, at = self._scores.get(key, (0.0, now))
        return max(0.0, score - (now - at))


def _key(address: str | None) -> str:
    """An address as throttled: IPv4 as it is, IPv6 by its /64."""
    if address is None:
        return ""
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        return address
    if ip.version == 6:
        return str(ipaddress.ip_network(f"{ip}/64", strict=False))
    return str(ip)
