"""The one clock: how a receiver reads a sender's times on its own clock.

Clocks
------
Every host keeps time on its own monotonic clock (``time.monotonic()``, seconds: it never
steps, unlike the wall clock). Times that travel between hosts (a frame's capture, later a
sound's) are on the *sender's* clock; a receiver turns them into its own by subtracting the
offset ``theta`` (the sender's clock minus the receiver's), estimated over the control
channel as NTP does (RFC 5905, section 8).

Offset: four timestamps
-----------------------
The receiver sends ``TimeRequest(t1)`` at ``t1`` on its clock; the sender stamps ``t2`` on
receiving it and ``t3`` on replying, on its clock (``TimeReply(t1, t2, t3)``); the reply
arrives at ``t4`` on the receiver's clock. With ``d_up``, ``d_down`` the two one-way delays::

    t2 = t1 + theta + d_up,   t4 = t3 - theta + d_down
    offset  = ((t2 - t1) + (t3 - t4)) / 2 = theta + (d_up - d_down) / 2
    delay   = (t4 - t1) - (t3 - t2)       = d_up + d_down

so ``|offset - theta| <= delay / 2`` whatever the split of the path: the sample with the
least delay bounds the error best. ``OffsetEstimator`` keeps the last ``WINDOW`` samples and
answers with the one of least delay (a queue behind a model chunk or a busy thread only ever
adds delay). A sample is refused (``ClockError``) when a timestamp is not finite, when
``t4 < t1`` or ``t3 < t2``, or when its delay is negative beyond ``NEGATIVE_DELAY_S`` (clocks
that are not monotonic, or a forged reply).

Capture times of a stream
-------------------------
The sender captures frame slot ``n`` at ``origin_s + n / rate_hz`` on its clock
(``sender.slots``); the Hello carries ``clock_origin_s`` and ``rate_hz``, and the packet's
16-bit ``seq`` is ``n mod 65536``. A receiver extends a wire ``seq`` to the ``n`` whose
capture time is nearest a time ``near_s`` it knows to be close (the packet's arrival on the
sender's clock): ``n = seq + 65536 m``, ``m = round(((near_s - origin_s) rate_hz - seq) /
65536)``, right while the capture is within half a wrap (18 minutes at 30 Hz) of ``near_s``.
Glass-to-glass latency is then ``t_out - (capture_s(n) - offset)`` on the receiver's clock,
``t_out`` the time its frame is out (written, shown, handed on).

A sender that releases a frame more than ``MAX_LAG_S`` after its slot's time (a busy
machine) starts its clock again at that frame: the origin moves later and the Hello announces
the new one, while the seqs stay consecutive. A receiver that keeps the old origin reads
every later capture as early by the move, so a packet that arrives more than ``MAX_LAG_S``
after its capture time by the origin taken is the sign to ask for the Hello again
(``receiver.link``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from facewire.protocol.errors import FacewireError

WINDOW = 16
MAX_LAG_S = 0.5  # a sender starts its slots' clock again at a frame later than this
NEGATIVE_DELAY_S = 1e-4
SEQ_WRAP = 1 << 16


class ClockError(FacewireError, ValueError):
    """Four timestamps that are not a valid exchange (the message says which rule failed)."""


@dataclass(frozen=True)
class Sample:
    """One exchange: ``offset_s`` (sender clock minus receiver clock), ``delay_s`` (round
    trip less the sender's time), ``at_s`` (its ``t4``, receiver clock)."""

    offset_s: float
    delay_s: float
    at_s: float


def sample(t1: float, t2: float, t3: float, t4: float) -> Sample:
    """The offset and delay of one exchange (module docstring).

    Raises:
        ClockError: a timestamp not finite, ``t4 < t1``, ``t3 < t2`` or a negative delay.
    """
    if not all(isinstance(t, (int, float)) and math.isfinite(t) for t in (t1, t2, t3, t4)):
        raise ClockError("clock exchange: a timestamp is not a finite number")
    if t4 < t1 or t3 < t2:
        raise ClockError("clock exchange: a reply before its request (t4 < t1 or t3 < t2)")
    delay = (t4 - t1) - (t3 - t2)
    if delay < -NEGATIVE_DELAY_S:
        raise ClockError(f"clock exchange: negative delay {delay * 1000:.3f} ms")
    return Sample(((t2 - t1) + (t3 - t4)) / 2, max(delay, 0.0), t4)


class OffsetEstimator:
    """The offset of the least-delay sample of the last ``window`` (module docstring).

    Attributes:
        samples: how many were added in all.
    """

    def __init__(self, window: int = WINDOW) -> None:
        self._recent: deque[Sample] = deque(maxlen=window)
        self.samples = 0

    def add(self, s: Sample) -> None:
        self._recent.append(s)
        self.samples += 1

    def best(self) -> Sample | None:
        """The least-delay sample of the window, or None before any."""
        return min(self._recent, key=lambda s: s.delay_s) if self._recent else None


def capture_s(seq: int, origin_s: float, rate_hz: float, near_s: float) -> float:
    """The capture time (sender clock, s) of wire ``seq`` in a stream whose slot 0 was
    captured at ``origin_s``, extended to the wrap nearest ``near_s`` (module docstring)."""
    m = round(((near_s - origin_s) * rate_hz - seq) / SEQ_WRAP)
    return origin_s + (seq + SEQ_WRAP * m) / rate_hz
