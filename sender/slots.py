"""The stream's slots on the sender's clock: which slot a frame is, and when it was captured.

A stream at ``rate_hz`` has slot ``n`` captured at ``origin_s + n / rate_hz`` on the sender's
clock (``protocol.clock``); its packet's ``seq`` is ``n mod 65536``, and the Hello announces
``origin_s`` as ``clock_origin_s``, so that a receiver knows every frame's capture time from
its ``seq`` alone, with no field in the packet. Slot 0 is the stream's first frame, so the
first packet's seq is 0. The mapping holds exactly because numbers follow time, not frames:

- a video file (``release``): slot ``n`` is the file's frame for media time ``t_0 + n /
  rate_hz``, released (its capture, as a camera would deliver it) at ``origin_s + n /
  rate_hz``; the first slot released sets ``origin_s``. A frame late by up to ``max_lag_s``
  (the machine was busy) is released at once, its capture time still its slot's, so its
  lateness counts in the latency; a slot later than that is given up: its number stays
  unused and the stream resumes at the slot of the present, where a schedule that shifted
  instead would leave every later seq naming the wrong time;
- a camera (``camera_slot``): frame time ``t`` (seconds after the camera's first frame,
  read at ``origin_s``) is slot ``floor(t rate_hz + 1/4)`` (``sender.capture.RateLimiter``'s
  rule, which keeps one frame per slot): a slot without a frame (the camera was slower, or
  dropped one) leaves its number unused. The frame was read within ``[-1/4, +3/4)`` of a
  period of its slot's time: for a camera the announced capture time is the slot's, to
  that tolerance (the device's own exposure time, before it is read, is not known here).

A receiver sees an unused number as a missing packet (``receiver.playout``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

Clock = Callable[[], float]
Sleep = Callable[[float], object]


class SlotClock:
    """Release a file's slots on the sender's clock (module docstring).

    Args:
        rate_hz: the stream's rate, > 0.
        max_lag_s: the lateness beyond which a slot is given up.
        clock: the sender's clock, s.
        sleep: waits (e.g. ``threading.Event.wait``, which a stop ends early).

    Attributes:
        origin_s: slot 0's capture time, None before the first release.
    """

    def __init__(self, rate_hz: float, max_lag_s: float, clock: Clock = time.monotonic,
                 sleep: Sleep = time.sleep) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz: expected a positive number, got {rate_hz!r}")
        self.rate_hz, self.max_lag_s = float(rate_hz), max_lag_s
        self._clock, self._sleep = clock, sleep
        self.origin_s: float | None = None

    def skew_s(self) -> float:
        """The sender's clock minus ``time.monotonic()`` (a camera stamps with the latter)."""
        return self._clock() - time.monotonic()

    def capture_s(self, slot: int) -> float:
        """Slot ``slot``'s capture time (after the first release)."""
        assert self.origin_s is not None  # release() came first
        return self.origin_s + slot / self.rate_hz

    def release(self, slot: int) -> bool:
        """Wait for ``slot``'s time; False (at once) when it is more than ``max_lag_s`` late:
        give it up. The first call starts the clock at ``slot`` (0 for a stream)."""
        now = self._clock()
        if self.origin_s is None:
            self.origin_s = now - slot / self.rate_hz
            return True
        delay = self.capture_s(slot) - now
        if delay > 0:
            self._sleep(delay)
        return -delay <= self.max_lag_s


def camera_slot(t: float, rate_hz: float) -> int:
    """The slot of a camera frame at ``t`` s after the camera's first (module docstring)."""
    return math.floor(t * rate_hz + 0.25)
