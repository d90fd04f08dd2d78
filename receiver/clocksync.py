"""The sender's clock as this host sees it: time exchanges on a thread of their own.

A ``ClockSync`` asks the sender ``TimeRequest(t1)`` over a control socket of its own
(``receiver.acquire.ControlChannel``, so that neither the Hello nor the model's chunks wait
behind it) and keeps each valid exchange in a ``protocol.clock.OffsetEstimator``: ``BURST``
exchanges ``BURST_GAP_S`` apart at the start, then one every ``REFRESH_S``, each waiting at
most ``TIMEOUT_S``. The estimate is the least-delay sample of the last
``protocol.clock.WINDOW`` (16 s at one a second: two hosts' clocks drift apart by tens of
microseconds in that time). A sender that answers the request with an ``Error`` (an older
one, which does not know it) is asked again only every ``REFUSED_S``.

``refused`` counts the replies dropped: malformed, an ``Error``, not a time reply, not the
reply to the request asked (``t1`` not echoed), or not a valid exchange
(``protocol.clock.sample``); none of them ends anything.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import ClassVar

from facewire.protocol.clock import ClockError, OffsetEstimator, Sample, sample
from facewire.protocol.control import Error, TimeReply, TimeRequest
from facewire.protocol.keys import CurveClient
from facewire.receiver.acquire import ControlChannel

BURST = 8
BURST_GAP_S = 0.05
REFRESH_S = 1.0
TIMEOUT_S = 0.5
REFUSED_S = 10.0


class ClockSync:
    """Estimates the offset of the sender's clock at ``endpoint`` (module docstring) until
    ``close``.

    Args:
        endpoint: the sender's control endpoint.
        curve: CURVE client keys, or None.
        clock: this host's clock (``time.monotonic``).

    Attributes:
        refused: replies dropped (module docstring).
        answers: whether the sender answers time requests: None until it has answered one
            or refused one with an ``Error``.
        EMPTY: the summary of no clock sync (before a sender answered).
    """

    EMPTY: ClassVar[dict[str, float | int | None]] = {
        "clock_offset_ms": None, "clock_delay_ms": None, "clock_samples": 0,
        "clock_refused": 0}

    def __init__(self, endpoint: str, curve: CurveClient | None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._endpoint, self._curve, self._clock = endpoint, curve, clock
        self._estimator = OffsetEstimator()
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self.refused = 0
        self.answers: bool | None = None
        self._thread = threading.Thread(target=self._run, name="facewire clock sync",
                                        daemon=True)
        self._thread.start()

    def best(self) -> Sample | None:
        """The current estimate (``offset_s``: the sender's clock minus this host's), or
        None before a valid exchange."""
        with self._lock:
            return self._estimator.best()

    def summary(self) -> dict[str, float | int | None]:
        """``clock_offset_ms``, ``clock_delay_ms`` (the estimate's sample), ``clock_samples``
        (valid exchanges), ``clock_refused``."""
        best = self.best()
        return {"clock_offset_ms": None if best is None else round(best.offset_s * 1000, 3),
                "clock_delay_ms": None if best is None else round(best.delay_s * 1000, 3),
                "clock_samples": self._estimator.samples, "clock_refused": self.refused}

    def close(self) -> None:
        self._closing.set()
        self._thread.join()

    def _run(self) -> None:
        channel = ControlChannel(self._endpoint, self._curve)
        try:
            asked = 0
            while not self._closing.is_set():
                wait = BURST_GAP_S if asked < BURST else REFRESH_S
                if not self._exchange(channel):
                    wait = REFUSED_S
                asked += 1
                self._closing.wait(wait)
        finally:
            channel.close()

    def _exchange(self, channel: ControlChannel) -> bool:
        """One exchange; False when the sender answered with an ``Error`` (an older sender
        that does not know the request)."""
        errors = channel.errors
        t1 = self._clock()
        reply = channel.ask(TimeRequest(t1), (TimeReply, Error), TIMEOUT_S)
        t4 = self._clock()
        if reply is None:
            self.refused += channel.errors > errors
            return True  # no answer, or a bad one: asked again at the usual pace
        if isinstance(reply, Error):
            self.refused += 1
            self.answers = self.answers or False
            return False
        if reply.t1 != t1:
            channel.reject(f"a time reply to t1 = {reply.t1!r}, asked {t1!r}")
            self.refused += 1
            return True
        try:
            s = sample(t1, reply.t2, reply.t3, t4)
        except ClockError as exc:
            channel.reject(str(exc))
            self.refused += 1
            return True
        with self._lock:
            self._estimator.add(s)
        self.answers = True
        return True
