"""Where the received voice is heard: an output device, or a clock of our own without one.

``Speaker(pull, device)`` opens an output device through sounddevice (PortAudio): 48 kHz
mono 16-bit, blocks of one 20-ms frame, its callback calling ``pull()`` for each block (the
jitter buffer's, ``receiver.jitterbuffer``), so the device's own clock paces the playout
and never waits. ``device`` is PortAudio's index or name; None is the default output. No
PortAudio, no such device, or none at all (a server) is one clear line (``SpeakerError``),
and the caller goes on without sound.

``SoundClock(pull)`` is the same pacing without a device: a thread that calls ``pull()``
every 20 ms of the monotonic clock (a stall is caught up, never skipped: every frame is
pulled), for a receiver that writes the sound into a file or has no speaker.

Both hand each frame to ``heard(pcm, t)``, when given, with the time it went out (the
monotonic clock; for a device, PortAudio's estimate of when its first sample reaches the
DAC), from their own thread: for the file's sound track and for measuring sync.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import FRAME_S, FRAME_SAMPLES, SAMPLE_RATE, version

Pull = Callable[[], np.ndarray]
Heard = Callable[[np.ndarray, float], None]


class SpeakerError(FacewireError, RuntimeError):
    """The output device cannot be opened (the message names it)."""


def check_sound() -> str:
    """One line for ``facewire check``: the Opus library, PortAudio and its devices.

    Raises:
        SpeakerError: no PortAudio (install.sh installs libportaudio2).
    """
    try:
        import sounddevice  # noqa: PLC0415 - as in Speaker
    except (ImportError, OSError) as error:
        raise SpeakerError(f"sound: no PortAudio ({error}); install libportaudio2 "
                           "(Debian/Ubuntu) or run ./install.sh again") from None
    devices = sounddevice.query_devices()
    inputs = sum(d["max_input_channels"] > 0 for d in devices)
    outputs = sum(d["max_output_channels"] > 0 for d in devices)
    return (f"sound: {version()}, {sounddevice.get_portaudio_version()[1]}; {inputs} input and "
            f"{outputs} output devices" + ("" if inputs and outputs else
                                           " (voice from files and into files only)"))


class Speaker:
    """An output device that pulls a frame per 20-ms block (module docstring)."""

    def __init__(self, pull: Pull, device: str | None = None, heard: Heard | None = None
                 ) -> None:
        name = device if device is not None else "the default output"
        try:
            import sounddevice  # noqa: PLC0415 - PortAudio is looked for only for a speaker
        except (ImportError, OSError) as error:
            raise SpeakerError(f"speaker {name}: no PortAudio ({error}); "
                               "install libportaudio2, or receive with --no-audio") from None
        self._pull, self._heard = pull, heard
        target: int | str | None = int(device) if device is not None and device.isdigit() \
            else device
        try:
            self._stream = sounddevice.OutputStream(
                samplerate=SAMPLE_RATE, blocksize=FRAME_SAMPLES, device=target, channels=1,
                dtype="int16", callback=self._fill)
        except (sounddevice.PortAudioError, ValueError) as error:
            raise SpeakerError(f"speaker {name}: {error}") from None
        self._shift = time.monotonic() - self._stream.time  # PortAudio's clock to ours

    def _fill(self, out: np.ndarray, frames: int, when: object, _status: object) -> None:
        pcm = self._pull()
        out[:, 0] = pcm[:frames]
        if self._heard is not None:
            self._heard(pcm, float(getattr(when, "outputBufferDacTime", 0.0)) + self._shift)

    def start(self) -> None:
        """Start playing."""
        self._stream.start()

    def stop(self) -> None:
        """Stop and close the device."""
        self._stream.stop()
        self._stream.close()


class SoundClock:
    """Pulls a frame every 20 ms on a thread, without a device (module docstring)."""

    def __init__(self, pull: Pull, heard: Heard | None = None) -> None:
        self._pull, self._heard = pull, heard
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sound clock", daemon=True)
        self.frames = 0

    def start(self) -> None:
        """Start pulling."""
        self._thread.start()

    def stop(self) -> None:
        """Stop and wait for the thread."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def _run(self) -> None:
        start = time.monotonic()
        while True:
            due = start + self.frames * FRAME_S
            wait = due - time.monotonic()
            if wait > 0 and self._stop.wait(wait) or self._stop.is_set():
                return
            pcm = self._pull()
            if self._heard is not None:
                self._heard(pcm, due)
            self.frames += 1
