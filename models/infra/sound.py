"""A video file's sound track as the voice codec takes it: 48 kHz mono 16-bit PCM.

``read_sound(path)`` decodes the file's first audio stream with PyAV (FFmpeg), mixes it down
to mono and resamples it to ``protocol.opus.SAMPLE_RATE`` (FFmpeg's swresample), and places it
on the file's presentation timeline: sample ``i`` of ``Sound.pcm`` plays at
``Sound.start + i / 48000`` seconds, the clock the file's video frames are stamped on
(``models.infra.video.VideoFrame.time``), so a frame and the sound beside it keep the sync the
file has. A file without a sound track gives ``None``; a sound track that cannot be decoded is
a ``SoundError`` naming the file.

``Sound.between(t0, t1)`` cuts the samples of an interval of that timeline, with silence where
the track does not reach.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import av
import numpy as np

from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import SAMPLE_RATE

MAX_SOUND_S = 3 * 3600.0  # a longer track is refused before it is decoded


class SoundError(FacewireError, ValueError):
    """A sound track cannot be read; the message names the file."""


@dataclass(frozen=True)
class Sound:
    """Mono 48 kHz sound on a file's timeline.

    Attributes:
        pcm: (N,) int16 samples.
        start: the time of sample 0 on the file's presentation timeline, seconds.
    """

    pcm: np.ndarray
    start: float

    @property
    def seconds(self) -> float:
        """The track's duration."""
        return len(self.pcm) / SAMPLE_RATE

    def between(self, t0: float, t1: float) -> np.ndarray:
        """(round((t1 - t0) * 48000),) int16: the samples from ``t0`` to ``t1`` on the file's
        timeline, zeros where the track has none."""
        first = round((t0 - self.start) * SAMPLE_RATE)
        count = max(0, round((t1 - t0) * SAMPLE_RATE))
        out = np.zeros(count, np.int16)
        lo, hi = max(first, 0), min(first + count, len(self.pcm))
        if hi > lo:
            out[lo - first:hi - first] = self.pcm[lo:hi]
        return out


def read_sound(path: str | os.PathLike[str]) -> Sound | None:
    """The file's first sound track, or None when it has none.

    Raises:
        SoundError: the file cannot be opened, or its sound cannot be decoded.
    """
    name = Path(path)
    try:
        with av.open(os.fspath(name)) as container:
            if not container.streams.audio:
                return None
            stream = container.streams.audio[0]
            if stream.duration is not None and stream.time_base is not None \
                    and float(stream.duration * stream.time_base) > MAX_SOUND_S:
                raise SoundError(f"{name}: its sound track is longer than "
                                 f"{MAX_SOUND_S / 3600:.0f} hours")
            resampler = av.AudioResampler(format="s16", layout="mono", rate=SAMPLE_RATE)
            parts, start = [], None
            for frame in container.decode(stream):
                if start is None and frame.time is not None:
                    start = float(frame.time)
                parts += [out.to_ndarray().reshape(-1) for out in resampler.resample(frame)]
            parts += [out.to_ndarray().reshape(-1) for out in resampler.resample(None)]
    except av.FFmpegError as error:
        raise SoundError(f"{name}: cannot read its sound track ({error})") from error
    if not parts:
        return None
    return Sound(np.concatenate(parts).astype(np.int16, copy=False), start or 0.0)
