"""The voice's jitter buffer: voice packets in (any order), one 20-ms frame of sound out per pull.

The output device's clock drives it: ``pull`` is called once per 20 ms of sound the device
plays and always returns a frame, so the device never starves and a lost packet costs one
concealed frame, never a gap.

Numbers. Voice frames are numbered by the sender (``protocol.voice``: 16 bits, wrapping); the
buffer extends them to integers relative to the newest frame seen (``protocol.voice.unwrap``).

Depth. The first packet of a stream (or after a reset) starts the buffer *priming*: ``pull``
gives silence until ``target`` frames are buffered after the first, then plays that first
frame and every frame after it in order. ``target`` follows the network's jitter: with
``P = 20 ms`` and ``o_i = a_i - e_i P`` the offsets of the last ``JITTER_PACKETS`` arrivals
(arrival ``a_i``, extended number ``e_i``), ``target = clamp(ceil((max(o) - min(o)) / P) + 1,
MIN_DEPTH, MAX_DEPTH)`` frames: enough that a packet as late as any lately seen still arrives
before its turn. A buffer holding more than ``target + SLACK`` frames (a burst after a stall,
or a sender clock faster than the device's) drops its oldest frame (``dropped``), so the delay
comes back to the target instead of staying high.

What a pull plays, for the frame ``n`` whose turn it is:

- ``n``'s packet is buffered: it is decoded (``played``);
- it is missing and ``n + 1``'s is buffered and carries in-band FEC
  (``protocol.opus.has_fec``): ``n`` is rebuilt from it (``recovered``;
  ``protocol.opus.Decoder.recover``);
- neither: Opus's loss concealment (``concealed``; the case of every lost frame at rates
  under about 17 kbit/s, whose packets carry no FEC); after ``MAX_CONCEALED`` concealed frames
  in a row the stream is taken as stopped, the buffer is reset (decoder state, numbering and
  jitter history) and primes again on the next packet (``resets``), so a sender that pauses
  is followed by silence, not by a concealment that fades forever.

Sync. The player (``receiver.voiceplayer``) keeps the sound with the face, whose latency is
the larger on a receiver that renders: ``stretch()`` makes the next pull a frame of Opus's
concealment without taking a frame (``stretched``), so that every frame after it plays 20 ms
later, and raises ``target`` by one frame (``extra``, at most ``MAX_EXTRA``) so that the depth
won is kept; ``shrink()`` undoes one: it drops the frame whose turn is next (``shrunk``) and
lowers ``extra`` by one. ``target`` is the jitter's depth plus ``extra``.

A packet for a frame already played is ``late``; a second copy of a buffered frame a
``duplicate``; a packet more than ``MAX_AHEAD`` frames ahead of the frame to play (a sender
that restarted at another number) resets the buffer to it. A packet whose Opus bytes do not
decode is ``corrupt``, and its frame is concealed as if lost.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from facewire.protocol.opus import FRAME_S, FRAME_SAMPLES, Decoder, OpusError, has_fec
from facewire.protocol.voice import VoicePacket, unwrap

MIN_DEPTH = 2
MAX_DEPTH = 10
SLACK = 3
JITTER_PACKETS = 50
MAX_CONCEALED = 10
MAX_AHEAD = 250  # 5 s
MAX_EXTRA = 50  # 1 s: the most the sound waits for the face


class JitterBuffer:
    """Voice packets in, 20-ms frames out; see the module docstring."""

    def __init__(self) -> None:
        self._decoder = Decoder()
        self._packets: dict[int, bytes] = {}
        self._offsets: deque[float] = deque(maxlen=JITTER_PACKETS)
        self._newest: int | None = None
        self._next: int | None = None  # the frame to play next; None: priming
        self._first: int | None = None  # the stream's first buffered frame while priming
        self._concealed_run = 0
        self._hold = 0  # pulls to fill with concealment before the next frame (stretch)
        self.extra = 0  # frames of depth beyond the jitter's, for sync
        self.pulled: int | None = None  # the extended number of the last pull's frame
        self.stats = dict.fromkeys(("received", "played", "recovered", "concealed", "silent",
                                    "late", "duplicate", "dropped", "corrupt", "resets",
                                    "stretched", "shrunk"), 0)

    @property
    def target(self) -> int:
        """The depth the buffer primes to and keeps, in frames (module docstring)."""
        if len(self._offsets) < 2:
            return MIN_DEPTH + self.extra
        jitter = max(self._offsets) - min(self._offsets)
        return min(MAX_DEPTH, max(MIN_DEPTH, math.ceil(jitter / FRAME_S) + 1)) + self.extra

    def stretch(self) -> bool:
        """Play the sound one frame later from the next pull on (module docstring, "Sync");
        False when it is at ``MAX_EXTRA`` already."""
        if self.extra >= MAX_EXTRA:
            return False
        self.extra += 1
        if self._next is not None:  # while priming, the deeper target alone waits the frame
            self._hold += 1
        return True

    def shrink(self) -> bool:
        """Play the sound one frame sooner (module docstring, "Sync"); False without a stretch
        to undo."""
        if self.extra == 0:
            return False
        self.extra -= 1
        if self._hold:
            self._hold -= 1
        elif self._next is not None:
            self._packets.pop(self._next, None)
            self._next += 1
            self.stats["shrunk"] += 1
        return True

    @property
    def depth(self) -> int:
        """Frames buffered from the frame to play on."""
        start = self._next if self._next is not None else self._first
        return 0 if start is None else sum(1 for n in self._packets if n >= start)

    @property
    def playing(self) -> int | None:
        """The extended number of the frame the next pull plays; None while priming."""
        return self._next

    def push(self, packet: VoicePacket, arrival: float) -> None:
        """Take one packet that arrived at ``arrival`` (seconds, the receiver's clock)."""
        n = unwrap(packet.seq, self._newest)
        anchor = self._next if self._next is not None else self._first
        if anchor is not None and abs(n - anchor) > MAX_AHEAD:
            self._reset()
            n = packet.seq
        self.stats["received"] += 1
        self._newest = n if self._newest is None else max(self._newest, n)
        self._offsets.append(arrival - n * FRAME_S)
        if self._next is not None and n < self._next:
            self.stats["late"] += 1
            return
        if n in self._packets:
            self.stats["duplicate"] += 1
            return
        self._packets[n] = packet.opus
        if self._next is None and (self._first is None or n < self._first):
            self._first = n

    def pull(self) -> np.ndarray:
        """(FRAME_SAMPLES,) int16: the next 20 ms of sound (module docstring)."""
        self.pulled = None
        if self._next is None:
            if self._first is None or self.depth <= self.target:
                self.stats["silent"] += 1
                return np.zeros(FRAME_SAMPLES, np.int16)
            self._next = self._first
        if self._hold:
            self._hold -= 1
            self.stats["stretched"] += 1
            return self._decoder.conceal()
        while self.depth > self.target + SLACK:
            self._packets.pop(self._next, None)
            self._next += 1
            self.stats["dropped"] += 1
        n, self._next = self._next, self._next + 1
        self.pulled = n
        data = self._packets.pop(n, None)
        following = self._packets.get(n + 1)
        stream_on = data is not None or following is not None
        try:
            if data is not None:
                out = self._decoder.decode(data)
                self.stats["played"] += 1
            elif following is not None and has_fec(following):
                out = self._decoder.recover(following)
                self.stats["recovered"] += 1
            else:
                out = self._conceal(stream_on)
        except OpusError:
            self.stats["corrupt"] += 1
            out = self._conceal(stream_on)
        if stream_on:
            self._concealed_run = 0
        return out

    def _conceal(self, stream_on: bool) -> np.ndarray:
        """A frame of concealment; the ``MAX_CONCEALED``-th in a row with no packet at or
        after it (``stream_on`` False) resets the buffer."""
        self.stats["concealed"] += 1
        out = self._decoder.conceal()
        if not stream_on:
            self._concealed_run += 1
            if self._concealed_run >= MAX_CONCEALED:
                self._reset()
        return out

    def _reset(self) -> None:
        self.stats["resets"] += 1
        self._decoder = Decoder()
        self._packets.clear()
        self._offsets.clear()
        self._next = self._first = self._newest = None
        self._concealed_run = self._hold = 0
