"""Model update traffic: its limits per receiver, the sender's shaper, and how it is measured.

A model update (``protocol.control``: ``update_chunk`` replies) must never crowd out the
packets, so each receiver's update traffic is bounded twice: at most ``LIMIT_KBPS_1S``
(32 kbit/s) over any 1 s and at most ``LIMIT_KBPS_60S`` (8 kbit/s) over any 60 s. The traffic
counted is the bytes of the ``update_chunk`` messages (msgpack, as ``encode_message`` makes
them; ZeroMQ's frames and the routing envelope add about 10 bytes a message, which the
margins below cover).

The shaper (``UpdateShaper``) keeps, per receiver, a sliding window and a token bucket:

- window: the bytes sent in the last ``WINDOW_S + GUARD_S`` = 1.1 s never exceed
  ``WINDOW_BYTES`` = 4000 (32 kbit/s over 1 s). A message of ``n`` bytes waits until the
  messages sent longer ago than that leave room for it. The 0.1 s guard covers the jitter
  of the messages' transit: as long as it varies by less than that, the bytes that *arrive*
  in any 1 s are what was sent in at most 1.1 s, so at most 4000;
- bucket: (rate r = 700 B/s, depth b = 17000 B), ``BUCKET``. It holds ``min(b, tokens +
  r dt)`` tokens after ``dt`` seconds; a message of ``n`` bytes goes when it holds ``n`` and
  takes them. Over any window of ``T`` s it lets through at most ``b + r T``:
  60 s: 17000 + 700 * 60 = 59000 bytes = 7.87 kbit/s <= 8.

A message goes at the earliest time both allow (each only loosens with time). A receiver
fetching continuously gets three 1.3 kB chunks every 1.1 s (3.6 kB/s) for its first 17 kB,
then 700 B/s: an 8 kB update (about 10.5 kB of chunks) arrives in about 2.2 s. (Two token
buckets, 1 s and 60 s, cannot do as well: with a depth of one message the 1-s bucket's rate
is at most 4000 B/s less a message, 2.5 kB/s.) A message may not exceed
``MAX_MESSAGE_BYTES``, the smaller of the window's bytes and the bucket's depth: an update
chunk is at most ``protocol.control.UPDATE_CHUNK_BYTES`` of data plus about 290 bytes of
fields. A receiver is forgotten once its window is empty and its bucket full again (a new
receiver starts so, nothing is lost).

The replies are held, never the packets: the sender answers control requests on a thread of
its own and sends a held reply when its time comes (``sender.responder``).

Measuring (``window_kbps``): from the times messages arrived and their sizes, the most bytes in
any window ``(t - T, t]`` (one ending at each arrival), over ``T``, in kbit/s; a session
shorter than ``T`` is judged by what it carried over ``T`` all the same (the window extends
beyond it).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np

LIMIT_KBPS_1S = 32.0
LIMIT_KBPS_60S = 8.0
WINDOW_BYTES = int(LIMIT_KBPS_1S * 1000 / 8)  # 4000
WINDOW_S = 1.0
GUARD_S = 0.1
BUCKET = (700.0, 17000.0)  # (bytes per second, depth in bytes)
MAX_MESSAGE_BYTES = int(min(WINDOW_BYTES, BUCKET[1]))


@dataclass
class _Peer:
    sent: deque[tuple[float, int]]  # (time, bytes) of the messages in the window, in order
    tokens: float
    at: float  # the time the tokens are counted at (the last message's departure)


class UpdateShaper:
    """A sliding window and a token bucket per receiver (module docstring): when each
    update message may go.

    Args:
        window_bytes: the most bytes sent in any ``window_s``.
        window_s: the window, s (the limit's second and the guard).
        bucket: (rate bytes/s, depth bytes) of the token bucket.
    """

    def __init__(self, window_bytes: int = WINDOW_BYTES, window_s: float = WINDOW_S + GUARD_S,
                 bucket: tuple[float, float] = BUCKET) -> None:
        self.window_bytes, self.window_s = int(window_bytes), float(window_s)
        self.rate, self.depth = float(bucket[0]), float(bucket[1])
        self._peers: dict[Hashable, _Peer] = {}

    def schedule(self, peer: Hashable, size: int, now: float) -> float:
        """The time (>= ``now``, same clock) at which a message of ``size`` bytes may go to
        ``peer``; it counts as sent then.

        Raises:
            ValueError: ``size`` is not in [1, the window's bytes and the bucket's depth].
        """
        if not 0 < size <= min(self.window_bytes, self.depth):
            raise ValueError(f"update message of {size} bytes: the shaper sends 1 to "
                             f"{int(min(self.window_bytes, self.depth))}")
        self.forget(now)
        state = self._peers.get(peer)
        if state is None:
            state = self._peers[peer] = _Peer(deque(), self.depth, now)
        due = max(now, state.at)
        carried = sum(n for _, n in state.sent)
        for sent_at, n in state.sent:  # the oldest leave the window first
            if carried + size <= self.window_bytes:
                break
            carried -= n
            due = max(due, sent_at + self.window_s)
        tokens = min(self.depth, state.tokens + self.rate * (due - state.at))
        if tokens < size:
            due += (size - tokens) / self.rate
            tokens = size
        state.tokens, state.at = tokens - size, due
        state.sent.append((due, size))
        while state.sent and state.sent[0][0] <= due - self.window_s:
            state.sent.popleft()
        return due

    def peers(self, first: Hashable | None = None) -> int:
        """Receivers being shaped (their window not empty or their bucket not full, as of the
        last ``schedule`` or ``forget``); with
        ``first``, only those named by a tuple that starts with it (the receivers of one
        connection, ``sender.responder``)."""
        if first is None:
            return len(self._peers)
        return sum(isinstance(p, tuple) and p[:1] == (first,) for p in self._peers)

    def shaped(self, peer: Hashable) -> bool:
        """Whether ``peer`` is being shaped (as of the last ``schedule`` or ``forget``)."""
        return peer in self._peers

    def forget(self, now: float) -> None:
        """Drop the receivers whose window is empty and bucket full again by ``now``."""
        for peer, state in list(self._peers.items()):
            if state.at + self.window_s <= now and \
                    state.tokens + self.rate * (now - state.at) >= self.depth:
                del self._peers[peer]


def window_kbps(times: Sequence[float] | np.ndarray, sizes: Sequence[int] | np.ndarray,
                window_s: float) -> float:
    """The most kbit/s carried over any window of ``window_s`` (module docstring).

    Args:
        times: (N,) arrival times, s, any order.
        sizes: (N,) bytes of each message.
        window_s: the window, s.

    Returns:
        8 * max bytes in any ``(t - window_s, t]`` / 1000 / ``window_s``; 0 for no messages.
    """
    t = np.asarray(times, np.float64)
    n = np.asarray(sizes, np.float64)
    if t.shape != n.shape or t.ndim != 1:
        raise ValueError(f"times and sizes: expected two (N,) arrays, got {t.shape} and "
                         f"{n.shape}")
    if len(t) == 0:
        return 0.0
    order = np.argsort(t, kind="stable")
    t, n = t[order], n[order]
    total = np.concatenate([[0.0], np.cumsum(n)])
    first = np.searchsorted(t, t - window_s, side="right")
    carried = total[np.arange(1, len(t) + 1)] - total[first]
    return float(carried.max()) * 8 / 1000 / window_s
