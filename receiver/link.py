"""The link to one sender: its Hello, and the signs that it restarted, resumed or changed.

``receiver.receiver.receive`` and the browser gateway (``receiver.gateway``) both hold one
``SenderLink``: it owns the control channel (``receiver.acquire.ControlChannel``), asks for the
Hello, keeps the Hello taken, and says when to ask again.

State machine
-------------
::

    WAITING --Hello answered--> LINKED --sign--> DUE --asked, answered--> LINKED
       ^                                          |  \\--no answer: asked again every
       |                                          |     RECHECK_EVERY_S (still DUE)
       +---- the caller calls the sender lost ----+

- WAITING: no Hello taken. ``await_hello`` asks, each ask waiting at most
  ``HELLO_TIMEOUT_S``, until a sender answers (the gateway asks on its own schedule, with
  the same timeout).
- LINKED: a Hello taken (``take``). A *sign* makes a recheck due (``due``):

  - packets resume after ``RESUME_GAP_S`` without one (a restart the sequence numbers alone
    may not show; ``note_packet``);
  - a packet's seq is not among the ``FAR_SLOTS`` after the last one's (``note_packet`` with
    the seq: a restarted sender, or one that gave up slots after a stall);
  - the playout resynced (``note_restart``);
  - a packet arrived more than ``protocol.clock.MAX_LAG_S`` after its capture time by the
    Hello's clock, and later than the last packet that made a recheck due by as much again
    (``note_lateness``), at most once every ``RECHECK_EVERY_S``: a sender behind its
    schedule has moved its clock's origin (seqs consecutive, packets flowing, so no other
    sign shows it), and every capture time read with the old origin is early by the move; a
    path whose delay is that long asks once, not at every packet, and a sender far behind
    (a move every few frames) is asked every ``RECHECK_EVERY_S``, not at every move;
  - the Hello taken has no clock (``clock_origin_s``: it was asked before the stream's first
    frame), or announces a voice without its origin (``voice_origin_s``: asked before the
    voice began), and a packet came, from a sender that answers time requests (an older one
    does not, and its Hello never has the clock): asked once per Hello taken.

- DUE: the caller asks at once (``RECHECK_TIMEOUT_S``); unanswered, again from
  ``next_check``, every ``RECHECK_EVERY_S``. Meanwhile the receiver renders on, the gateway
  holds the packets in doubt; when a sender counts as lost is the caller's rule.

Each answer is classified against the Hello taken (``Change``): ``FIRST`` (none taken),
``SAME`` (equal but for ``model_serial``), ``DETAILS`` (same model and rate, another camera or
clock: the next frames use it), ``RATE`` (same model, another rate: a new playout), ``MODEL``
(another model sha256: that model, from the cache or fetched, and a new renderer and
playout). ``new_session``: the same model at a ``model_serial`` below the versions the caller
has fetched, a new session of that model whose updates are fetched anew (a restarted sender
that has already issued more updates than the caller holds is not told apart: the Hello
carries no session identity).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

from facewire.protocol.clock import MAX_LAG_S
from facewire.protocol.control import Hello, HelloRequest
from facewire.protocol.keys import CurveClient
from facewire.protocol.packet import SEQ_MODULO
from facewire.protocol.transport import control_endpoint
from facewire.receiver.acquire import ControlChannel

HELLO_TIMEOUT_S = 1.0
RECHECK_TIMEOUT_S = 0.5
RECHECK_EVERY_S = 2.0
RESUME_GAP_S = 0.5
FAR_SLOTS = 60

Say = Callable[[str], None]


class Change(Enum):
    """How an answered Hello differs from the one taken (module docstring)."""

    FIRST = "first"
    SAME = "same"
    DETAILS = "details"
    RATE = "rate"
    MODEL = "model"


@dataclass(frozen=True)
class Answer:
    """An answered Hello, how it differs from the one taken, and whether it starts a new
    session of the same model."""

    hello: Hello
    change: Change
    new_session: bool


class SenderLink:
    """The link to the sender at ``connect`` (module docstring).

    Args:
        connect: the sender's packet address ``tcp://HOST:PORT`` (control: port + 1).
        curve: CURVE client keys, or None.

    Attributes:
        control: the control channel (also used to fetch the model).
        hello: the Hello taken, or None (WAITING).
        due: a recheck is due (from ``next_check``, monotonic s).
        hellos: Hellos answered.
    """

    def __init__(self, connect: str, curve: CurveClient | None) -> None:
        self.connect = connect
        self.endpoint = control_endpoint(connect)
        self.control = ControlChannel(self.endpoint, curve)
        self.hello: Hello | None = None
        self.due = False
        self.next_check = 0.0
        self.hellos = 0
        self._last_arrival: float | None = None
        self._last_seq: int | None = None
        self._clock_asked = False
        self._lateness_asked = 0.0  # the lateness that last made a recheck due (this origin)
        self._lateness_at = -RECHECK_EVERY_S  # and when (monotonic s)

    def close(self) -> None:
        self.control.close()

    def ask(self, timeout_s: float, fetched: int | None = None) -> Answer | None:
        """Ask for the Hello; the answer classified against the one taken, or None (no
        answer, or a bad one: asked again from ``next_check``). ``fetched``: the newest
        model version the caller holds (for ``new_session``)."""
        got = self.control.ask(HelloRequest(), Hello, timeout_s)
        if got is None:
            self.next_check = time.monotonic() + RECHECK_EVERY_S
            return None
        self.hellos += 1
        self.due = False
        old = self.hello
        if old is None:
            change = Change.FIRST
        elif got.model_sha256 != old.model_sha256:
            change = Change.MODEL
        elif got.rate_hz != old.rate_hz:
            change = Change.RATE
        elif dataclasses.replace(got, model_serial=0) != \
                dataclasses.replace(old, model_serial=0):
            change = Change.DETAILS
        else:
            change = Change.SAME
        new_session = old is not None and change is not Change.MODEL and \
            fetched is not None and got.model_serial < fetched
        return Answer(got, change, new_session)

    def take(self, hello: Hello) -> None:
        """The Hello now played (or served): later answers are classified against it."""
        if _origins(hello) != (_origins(self.hello) if self.hello else None):
            self._clock_asked = False
            self._lateness_asked = 0.0
        self.hello = hello

    def await_hello(self, check_end: Callable[[], None], timeout_s: Callable[[], float],
                    say: Say) -> Answer:
        """Ask until a sender answers, saying that the caller waits, where and for how long.

        Args:
            check_end: called before each ask; raises to stop waiting.
            timeout_s: the longest wait for the next ask, s (at most ``HELLO_TIMEOUT_S``
                is used).
            say: called with one line after each ask.
        """
        since = time.monotonic()
        while True:
            check_end()
            answer = self.ask(min(HELLO_TIMEOUT_S, timeout_s()))
            if answer is not None:
                cam = answer.hello.camera
                say(f"sender at {self.connect}: model {answer.hello.model_sha256[:12]}, "
                    f"{answer.hello.rate_hz:g} Hz, camera {cam.width}x{cam.height}, "
                    f"{len(answer.hello.regions)} regions")
                return answer
            why = f"; last reply: {self.control.last_error}" if self.control.last_error \
                else ""
            say(f"waiting for a sender at {self.connect} (control {self.endpoint}): no "
                f"answer for {time.monotonic() - since:.0f} s{why}")

    def note_packet(self, arrival: float, seq: int | None = None,
                    clocked: bool = True) -> bool:
        """A packet arrived at ``arrival`` (monotonic s), with its wire ``seq`` if the caller
        decoded it; ``clocked``: the sender may announce a clock (it has not refused a time
        request). A sign (module docstring) makes the recheck due. True when the sign is
        that the stream resumed or jumped (perhaps a restarted sender)."""
        resumed = self._last_arrival is not None and arrival - self._last_arrival > RESUME_GAP_S
        jumped = seq is not None and self._last_seq is not None and \
            not 0 < (seq - self._last_seq) % SEQ_MODULO <= FAR_SLOTS
        self._last_arrival = arrival
        if seq is not None:
            self._last_seq = seq
        clockless = clocked and self.hello is not None and not self._clock_asked and (
            self.hello.clock_origin_s is None or
            self.hello.voice_bitrate is not None and self.hello.voice_origin_s is None)
        if clockless:
            self._clock_asked = True
        if resumed or jumped:
            self._clock_asked = False
        if resumed or jumped or clockless:
            self.due, self.next_check = True, 0.0
        return resumed or jumped

    def note_lateness(self, lateness_s: float, now: float) -> bool:
        """A packet arrived ``lateness_s`` after its capture time (this host's clock, by the
        Hello taken), noted at ``now`` (monotonic s); True when that makes a recheck due
        (module docstring)."""
        if not (lateness_s > self._lateness_asked + MAX_LAG_S and
                now >= self._lateness_at + RECHECK_EVERY_S):
            return False
        self._lateness_asked, self._lateness_at = lateness_s, now
        self.due, self.next_check = True, 0.0
        return True

    def note_restart(self) -> None:
        """The playout resynced: a new stream, perhaps of a restarted sender."""
        self.due, self.next_check = True, 0.0
        self._clock_asked = False

    def check_due(self, now: float) -> bool:
        """Whether to ask for the Hello now."""
        return self.due and now >= self.next_check


def _origins(hello: Hello) -> tuple[float | None, float | None]:
    """The face's and the voice's clock origins a Hello announces."""
    return hello.clock_origin_s, hello.voice_origin_s
