"""The receiver's voice: voice packets in from the packet thread, sound out, kept beside the face.

Packets. The packet socket's thread hands every message to ``push`` first
(``receiver.packetreader``'s ``divert``): a voice packet (``protocol.voice``: its first
nibble) is taken here and never queued behind the face's packets; one that does not decode
is dropped and counted by its reason (``corrupt``), never played. The rest go to the face.

Playing. A jitter buffer (``receiver.jitterbuffer``) is pulled once per 20 ms by the output
device (``receiver.speaker.Speaker``, PortAudio's clock) or, without one, by a clock of our
own (``SoundClock``): with ``--no-audio`` on the receiver there is no player at all; with a
speaker asked for (``speaker``, or the default output) that cannot be opened, one line says
so (for the default output, whose absence on a server is the rule, nothing is said) and
the clock plays into the file alone. Each pulled frame goes to ``on_sound`` (for the
video file's sound track) with the time it went out.

Sync (``av_skew_ms``): both streams' capture times are on the sender's clock (the Hello's
``clock_origin_s`` and ``voice_origin_s``; ``protocol.clock``), and the receiver moves them
to its own with one offset estimate. For each voice frame played, its latency (out time minus
capture) less the latency of the last face frame out (``face``: the receiver reports each
frame it shows; none when it was out more than ``FACE_STALE_S`` before) is the skew: what
the viewer meets at that moment, positive when the sound comes later after its capture than
the face does after its own. The offset cancels in that difference, so only the two
streams' own delays count. Over the session: ``av_skew_ms_median``, ``av_skew_ms_p95`` (the
95th percentile: how far behind the sound is at worst but 5 %) and ``av_skew_ms_p5`` (the
5th: how far ahead, when negative); ITU-R BT.1359 finds sound noticed from 45 ms ahead of
the picture or 125 ms behind it.

Keeping them together. A receiver that renders shows the face later after its capture than
it plays the sound (tracking, rendering and the face's playout against a jitter buffer of a
few frames), so the player holds the sound back to the face's latency: after each frame
played whose skew is known, with ``face_latency`` the median latency of the last
``FACE_FRAMES`` face frames out, a sound ahead of the face by more than ``AHEAD_S`` is
stretched by one frame (``receiver.jitterbuffer``'s ``stretch``), and one behind by more than
``BEHIND_S`` shrunk by one (``shrink``, only a stretch is undone: the voice's own path is never
cut), at most one change per ``ADJUST_EVERY`` frames, so the sound walks to the face at 20 ms
per 60 ms played rather than jumping; but the first time the skew is known (the stream's
first frames, whose sound would otherwise lead the face while it walks) the whole wait is
taken at once. The window kept, -``AHEAD_S`` to ``BEHIND_S``, sits
inside BT.1359's -45 to +125 ms. The buffer waits at most ``jitterbuffer.MAX_EXTRA`` frames
(1 s) for the face: a face later than that leaves the sound ahead. ``voice_extra_ms`` in the
summary is the wait at the end.

Thread safety: ``push`` runs on the packet thread, the pull on the device's or the clock's,
``face`` and ``summary`` on the render loop's; one lock guards the buffer and the records.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from facewire.protocol.clock import capture_s
from facewire.protocol.opus import FRAME_S
from facewire.protocol.voice import VoiceError, decode, is_voice
from facewire.receiver.jitterbuffer import JitterBuffer
from facewire.receiver.speaker import SoundClock, Speaker, SpeakerError

VOICE_RATE_HZ = 1.0 / FRAME_S  # voice frames are slots of 50 Hz on the sender's clock
FACE_STALE_S = 0.5  # a face frame older than this is no reference for the skew
SKEWS_KEPT = 30_000  # 10 minutes of voice frames
FACE_FRAMES = 25  # the face latency followed: the median of the last second's frames
AHEAD_S = 0.02  # sound ahead of the face by more: stretched
BEHIND_S = 0.06  # sound behind the face by more: a stretch undone
ADJUST_EVERY = 3  # frames played between two changes

OnSound = Callable[[np.ndarray, float], None]
ToLocal = Callable[[int, float], float | None]


class VoicePlayer:
    """See the module docstring.

    Args:
        speaker: the output device's index or name, "" for the default output, None for no
            device (the sound only handed on).
        on_sound: called with each pulled frame ((FRAME_SAMPLES,) int16) and its out time
            (``time.monotonic()``), on the player's thread.
        say: one line of text (a named speaker that cannot be opened).
        to_local: the capture time of voice frame ``seq`` (wire number) on this host's clock,
            given a time near it on this host's clock; None while the Hello's voice origin or
            the clock offset is unknown.
    """

    def __init__(self, speaker: str | None, on_sound: OnSound | None,
                 say: Callable[[str], None], to_local: ToLocal) -> None:
        self._buffer = JitterBuffer()
        self._lock = threading.Lock()
        self._on_sound, self._to_local = on_sound, to_local
        self._face: tuple[float, float] | None = None  # the last face frame's (capture, out)
        self._face_latencies: deque[float] = deque(maxlen=FACE_FRAMES)
        self._since_change = 0  # frames heard since the last stretch or shrink
        self._joined = False  # the sound has been brought to the face once
        self.skews: deque[float] = deque(maxlen=SKEWS_KEPT)
        self.latencies: deque[float] = deque(maxlen=SKEWS_KEPT)  # capture to out, s
        self.own: deque[float] = deque(maxlen=SKEWS_KEPT)  # the same less the wait for the face
        self.corrupt: dict[str, int] = {}
        self.bytes = 0
        self.first: float | None = None  # the first arrival
        self.last: float | None = None
        self.device = "none"
        self._pulled: int | None = None  # the frame of the last pull (player's thread)
        self._sounding = False  # the last pull was the stream's sound, not priming's silence
        self._output: Speaker | SoundClock
        if speaker is not None:
            try:
                self._output = Speaker(self._pull, speaker or None, self._heard)
                self.device = speaker or "default"
            except SpeakerError as error:
                if speaker:  # a device the user named; the default's absence goes unsaid
                    say(f"{error}; the voice goes into the file only")
                self._output = SoundClock(self._pull, self._heard)
        else:
            self._output = SoundClock(self._pull, self._heard)
        self._output.start()

    def push(self, data: bytes, arrival: float) -> bool:
        """Take ``data`` if it is a voice packet (True), else leave it to the face (False)."""
        if not is_voice(data):
            return False
        try:
            packet = decode(data)
        except VoiceError as error:
            with self._lock:
                self.corrupt[error.reason] = self.corrupt.get(error.reason, 0) + 1
            return True
        with self._lock:
            self._buffer.push(packet, arrival)
            self.bytes += len(data)
            self.first = arrival if self.first is None else self.first
            self.last = arrival
        return True

    def face(self, capture: float, out: float) -> None:
        """A face frame captured at ``capture`` was out at ``out`` (this host's clock)."""
        with self._lock:
            self._face = (capture, out)
            self._face_latencies.append(out - capture)

    def _pull(self) -> np.ndarray:
        with self._lock:
            pcm = self._buffer.pull()
            self._pulled = self._buffer.pulled
            self._sounding = self._buffer.playing is not None  # a frame, or a stretch's
        return pcm

    def _heard(self, pcm: np.ndarray, out: float) -> None:
        n = self._pulled
        if n is not None:
            capture = self._to_local(n % 65536, out)
            with self._lock:
                if capture is not None:
                    self.latencies.append(out - capture)
                    self.own.append(out - capture - self._buffer.extra * FRAME_S)
                face = self._face
                if capture is not None and face is not None and out - face[1] < FACE_STALE_S:
                    self.skews.append((out - capture) - (face[1] - face[0]))
                    self._follow(out - capture)
        if self._on_sound is not None and self._sounding:
            self._on_sound(pcm, out)

    def _follow(self, latency: float) -> None:
        """Stretch or shrink the sound toward the face's latency (module docstring, "Keeping
        them together"); ``latency``: the frame just heard's. Under the lock."""
        skew = latency - float(np.median(self._face_latencies))
        if not self._joined:  # the first skew known: the whole wait at once
            self._joined = True
            while skew < -AHEAD_S and self._buffer.stretch():
                skew += FRAME_S
            self._since_change = 0
            return
        self._since_change += 1
        if self._since_change < ADJUST_EVERY:
            return
        if skew < -AHEAD_S and self._buffer.stretch() or skew > BEHIND_S and self._buffer.shrink():
            self._since_change = 0

    def close(self) -> None:
        """Stop the device or the clock."""
        self._output.stop()

    def summary(self) -> dict[str, Any]:
        """``voice_*`` counts (``receiver.jitterbuffer``'s, ``voice_corrupt`` with the packets
        that did not decode), ``voice_target_ms`` (the buffer's depth), ``voice_extra_ms`` (of
        it, the wait for the face: module docstring), ``audio_kbps`` (voice
        packets' bytes over their span), ``av_skew_ms_median``, ``_p95``, ``_p5``,
        ``voice_glass_to_glass_ms_median`` and ``_p95`` (capture to out; None without samples),
        ``voice_own_ms_median`` and ``_p95`` (the same less the wait for the face: the
        voice's own path, what a call without a face would hear) and ``speaker`` (the device,
        or "none")."""
        with self._lock:
            stats = dict(self._buffer.stats)
            skews = np.array(self.skews) * 1000
            latencies = np.array(self.latencies) * 1000
            own = np.array(self.own) * 1000
            span = (self.last - self.first) if self.first is not None and self.last else 0.0
            corrupt = sum(self.corrupt.values())
        def pct(q: float, values: np.ndarray = skews) -> float | None:
            return round(float(np.percentile(values, q)), 1) if len(values) else None

        return {**{f"voice_{k}": v for k, v in stats.items() if k != "corrupt"},
                "voice_corrupt": corrupt + stats["corrupt"],
                "voice_target_ms": round(self._buffer.target * FRAME_S * 1000),
                "voice_extra_ms": round(self._buffer.extra * FRAME_S * 1000),
                "audio_kbps": round(self.bytes * 8 / span / 1000, 3) if span > 0 else 0.0,
                "av_skew_ms_median": pct(50), "av_skew_ms_p95": pct(95),
                "av_skew_ms_p5": pct(5),
                "voice_glass_to_glass_ms_median": pct(50, latencies),
                "voice_glass_to_glass_ms_p95": pct(95, latencies),
                "voice_own_ms_median": pct(50, own), "voice_own_ms_p95": pct(95, own),
                "speaker": self.device}


def voice_capture(seq: int, origin_s: float, near_s: float) -> float:
    """Voice frame ``seq``'s capture time (sender clock) of a voice stream from ``origin_s``,
    extended to the wrap nearest ``near_s`` (``protocol.clock.capture_s`` at 50 Hz)."""
    return capture_s(seq, origin_s, VOICE_RATE_HZ, near_s)

