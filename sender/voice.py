"""The sender's voice: sound in 20-ms frames, Opus-encoded, published beside the face.

Sources (``open_voice``):

- a video file's own sound track (``models.infra.sound``): frame ``j`` holds the sound of
  stream time ``t0 + j * 20 ms``, ``t0`` the stream time of the face's first slot, so the
  voice is cut on the timeline the face's frames are stamped on. A looped file's stream time
  runs on across passes; ``passes`` holds each pass's start offset (the send loop's, as it
  reads the file), and stream time ``t`` is file time ``t - o`` for the last pass offset
  ``o`` whose first frame is at or before ``t``, so the sound loops exactly where the frames
  do. After the face's stream stalled and its clock started again later (``sender.slots``),
  the face's stream time is ``lag_s`` behind the voice's capture clock; the voice follows it
  (the send loop sets ``lag_s``). A file without a sound track sends no voice (one line says so);
- a microphone (``mic:N`` or a device name, through sounddevice/PortAudio): 48 kHz mono
  blocks of one frame each, as the device delivers them. No such device, or no PortAudio, is
  one clear line (``VoiceSourceError``), and the face goes on without voice.

Clock. The voice's frames are numbered from 0 at ``origin_s`` on the sender's clock
(``protocol.clock``: ``time.monotonic()``): frame ``j`` holds the sound captured from
``origin_s + j * 20 ms``, the Hello announces ``origin_s`` (``protocol.control.Voice``), and
so every voice packet's capture time is known to a receiver as every face packet's is. For a
file, ``origin_s`` is the face's own origin (the first slot's release), so the two start
together; frame ``j`` is released at ``origin_s + (j + 1) * 20 ms``, when its last sample
would have been captured by a microphone.

``VoiceThread`` runs a source on a thread of its own (the face's frame loop must not wait
for sound, nor the sound for a face), encodes each frame (``protocol.opus``) and hands the
packet (``protocol.voice``) to ``publish``, which must be safe to call from that thread
(the send loop guards its PUB socket with a lock).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from facewire.models.infra.sound import Sound
from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import FRAME_S, FRAME_SAMPLES, SAMPLE_RATE, Encoder
from facewire.protocol.voice import SEQ_MODULO, VoicePacket, encode

MIC_QUEUE_FRAMES = 50  # 1 s of blocks waiting for the encoder; older ones are dropped


class VoiceSourceError(FacewireError, RuntimeError):
    """The voice source cannot be opened (the message names it)."""


@dataclass
class FileVoice:
    """A file's sound cut into frames from stream time ``t0`` (module docstring); after the
    end of the file's last pass, silence."""

    sound: Sound
    t0: float = 0.0
    passes: list[float] = field(default_factory=lambda: [0.0])
    lag_s: float = 0.0

    def frame(self, j: int) -> np.ndarray:
        """(FRAME_SAMPLES,) int16: frame ``j``."""
        t = self.t0 + j * FRAME_S - self.lag_s
        first = self.t0 - self.passes[0]  # the first frame's time in the file
        offset = max((o for o in self.passes if o + first <= t + 1e-9), default=0.0)
        t -= offset
        pcm = self.sound.between(t, t + FRAME_S)
        return pcm[:FRAME_SAMPLES] if len(pcm) >= FRAME_SAMPLES else np.pad(
            pcm, (0, FRAME_SAMPLES - len(pcm)))

    def frames(self, origin_s: float, stop: threading.Event
               ) -> Iterator[tuple[int, np.ndarray]]:
        """(j, frame j), each released at ``origin_s + (j + 1) * 20 ms`` (module docstring);
        after a stall of more than a second the frames of the time missed are skipped."""
        j = 0
        while not stop.is_set():
            due = origin_s + (j + 1) * FRAME_S
            wait = due - time.monotonic()
            if wait > 0 and stop.wait(wait):
                return
            if wait < -1.0:  # a stalled machine: start again from now, numbering kept
                j += int(-wait / FRAME_S)
                continue
            yield j, self.frame(j)
            j += 1


class MicVoice:
    """A microphone through sounddevice (PortAudio), one frame per block."""

    def __init__(self, device: str) -> None:
        try:
            import sounddevice  # noqa: PLC0415 - PortAudio is looked for only when a mic is asked
        except (ImportError, OSError) as error:
            raise VoiceSourceError(f"microphone {device}: no PortAudio ({error}); "
                             "install libportaudio2, or send with --no-audio") from None
        index: int | str = int(device[4:]) if device.startswith("mic:") and \
            device[4:].isdigit() else device
        self._blocks: queue.Queue[tuple[int, np.ndarray]] = queue.Queue(MIC_QUEUE_FRAMES)
        self._count = 0  # blocks the device delivered
        self.dropped = 0
        try:
            self._stream = sounddevice.InputStream(
                samplerate=SAMPLE_RATE, blocksize=FRAME_SAMPLES, device=index, channels=1,
                dtype="int16", callback=self._take)
        except (sounddevice.PortAudioError, ValueError) as error:
            raise VoiceSourceError(f"microphone {device}: {error}") from None

    def _take(self, block: np.ndarray, frames: int, _time: object, _status: object) -> None:
        try:
            self._blocks.put_nowait((self._count, block[:, 0].copy()))
        except queue.Full:
            self.dropped += 1
        self._count += 1

    def frames(self, origin_s: float, stop: threading.Event
               ) -> Iterator[tuple[int, np.ndarray]]:
        """(j, block j) as the device delivers them (``origin_s`` is when the stream
        starts; a block dropped from a full queue leaves its number unused)."""
        del origin_s
        with self._stream:
            while not stop.is_set():
                try:
                    yield self._blocks.get(timeout=0.1)
                except queue.Empty:
                    continue


VoiceSource = FileVoice | MicVoice


class VoiceThread:
    """Runs a voice source on its own thread: encode, packetise, ``publish``."""

    def __init__(self, source: VoiceSource, encoder: Encoder, origin_s: float,
                 publish: Callable[[bytes], None]) -> None:
        self._source, self._encoder, self._publish = source, encoder, publish
        self.origin_s = origin_s
        self.packets = 0
        self.bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="voice", daemon=True)

    def start(self) -> None:
        """Start sending frames from ``origin_s`` on."""
        self._thread.start()

    def stop(self) -> None:
        """Stop and wait for the thread."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def _run(self) -> None:
        for j, pcm in self._source.frames(self.origin_s, self._stop):
            data = encode(VoicePacket(j % SEQ_MODULO, self._encoder.encode(pcm)))
            self._publish(data)
            self.packets += 1
            self.bytes += len(data)
