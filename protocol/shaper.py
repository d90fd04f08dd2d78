"""Model update traffic: its limits per receiver, the sender's shaper, and how it is measured.

A model update (``protocol.control``: ``update_chunk`` replies) must never crowd out the
packets, so each receiver's update traffic is bounded twice: at most ``LIMIT_KBPS_1S``
(32 kbit/s) over any 1 s and at most ``LIMIT_KBPS_60S`` (8 kbit/s) over any 60 s. The traffic
counted is the bytes of the ``update_chunk`` messages (msgpack, as ``encode_message`` makes
them; ZeroMQ's frames and the routing envelope add about 10 bytes a message, which the
margins below cover).

The shaper (``UpdateShaper``) holds two token buckets per receiver, (rate r_i bytes/s, depth
b_i bytes), ``BUCKETS``. A bucket holds ``min(b_i, tokens + r_i dt)`` tokens after ``dt``
seconds; a message of ``n`` bytes goes out at the earliest time every bucket holds ``n``
tokens, and takes ``n`` from each. Over any window of ``T`` seconds a bucket lets through at
most ``b_i + r_i T`` bytes, so:

    1 s:   1500 + 2400 * 1  =  3900 bytes  = 31.2 kbit/s  <= 32
    60 s: 17000 +  700 * 60 = 59000 bytes  =  7.87 kbit/s <= 8

A receiver fetching continuously gets about 2.4 kB/s for the first 7 s (the deep bucket's
17 kB), then 700 B/s. A message may not exceed the smallest depth (``MAX_MESSAGE_BYTES``):
an update chunk is at most ``protocol.control.UPDATE_CHUNK_BYTES`` of data plus about 290
bytes of fields. A receiver's buckets are forgotten once full again (a new receiver starts
full, so nothing is lost).

The replies are held, never the packets: the sender answers control requests on a thread of
its own and sends a held reply when its time comes (``sender.responder``).

Measuring (``window_kbps``): from the times messages arrived and their sizes, the most bytes in
any window ``(t - T, t]`` (one ending at each arrival), over ``T``, in kbit/s; a session
shorter than ``T`` is judged by what it carried over ``T`` all the same (the window extends
beyond it).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np

LIMIT_KBPS_1S = 32.0
LIMIT_KBPS_60S = 8.0
BUCKETS = ((2400.0, 1500.0), (700.0, 17000.0))  # (bytes per second, depth in bytes)
MAX_MESSAGE_BYTES = int(min(depth for _, depth in BUCKETS))


@dataclass
class _Buckets:
    tokens: list[float]
    at: float  # the time the tokens are counted at (the last message's departure)


class UpdateShaper:
    """Two token buckets per receiver (module docstring): when each update message may go.

    Args:
        buckets: (rate bytes/s, depth bytes) of each bucket.
    """

    def __init__(self, buckets: Sequence[tuple[float, float]] = BUCKETS) -> None:
        self.buckets = tuple((float(r), float(b)) for r, b in buckets)
        self._peers: dict[Hashable, _Buckets] = {}

    def schedule(self, peer: Hashable, size: int, now: float) -> float:
        """The time (>= ``now``, same clock) at which a message of ``size`` bytes may go to
        ``peer``; its bytes are taken from the peer's buckets at that time.

        Raises:
            ValueError: ``size`` is not in [1, the smallest depth].
        """
        if not 0 < size <= min(b for _, b in self.buckets):
            raise ValueError(f"update message of {size} bytes: the shaper sends 1 to "
                             f"{MAX_MESSAGE_BYTES}")
        self._forget(now)
        state = self._peers.get(peer)
        if state is None:
            state = self._peers[peer] = _Buckets([b for _, b in self.buckets], now)
        start = max(now, state.at)
        tokens = [min(b, t + r * (start - state.at))
                  for (r, b), t in zip(self.buckets, state.tokens, strict=True)]
        wait = max(max(0.0, (size - t) / r) for (r, _), t in zip(self.buckets, tokens,
                                                                 strict=True))
        due = start + wait
        state.tokens = [min(b, t + r * wait) - size
                        for (r, b), t in zip(self.buckets, tokens, strict=True)]
        state.at = due
        return due

    def peers(self) -> int:
        """Receivers whose buckets are not full (those being shaped)."""
        return len(self._peers)

    def _forget(self, now: float) -> None:
        """Drop the receivers whose buckets are full again by ``now``."""
        for peer, state in list(self._peers.items()):
            if state.at <= now and all(t + r * (now - state.at) >= b for (r, b), t in
                                       zip(self.buckets, state.tokens, strict=True)):
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
