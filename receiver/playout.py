"""The playout buffer of the receive loop: packets in (any order, any bytes), one state per slot.

Slots and the render clock
--------------------------
The sender numbers its packets 0, 1, 2, ... (16 bits, wrapping at 65536), one per frame at
``rate_hz``. Each sequence number is a *slot*. The receiver calls ``Playout.pop`` once per
output frame, on its own clock at ``rate_hz``; every call after playback has started plays the
next slot in sequence order, whether its packet arrived or not, so the receiver never waits
for the network (it never stalls) and a lost packet costs exactly one concealed slot.

Sequence numbers (serial-number arithmetic, RFC 1982)
-----------------------------------------------------
A 16-bit ``seq`` is read relative to a reference ``r`` (the playout point once playing, the
stream's first packet before) as the signed distance ``d = ((seq - r) + 32768) mod 65536 -
32768`` in [-32768, 32767], and extended to the integer ``r + d``. Inside one stream, extended
numbers never wrap: 65535 is followed by 65536 (wire 0), which plays with no gap.

Depth and latency
-----------------
The first packet of a stream starts a countdown of ``depth`` pops (``DEFAULT_DEPTH`` = 3) that
return the previous state without a slot (``seq`` None); the next pop plays the smallest
buffered slot, and each pop after it the slot after. A packet that arrives on time is thus
played ``depth`` pops after it arrived: the buffer adds ``depth / rate_hz`` of latency (100 ms
at 30 Hz; ``Playout.latency_s``), plus the wait for the next pop (under one slot period), and
a packet may arrive up to ``depth`` slot periods behind its nominal time (network jitter,
reordering) and still be played.

What happens to a valid packet (``stats`` keys in brackets)
-----------------------------------------------------------
Every packet that decodes (``protocol.packet.decode``: size, version, CRC, reserved bits)
counts as [received]; anything else (any length, any content, not even bytes) is [corrupt]
and dropped. With ``W = max(4 depth, ceil(JUMP_S rate_hz))`` slots (60 at 30 Hz, depth 3):

- a second packet for a buffered slot, or a byte-identical copy of a packet already played
  or late: [duplicate], dropped (the first copy wins). A *different* packet for a slot already
  played is not a network duplicate: it is treated as late (below), as a sender that
  restarted a few frames back sends;
- ``d < -W`` or ``d >= W`` (far from the playout point): held as a restart candidate, see
  below; a candidate that the next valid packet does not confirm is [stray], dropped;
- behind the playout point (its slot was already concealed): [late], dropped;
- otherwise buffered until its slot plays.

Restart and resync (``stats["restarts"]``)
------------------------------------------
A resync clears the buffer (its packets count as [discarded]) and starts a new stream
(countdown of ``depth`` pops, during which the last state keeps being held or eased) from the
packets that triggered it. Two rules:

1. Jump (RFC 3550, appendix A.1): a far packet followed by its successor (``seq + 1``) is a new
   stream, e.g. a sender that restarts at 0 after thousands of frames, or at a random number.
   One far packet alone (a stray or a replayed old packet) moves nothing.
2. Fallen behind: a run of consecutive late packets (no on-time packet in between) that spans
   more than ``depth`` slot periods of arrival time, or holds ``W`` packets, means the stream
   now lives behind the playout point for good (a sender that restarted a few frames back, a
   sender that stalled, a sender clock slower than ours); the buffer resyncs on the packet
   that completes the run. Stragglers delivered in a burst after a network stall arrive at
   about the same time and do not trigger it.

Playing on arrival (the live receiver)
--------------------------------------
A live receiver need not wait for a clock: ``ready`` says that the next pop plays a packet
already buffered (or runs the countdown of a stream whose packets are buffered), so the
receiver pops at once and the slot is rendered as soon as its packet is in; the countdown then
costs nothing. Only a missing slot waits, until ``due()``: the latest time its packet is
expected, after which it is concealed and the slots behind it play. With ``n`` the slot's
extended number, ``P = 1 / rate_hz`` and ``o_i = a_i - e_i P`` the offset of each of the last
``JITTER_PACKETS`` packets of the stream (arrival ``a_i``, extended number ``e_i``; late ones
included, duplicates not), and ``o'`` the last ``BASE_PACKETS`` of them::

    due(n) = min(o') + n P + margin,   margin = min(P + max(o) - min(o) + GUARD_S, depth P)

and ``margin = depth P`` until the stream has ``MIN_JITTER_PACKETS`` arrivals (its first
second tells little of its jitter: a sender warming up sends unevenly, and one stall of a busy
machine can exceed the spread of the few packets before it).

``min(o')`` is the fastest transit of the last ``BASE_PACKETS`` packets, so a sender that
runs slower than its rate is followed: its packets come later by a share of a period each (at
24 fps for 30 Hz, 8 ms a packet), so ``min(o')`` trails by at most ``BASE_PACKETS - 1`` such
shares (58 ms), within the margin, where the minimum over all ``JITTER_PACKETS`` would trail by
half a second and conceal every slot. ``max(o) - min(o)`` is the jitter (reordering and drift
included) of the longer window. The margin is one slot period more than the jitter, so a
packet overtaken by its successor (which itself may come as late as the jitter) is not given
up before it arrives, and at most the depth, as on the tick clock. A lost packet thus delays
the slots behind it by about one period and the jitter (and at most the base's trail more),
and a packet on time is never delayed.

Skip (``stats["skipped"]``; only with ``skip``, the default): when the newest buffered
packet is ``2 depth`` or more slots ahead of the playout point ``n``, the latency has grown
by ``depth`` slots or more; the playout point moves forward so that the newest is ``depth``
slots ahead again (``target = newest - depth``), giving up missing slots before received
ones:

- slot ``n`` missing (a forward jump in ``seq``: the sender skipped numbers): jump over the
  missing run, to ``min(target, first buffered slot)``;
- every slot in ``[n, target)`` buffered (a sender clock faster than ours): jump to
  ``target``; the packets jumped over count as [discarded];
- otherwise play ``n`` as usual; the missing slots ahead are jumped over when reached.

Skipped slots get no state (they are neither played nor [concealed]).

Concealment
-----------
The pose (rotation, translation) is never eased: it is the pose of the last packet played
(the protocol's default frontal pose, 600 mm away, before any). Easing it toward the default
would fly the head across the picture; a still head is the better guess. The expression
(residuals, Q) is ``weight * E``, where ``E`` is the expression of the last played packet with
the face present (``Flag.FACE_PRESENT`` set, ``Flag.TRACKING_LOST`` clear), and ``weight``:

- 1 on a slot whose packet has the face present ("received");
- on a missing slot, held at its value for ``hold_s`` (``HOLD_S`` = 0.2 s, counted from the last
  face-present slot; "held"), then eased to 0 over ``ease_s`` (``EASE_S`` = 0.5 s; "easing",
  then "neutral"). A pop without a slot (countdown after a resync) advances the clock too;
- on a played packet with the face lost, eased to 0 over ``ease_s`` starting at once, no
  hold ("face_lost"); its pose is used, its residuals and Q are not.

The model version (``serial``) and the light (``shade``) are those of that same last
face-present packet, never eased (0 and zeros before any): the Q values played refer to
the model version they were classified against, and the light does not go out when the
tracker loses the face.

Once easing has started, only a face-present packet stops it. The curve is smoothstep:
``weight = 1 - (3 p^2 - 2 p^3)``, ``p = (t - t_begin) / ease_s`` clipped to [0, 1]: it leaves 1
and reaches 0 with zero slope and never increases; ``weight`` falls by at most
``1.5 / (ease_s rate_hz)`` per slot. Neutral is zero residuals (the model's own shape) and
each region's rest value (``rest_q``: the Q of the model's neutral face, ``Region.rest``; 0
when not given); in between, Q = rest + weight (E_q - rest).

Replay
------
``replay_states`` feeds a recorded log (packets and their times) through a ``Playout`` on a
render clock ticking at ``times.min() + k / rate_hz``: before the pop of tick ``k``, every packet
whose time is at most the tick is pushed (in time order, log order among equal times). It
yields the states that have a slot, and stops once every packet has been pushed and every
buffered slot played; for a log whose times follow its sequence numbers, that is one state
per slot from the first sequence number to the last, concealed where packets are missing.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from facewire.models.geometry import rotation_matrix
from facewire.protocol.packet import (
    N_REGIONS,
    N_RESIDUAL_POINTS,
    N_SHADE,
    PACKET_BYTES,
    SEQ_MODULO,
    Flag,
    Frame,
    PacketError,
    decode,
)
from facewire.protocol.rate import MAX_RATE_HZ, MIN_RATE_HZ

DEFAULT_DEPTH = 3
HOLD_S = 0.2
EASE_S = 0.5
JUMP_S = 2.0
JITTER_PACKETS = 64
MIN_JITTER_PACKETS = 30  # a second at 30 Hz
GUARD_S = 0.005
BASE_PACKETS = 8  # the deadline's base: the last quarter second at 30 Hz
MAX_DEPTH = 1024
MAX_REPLAY_SLOTS = 1 << 24  # about 6 days at 30 Hz
STATUSES = ("received", "held", "easing", "neutral", "face_lost")
_HALF = SEQ_MODULO // 2
_EPS = 1e-9


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


_ZERO_SHADE = _frozen(np.zeros(N_SHADE, np.float32))


@dataclass(frozen=True, eq=False)
class FrameState:
    """What to render for one output frame.

    Attributes:
        seq: the slot's wire sequence number (0..65535), or None for a pop that plays no slot
            (before the first packet, and the countdown at the start of a stream).
        rotation: (3, 3) float64 rotation, model -> camera (``models.geometry.Pose`` convention).
        translation: (3,) float64 model origin in the camera frame, mm.
        residuals: (9, 2) float32 tangent-frame residuals, mm, NONRIGID order (turn them into
            model space with ``models.rig.Rig.from_tangent``).
        q: (8,) float32 region values, layers.
        flags: the played packet's ``Flag`` bits; ``Flag(0)`` when no packet was played.
        status: one of ``STATUSES`` (module docstring).
        weight: the fraction of the last face-present expression kept, 1 .. 0.
        arrival_s: the played packet's arrival time (the ``push`` argument), else None.
        serial: the model version ``q`` refers to (``protocol.packet``; 0: the model file).
        shade: (3,) float32 the light's log-gain field (``protocol.packet``), zeros: the
            model's own light.

    The arrays are read-only.
    """

    seq: int | None
    rotation: np.ndarray
    translation: np.ndarray
    residuals: np.ndarray
    q: np.ndarray
    flags: Flag
    status: str
    weight: float
    arrival_s: float | None = None
    serial: int = 0
    shade: np.ndarray = field(default_factory=lambda: _ZERO_SHADE)


@dataclass(frozen=True, eq=False)
class _Packet:
    """A decoded packet, ready to play."""

    seq: int  # wire sequence number
    flags: Flag
    rotation: np.ndarray  # (3, 3) float64
    translation: np.ndarray  # (3,) float64
    residuals: np.ndarray  # (9, 2) float32
    q: np.ndarray  # (8,) float32
    arrival_s: float
    serial: int
    shade: np.ndarray  # (3,) float32

    @property
    def face(self) -> bool:
        return bool(self.flags & Flag.FACE_PRESENT) and not self.flags & Flag.TRACKING_LOST


def serial_distance(seq: int, ref: int) -> int:
    """Signed distance from ``ref`` to ``seq`` on the 16-bit circle, in [-32768, 32767]."""
    return (seq - ref + _HALF) % SEQ_MODULO - _HALF


_ZERO_RESIDUALS = _frozen(np.zeros((N_RESIDUAL_POINTS, 2), np.float32))
_DEFAULT = Frame()
_DEFAULT_ROTATION = _frozen(rotation_matrix(_DEFAULT.rotation))
_DEFAULT_TRANSLATION = _frozen(_DEFAULT.translation.astype(np.float64))


class Playout:
    """The playout buffer and loss concealment of one receiver (module docstring).

    Args:
        rate_hz: the stream's frame rate (the Hello's), which is also the pop rate; (0, 1000].
        depth: the buffer depth in slots, 1 .. 1024; latency added ``depth / rate_hz``.
        hold_s: how long a lost slot's expression is held before easing, s, >= 0.
        ease_s: how long the ease to neutral takes, s, >= 0 (0 snaps to neutral).
        rest_q: (8,) the Q of each slot on the neutral face (the model's ``Region.rest`` in
            packet order, 0 beyond its regions); zeros when None.
        skip: apply the skip rule (module docstring); without it every slot is played, however
            far behind (a receiver writing a file rather than showing a live picture).

    Raises:
        ValueError: an argument out of range (naming it).

    Not thread-safe: call ``push`` and ``pop`` from one thread, or under one lock.
    """

    def __init__(self, rate_hz: float, depth: int = DEFAULT_DEPTH, hold_s: float = HOLD_S,
                 ease_s: float = EASE_S, rest_q: np.ndarray | None = None,
                 skip: bool = True) -> None:
        # numbers.Real, spelled so that mypy follows it (it takes float and Real as disjoint)
        if not (isinstance(rate_hz, (int, float, np.integer, np.floating))
                and MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ):
            raise ValueError(f"rate_hz: expected a number in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}], "
                             f"got {rate_hz!r}")
        if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) \
                or not 1 <= depth <= MAX_DEPTH:
            raise ValueError(f"depth: expected an integer in [1, {MAX_DEPTH}], got {depth!r}")
        for name, value in (("hold_s", hold_s), ("ease_s", ease_s)):
            if not (isinstance(value, (int, float, np.integer, np.floating))
                    and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {value!r}")
        self.rate_hz = float(rate_hz)
        self.depth = int(depth)
        self.hold_s = float(hold_s)
        self.ease_s = float(ease_s)
        self.skip = bool(skip)
        self.window = max(4 * self.depth, math.ceil(JUMP_S * self.rate_hz))
        rest = np.zeros(N_REGIONS, np.float32) if rest_q is None else \
            np.asarray(rest_q, np.float32)
        if rest.shape != (N_REGIONS,) or not np.isfinite(rest).all():
            raise ValueError(f"rest_q: expected {N_REGIONS} finite values, got {rest_q!r}")
        self._rest_q = _frozen(rest.copy())
        self._counts = dict.fromkeys(("received", "corrupt", "duplicate", "late", "stray",
                                      "discarded", "concealed", "skipped", "restarts"), 0)
        # stream
        self._started = False
        self._playing = False
        self._countdown = 0
        self._ref = 0  # extended seq: the first packet's, then the playout point (_next)
        self._next = 0
        self._newest = 0
        self._buffer: dict[int, _Packet] = {}
        self._seen: dict[int, bytes] = {}  # extended seq -> the packet's bytes
        self._candidate: tuple[_Packet, bytes] | None = None
        self._late_run = 0
        self._late_start = 0.0
        self._offsets: deque[float] = deque(maxlen=JITTER_PACKETS)  # a_i - e_i / rate_hz
        # output
        self._rotation = _DEFAULT_ROTATION
        self._translation = _DEFAULT_TRANSLATION
        self._residuals = _ZERO_RESIDUALS  # E, the last face-present expression
        self._q = self._rest_q
        self._serial, self._shade = 0, _ZERO_SHADE  # E's model version and light
        self._weight = 0.0
        self._easing = True
        self._since = 0  # slots since the last face-present slot
        self._ease_begin = 0.0  # the value of _since at which the ease began, slots

    @property
    def rest_q(self) -> np.ndarray:
        """(8,) float32, read-only: the Q of each slot on the neutral face (``__init__``)."""
        return self._rest_q

    @rest_q.setter
    def rest_q(self, value: np.ndarray) -> None:
        """Another model version's rest Q (``models.update`` moves a region's rest state when
        it inserts before it); a face lost from now on eases to it."""
        rest = np.asarray(value, np.float32)
        if rest.shape != (N_REGIONS,) or not np.isfinite(rest).all():
            raise ValueError(f"rest_q: expected {N_REGIONS} finite values, got {value!r}")
        self._rest_q = _frozen(rest.copy())

    @property
    def latency_s(self) -> float:
        """The latency the buffer adds to an on-time packet on a tick clock
        (``replay_states``), s: ``depth / rate_hz``; a live receiver playing on arrival
        adds none, and waits at most this long for a missing packet (``margin_s``)."""
        return self.depth / self.rate_hz

    @property
    def stats(self) -> dict[str, int]:
        """Counts so far: received, corrupt, duplicate, late, stray, discarded (packets);
        concealed (slots played without their packet), skipped (slots jumped over); restarts."""
        return dict(self._counts)

    @property
    def ready(self) -> bool:
        """True when the next pop plays a buffered packet, or counts down towards one: a live
        receiver pops at once (module docstring, "Playing on arrival")."""
        return bool(self._buffer) and (not self._playing or self._next in self._buffer)

    @property
    def ahead(self) -> int:
        """Slots from the playout point (the first buffered, before playing) to the newest
        buffered packet, both counted; 0 when nothing is buffered."""
        if not self._buffer:
            return 0
        return self._newest - (self._next if self._playing else min(self._buffer)) + 1

    @property
    def margin_s(self) -> float:
        """How long after its earliest expected arrival a missing slot waits, s (module
        docstring, "Playing on arrival")."""
        period = 1.0 / self.rate_hz
        if len(self._offsets) < MIN_JITTER_PACKETS:
            return self.depth * period
        spread = max(self._offsets) - min(self._offsets)
        return min(period + spread + GUARD_S, self.depth * period)

    def due(self) -> float | None:
        """The time, on the arrival clock, after which the next slot is concealed if its
        packet has not come: ``min(o') + n / rate_hz + margin_s``; None when nothing plays
        yet (before the first packet, or while ``ready`` counts down)."""
        if not self._playing or not self._offsets:
            return None
        base = min(itertools.islice(reversed(self._offsets), BASE_PACKETS))  # min(o')
        return base + self._next / self.rate_hz + self.margin_s

    @property
    def drained(self) -> bool:
        """True when no buffered packet waits to be played (nothing started, or all played)."""
        return not self._buffer and (self._playing or not self._started)

    def push(self, data: bytes, arrival_s: float) -> None:
        """Take one packet as it arrives; never raises on its content.

        Args:
            data: the packet, any bytes (a non-bytes object counts as corrupt).
            arrival_s: its arrival time, s, on one monotonic clock (used by the fallen-behind
                rule and passed through to ``FrameState.arrival_s``).

        Raises:
            ValueError: ``arrival_s`` is not a finite number.
        """
        if not (isinstance(arrival_s, (int, float, np.integer, np.floating))
                and math.isfinite(arrival_s)):
            raise ValueError(f"arrival_s: expected a finite number, got {arrival_s!r}")
        packet, raw = self._decode(data, float(arrival_s))
        if packet is None:
            self._counts["corrupt"] += 1
            return
        self._counts["received"] += 1
        if not self._started:
            self._restart([(packet, raw)], count=False)
            return
        d = serial_distance(packet.seq, self._ref % SEQ_MODULO)
        if d < -self.window or d >= self.window:
            self._far(packet, raw)
            return
        if self._candidate is not None:
            self._counts["stray"] += 1
            self._candidate = None
        ext = self._ref + d
        behind = self._playing and ext < self._next
        if ext in self._seen and (not behind or self._seen[ext] == raw):
            self._counts["duplicate"] += 1
            return
        self._seen[ext] = raw
        self._offsets.append(packet.arrival_s - ext / self.rate_hz)
        if behind:
            self._late(packet, raw)
            return
        self._buffer[ext] = packet
        self._newest = max(self._newest, ext)
        self._late_run = 0

    def pop(self) -> FrameState:
        """The state of the next output frame (call once per frame at ``rate_hz``)."""
        if not self._started:
            return self._state(None, "neutral", Flag(0), None)
        if not self._playing:
            if self._countdown > 0:
                self._countdown -= 1
                return self._conceal(None)
            self._playing = True
            self._next = min(self._buffer)
            self._ref = self._next
        if self.skip and self._buffer and self._newest - self._next >= 2 * self.depth:
            self._catch_up()
        slot = self._next
        self._next += 1
        self._ref = self._next
        self._prune()
        packet = self._buffer.pop(slot, None)
        if packet is None:
            self._counts["concealed"] += 1
            return self._conceal(slot % SEQ_MODULO)
        self._rotation, self._translation = packet.rotation, packet.translation
        if packet.face:
            self._residuals, self._q = packet.residuals, packet.q
            self._serial, self._shade = packet.serial, packet.shade
            self._weight, self._easing, self._since = 1.0, False, 0
            return self._state(packet.seq, "received", packet.flags, packet.arrival_s)
        self._advance(face_lost=True)
        return self._state(packet.seq, "face_lost", packet.flags, packet.arrival_s)

    # -- packets ---------------------------------------------------------------------------

    @staticmethod
    def _decode(data: object, arrival_s: float) -> tuple[_Packet | None, bytes]:
        """The decoded packet and its bytes; (None, b"") when it is not a valid packet."""
        if not isinstance(data, (bytes, bytearray, memoryview)):
            return None, b""
        try:
            raw = bytes(data)  # a copy: the caller may reuse its buffer
        except ValueError:  # a released memoryview
            return None, b""
        if len(raw) != PACKET_BYTES:
            return None, b""
        try:
            frame = decode(raw)
        except PacketError:
            return None, b""
        packet = _Packet(frame.seq, Flag(frame.flags), _frozen(rotation_matrix(frame.rotation)),
                         _frozen(frame.translation.astype(np.float64)),
                         _frozen(frame.residuals.astype(np.float32)),
                         _frozen(frame.q.astype(np.float32)), arrival_s, frame.serial,
                         _frozen(frame.shade.astype(np.float32)))
        return packet, raw

    def _far(self, packet: _Packet, raw: bytes) -> None:
        """Rule 1: a far packet is a candidate; its successor confirms a new stream."""
        cand = self._candidate
        if cand is not None and packet.seq == (cand[0].seq + 1) % SEQ_MODULO:
            self._restart([cand, (packet, raw)], count=True)
            return
        if cand is not None and raw == cand[1]:
            self._counts["duplicate"] += 1
            return
        if cand is not None:
            self._counts["stray"] += 1
        self._candidate = (packet, raw)

    def _late(self, packet: _Packet, raw: bytes) -> None:
        """A packet behind the playout point: dropped, unless it completes rule 2's run."""
        if self._late_run == 0:
            self._late_start = packet.arrival_s
        self._late_run += 1
        span = packet.arrival_s - self._late_start
        if (self._late_run >= 2 and span > self.depth / self.rate_hz + _EPS) \
                or self._late_run >= self.window:
            self._restart([(packet, raw)], count=True)
            return
        self._counts["late"] += 1

    def _restart(self, packets: list[tuple[_Packet, bytes]], count: bool) -> None:
        """Start a new stream from these packets and their bytes (in sequence order)."""
        self._counts["discarded"] += len(self._buffer)
        self._counts["restarts"] += count
        self._buffer.clear()
        self._seen.clear()
        self._candidate = None
        self._late_run = 0
        self._started, self._playing, self._countdown = True, False, self.depth
        self._ref = packets[0][0].seq
        self._offsets.clear()
        for packet, raw in packets:
            ext = self._ref + serial_distance(packet.seq, self._ref % SEQ_MODULO)
            self._buffer[ext] = packet
            self._seen[ext] = raw
            self._offsets.append(packet.arrival_s - ext / self.rate_hz)
        self._newest = max(self._buffer)

    def _catch_up(self) -> None:
        """The skip rule (module docstring): give up slots when the latency has grown."""
        target = self._newest - self.depth
        if self._next not in self._buffer:
            self._skip(min(target, min(self._buffer)))
        elif sum(self._next <= e < target for e in self._buffer) == target - self._next:
            self._skip(target)

    def _skip(self, target: int) -> None:
        """Move the playout point forward to ``target``, dropping the slots before it."""
        self._counts["skipped"] += target - self._next
        for ext in [e for e in self._buffer if e < target]:
            del self._buffer[ext]
            self._counts["discarded"] += 1
        self._next = target

    def _prune(self) -> None:
        """Forget the seen slots farther behind than the window (rule 1 covers those)."""
        if len(self._seen) > 4 * self.window:
            floor = self._next - self.window
            self._seen = {e: raw for e, raw in self._seen.items() if e >= floor}

    # -- concealment -----------------------------------------------------------------------

    def _advance(self, face_lost: bool) -> None:
        """One slot without a face-present packet: hold, or ease the weight toward 0."""
        self._since += 1
        if not self._easing:
            if face_lost:
                self._easing, self._ease_begin = True, self._since - 1.0
            elif self._since > self.hold_s * self.rate_hz + _EPS:
                self._easing, self._ease_begin = True, self.hold_s * self.rate_hz
        if self._easing:
            span = self.ease_s * self.rate_hz
            p = 1.0 if span <= 0 else min(max((self._since - self._ease_begin) / span, 0.0), 1.0)
            self._weight = min(self._weight, 1.0 - p * p * (3.0 - 2.0 * p))

    def _conceal(self, seq: int | None) -> FrameState:
        self._advance(face_lost=False)
        status = "held" if not self._easing else "easing" if self._weight > 0 else "neutral"
        return self._state(seq, status, Flag(0), None)

    def _state(self, seq: int | None, status: str, flags: Flag,
               arrival_s: float | None) -> FrameState:
        w = self._weight
        if w >= 1.0:
            residuals, q = self._residuals, self._q
        elif w <= 0.0:
            residuals, q = _ZERO_RESIDUALS, self._rest_q
        else:
            residuals = _frozen(self._residuals * np.float32(w))
            q = _frozen(self._rest_q + (self._q - self._rest_q) * np.float32(w))
        return FrameState(seq, self._rotation, self._translation, residuals, q, flags, status,
                          w, arrival_s, self._serial, self._shade)


def replay_states(packets: Sequence[bytes] | np.ndarray, times: Sequence[float] | np.ndarray,
                  rate_hz: float, *, playout: Playout | None = None) -> Iterator[FrameState]:
    """Play a recorded log as if its packets arrived at their recorded times (module docstring).

    Args:
        packets: N packets (bytes, or an (N, 43) uint8 array such as ``PacketLog.packets``);
            corrupt ones are counted and skipped like live ones.
        times: (N,) finite arrival times, s (``PacketLog.times``).
        rate_hz: the stream's rate (the Hello's).
        playout: the ``Playout`` to feed, to read its ``stats`` afterwards; a fresh one with
            the default depth, hold and ease when None. Its rate must be ``rate_hz``.

    Yields:
        one ``FrameState`` per played slot, in playout order.

    Raises:
        ValueError: ``times`` of the wrong length or not finite, a time span longer than
            ``MAX_REPLAY_SLOTS`` slots, or a ``playout`` of another rate.
    """
    if playout is None:
        playout = Playout(rate_hz)
    elif playout.rate_hz != float(rate_hz):
        raise ValueError(f"playout: its rate {playout.rate_hz} Hz is not rate_hz {rate_hz}")
    t = np.asarray(times, np.float64)
    if t.shape != (len(packets),):
        raise ValueError(f"times: expected ({len(packets)},) for {len(packets)} packets, "
                         f"got shape {t.shape}")
    if not np.isfinite(t).all():
        raise ValueError("times: every arrival time must be finite")
    if len(t) and (t.max() - t.min()) * playout.rate_hz > MAX_REPLAY_SLOTS:
        raise ValueError(f"times: span {t.max() - t.min():.6g} s is more than "
                         f"{MAX_REPLAY_SLOTS} slots at {playout.rate_hz} Hz")
    return _replay(packets, t, playout)


def _replay(packets: Sequence[bytes] | np.ndarray, t: np.ndarray,
            playout: Playout) -> Iterator[FrameState]:
    order = np.argsort(t, kind="stable")
    start = float(t[order[0]]) if len(t) else 0.0
    i, tick = 0, 0
    while True:
        now = start + tick / playout.rate_hz
        while i < len(order) and t[order[i]] <= now + _EPS:
            data = packets[order[i]]
            if isinstance(data, np.ndarray) and data.dtype == np.uint8:
                data = data.tobytes()
            playout.push(data, float(t[order[i]]))
            i += 1
        state = playout.pop()
        if state.seq is not None:
            yield state
        tick += 1
        if i == len(order) and playout.drained:
            return
