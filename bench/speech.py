"""How the received voice sounds against the source's, under loss (``facewire bench sync``'s
speech quality).

Speech quality is PESQ wideband (ITU-T P.862.2, through the ``pesq`` package: the ITU's
reference code), the received sound scored against the clip's own sound track, both
resampled to 16 kHz (PESQ-WB's rate; ``scipy.signal.resample_poly``, 48 kHz / 3). The
received sound comes from the voice's real path: 20-ms frames encoded by the sender's Opus
(``protocol.opus``) at ``bitrate``, set as the sender sets it (tuned for its default expected
loss, whatever the loss measured), made voice packets (``protocol.voice``), a seeded uniform
share of them dropped, the rest delivered on time into the receiver's jitter buffer
(``receiver.jitterbuffer``), which is pulled once per frame as a speaker would. The buffer's
delay and Opus's look-ahead shift the sound; it is aligned to the source by the lag of their
cross-correlation's peak (within ``MAX_LAG_S``) before scoring.

Scores, PESQ-WB MOS-LQO (1.04 .. 4.64, higher is better):

- ``pesq_wb_source``: the source against itself: PESQ-WB's ceiling, the reference;
- ``pesq_wb_opus``: Opus at the same rate, every packet decoded in order (the codec alone,
  no network);
- ``pesq_wb``: a map from each loss rate (percent, as text: ``"10"``) to the score with that
  share of the packets lost.

``recovered``: for each loss rate, the share of the lost frames rebuilt from the next
packet's in-band FEC (the rest concealed); ``fec_packets``: the share of packets carrying FEC
(both 0 under about 17 kbit/s: ``protocol.opus``).

Also ``audio_kbps``: the voice packets' payload rate (bytes on the packet socket, without
ZeroMQ's framing), the figure set beside the face's 12 kbit/s budget.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from scipy.signal import correlate, resample_poly

from facewire.models.infra.sound import read_sound
from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import (
    DEFAULT_BITRATE,
    FRAME_S,
    FRAME_SAMPLES,
    SAMPLE_RATE,
    Decoder,
    Encoder,
    has_fec,
)
from facewire.protocol.voice import SEQ_MODULO, VoicePacket, decode, encode
from facewire.receiver.jitterbuffer import JitterBuffer

PESQ_RATE = 16_000
MAX_LAG_S = 1.0
DEFAULT_LOSSES = (0, 10, 30)


class SpeechError(FacewireError, ValueError):
    """The clip cannot be scored (no sound track, too short); the message names it."""


def pesq_wb(reference: np.ndarray, degraded: np.ndarray) -> float:
    """PESQ-WB of ``degraded`` against ``reference``, both (N,) int16 at 48 kHz."""
    from pesq import pesq  # noqa: PLC0415 - a C extension, loaded only to score

    ref = resample_poly(reference.astype(np.float64), 1, SAMPLE_RATE // PESQ_RATE)
    deg = resample_poly(degraded.astype(np.float64), 1, SAMPLE_RATE // PESQ_RATE)
    return float(pesq(PESQ_RATE, ref, deg, "wb"))


def align(reference: np.ndarray, played: np.ndarray) -> np.ndarray:
    """``played`` shifted so that it lines up with ``reference`` (the lag of the peak of their
    cross-correlation, 0 .. ``MAX_LAG_S``), cut or padded with silence to its length.

    Args:
        reference: (N,) int16.
        played: (M,) int16, the reference delayed by the path.
    """
    most = int(MAX_LAG_S * SAMPLE_RATE)
    ref = reference.astype(np.float64)
    out = played.astype(np.float64)
    corr = correlate(out, ref, mode="full", method="fft")
    zero = len(ref) - 1
    lag = int(np.argmax(corr[zero:zero + most + 1]))
    shifted = played[lag:lag + len(reference)]
    return np.pad(shifted, (0, len(reference) - len(shifted)))


def _frames(pcm: np.ndarray) -> np.ndarray:
    n = len(pcm) // FRAME_SAMPLES
    return pcm[:n * FRAME_SAMPLES].reshape(n, FRAME_SAMPLES)


def received(frames: np.ndarray, bitrate: int, loss_percent: float, seed: int = 0
             ) -> tuple[np.ndarray, list[bytes], dict[str, int]]:
    """The sound a receiver plays, the voice packets sent and the jitter buffer's counts.

    Args:
        frames: (F, FRAME_SAMPLES) int16, the source in 20-ms frames.
        bitrate: Opus's rate, bit/s.
        loss_percent: the share of packets dropped, 0 .. 100.
        seed: the loss pattern's.

    Returns:
        ((F + tail) * FRAME_SAMPLES,) int16 as pulled from the jitter buffer (a pull per
        frame, from the first packet's arrival until every frame has had its turn), the F
        voice packets (``protocol.voice``) and ``JitterBuffer.stats`` with ``lost``, the
        packets dropped.
    """
    encoder = Encoder(bitrate)
    packets = [encode(VoicePacket(j % SEQ_MODULO, encoder.encode(f))) for j, f in
               enumerate(frames)]
    lost = np.random.default_rng(seed).random(len(packets)) < loss_percent / 100
    buffer = JitterBuffer()
    out = []
    for j in range(len(frames) + 20):
        if j < len(packets) and not lost[j]:
            buffer.push(decode(packets[j]), j * FRAME_S)
        out.append(buffer.pull())
    return np.concatenate(out), packets, {**buffer.stats, "lost": int(lost.sum())}


def losses(text: str) -> tuple[float, ...]:
    """``--loss``'s comma-separated percentages.

    Raises:
        SpeechError: not numbers in 0 .. 100.
    """
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise SpeechError(f"--loss: expected percentages like 0,10,30, got {text!r}") from None
    if not all(0 <= v <= 100 for v in values):
        raise SpeechError(f"--loss: percentages must be in 0..100, got {text!r}")
    return values


def speech_quality(source: str | os.PathLike[str], bitrate: int = DEFAULT_BITRATE,
                losses: tuple[float, ...] = DEFAULT_LOSSES) -> tuple[dict[str, Any], list[str]]:
    """The module docstring's rows for one clip's sound track, and their report lines.

    Raises:
        SpeechError: no sound track, or less than a second of it, or no loss asked for.
        SoundError: the sound cannot be decoded (names the file).
    """
    if not losses:
        raise SpeechError("losses: give at least one loss rate")
    sound = read_sound(source)
    if sound is None:
        raise SpeechError(f"{os.fspath(source)}: has no sound track")
    frames = _frames(sound.pcm)
    if len(frames) * FRAME_S < 1.0:
        raise SpeechError(f"{os.fspath(source)}: less than a second of sound")
    reference = frames.reshape(-1)
    decoder, encoder = Decoder(), Encoder(bitrate)
    codec_only = np.concatenate([decoder.decode(encoder.encode(f)) for f in frames])
    summary: dict[str, Any] = {
        "source": os.fspath(source), "seconds": round(len(reference) / SAMPLE_RATE, 3),
        "bitrate": bitrate,
        "pesq_wb_source": round(pesq_wb(reference, reference), 3),
        "pesq_wb_opus": round(pesq_wb(reference, align(reference, codec_only)), 3),
    }
    packets: list[bytes] = []
    scores, recovered = {}, {}
    for loss in losses:
        played, packets, stats = received(frames, bitrate, loss)
        scores[f"{loss:g}"] = round(pesq_wb(reference, align(reference, played)), 3)
        recovered[f"{loss:g}"] = round(stats["recovered"] / stats["lost"], 3) \
            if stats["lost"] else None
    fec = sum(has_fec(decode(p).opus) for p in packets) / len(packets)
    summary["pesq_wb"] = scores
    summary["recovered"] = recovered
    summary["fec_packets"] = round(fec, 3)
    summary["audio_kbps"] = round(sum(map(len, packets)) * 8 / (len(frames) * FRAME_S) / 1000,
                                  3)
    lines = [f"{summary['source']}: {summary['seconds']} s of sound, Opus at "
             f"{bitrate / 1000:g} kbit/s ({summary['audio_kbps']} kbit/s of voice packets, "
             f"{round(fec * 100)} % carrying FEC)",
             f"PESQ-WB: source {summary['pesq_wb_source']}, codec alone "
             f"{summary['pesq_wb_opus']}, " + ", ".join(
                 f"{loss} % loss {score}" for loss, score in scores.items())]
    return summary, lines


def speech_table(sources: list[str], bitrate: int = DEFAULT_BITRATE,
                 losses: tuple[float, ...] = DEFAULT_LOSSES) -> tuple[dict[str, Any], list[str]]:
    """``facewire bench speech``: ``speech_quality`` of each clip in one run, and the lowest
    score at each loss over them (``pesq_wb_min``).

    Raises:
        SpeechError, SoundError: as ``speech_quality``, for the first clip that fails.
    """
    clips, lines = [], []
    for source in sources:
        summary, clip_lines = speech_quality(source, bitrate, losses)
        clips.append(summary)
        lines += clip_lines
    lowest = {loss: min(c["pesq_wb"][loss] for c in clips) for loss in clips[0]["pesq_wb"]}
    lines.append(f"lowest PESQ-WB over {len(clips)} clips: " + ", ".join(
        f"{loss} % loss {score}" for loss, score in lowest.items()))
    return {"bitrate": bitrate, "clips": clips, "pesq_wb_min": lowest}, lines
