"""The stream's slots on the sender's clock: which slot a frame is, and when it was captured.

A stream at ``rate_hz`` has slot ``n`` captured at ``origin_s + n / rate_hz`` on the sender's
clock (``protocol.clock``); its packet's ``seq`` is ``n mod 65536``, and the Hello announces
``origin_s`` as ``clock_origin_s``, so that a receiver knows every frame's capture time from
its ``seq`` alone, with no field in the packet. Slot 0 is the stream's first frame, so the
first packet's seq is 0. The mapping holds exactly because numbers follow time, not frames:

- a video file (``SlotClock.release``): the file's frame for media time ``t_0 + k /
  rate_hz`` is released (its capture, as a camera would deliver it) at its slot's time. The
  clock starts at the first frame and, if the second is late, starts again there: the first
  frame's processing holds the pipeline's one-time warm-up (the tracker's first detection,
  the identity check: up to seconds on a busy machine), which no later frame pays (slot 0's
  capture time is then announced later than its release, by that warm-up less a period).
  A frame late by up to ``max_lag_s`` (the machine was busy) is released at once, its
  capture time still its slot's, so its lateness counts in the latency; one later than that
  starts the clock again at itself, as after the warm-up: the origin moves later by its
  lateness and the send loop announces the new origin in the Hello, so seqs stay consecutive
  (a receiver sees no lost slot) and the frames between the move and a receiver's next Hello
  are read with the old origin, too early by the move. Numbering the present slot instead,
  the numbers in between left unused, kept every seq exact but made receivers count a
  stalled sender's gap as lost and render it (measured in the demo under a loaded run: 140
  of 210 slots);
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
    """Release a file's frames on the sender's clock and number them (module docstring).

    Args:
        rate_hz: the stream's rate, > 0.
        max_lag_s: the lateness beyond which the clock starts again at the late frame.
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
        self._released = 0

    def skew_s(self) -> float:
        """The sender's clock minus ``time.monotonic()`` (a camera stamps with the latter)."""
        return self._clock() - time.monotonic()

    def release(self, k: int) -> int:
        """Wait for the time of the ``k``-th frame of the file's schedule (0, 1, ...) and
        return its slot number, ``k`` (module docstring)."""
        now = self._clock()
        self._released += 1
        if self.origin_s is None:
            self.origin_s = now - k / self.rate_hz
            return k
        delay = self.origin_s + k / self.rate_hz - now
        if delay > 0:
            self._sleep(delay)
        elif self._released == 2 or -delay > self.max_lag_s:  # the clock starts again here
            self.origin_s -= delay
        return k


def camera_slot(t: float, rate_hz: float) -> int:
    """The slot of a camera frame at ``t`` s after the camera's first (module docstring)."""
    return math.floor(t * rate_hz + 0.25)
