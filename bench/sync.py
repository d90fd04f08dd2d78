"""``facewire bench sync``: face and voice, sent and received live, and how well they agree.

One run, on loopback, through the real parts: ``sender.sender.send`` streams the clip's
frames and its own sound track (the voice: ``sender.voice``) on a free port, and
``receiver.receiver.receive``, on a thread of its own, fetches nothing (it is given the
model), plays both and writes what it showed into a video with its sound
(``--out``-style: ``receiver.receiver``, "Voice"), as a live picture: with ``keep_up``, a
draw or an encoder slower than the stream repeats the last frame for a slot already
overtaken instead of falling behind (what a viewer sees; ``frames_repeated``; in the file
the frame before lasts the slot, so ``frames_shown`` counts the file's slots). Measured:

- Playout skew (the receiver's own, ``receiver.voiceplayer``): for each voice frame played,
  its latency less the latency of the face frame out at that moment, so positive when the
  sound is behind: ``av_skew_ms_median``, ``av_skew_ms_p95``, ``av_skew_ms_p5`` (ITU-R
  BT.1359: noticed beyond 45 ms ahead, 125 ms behind). ``voice_glass_to_glass_ms_median``:
  capture (the file's read, on the sender's clock) to playout.
- Lip sync on the pictures (``lip_lag_ms``): the mouth's opening per frame (the inner lips'
  gap, points 62 and 66 of the project's tracker run afresh on each picture,
  ``bench.render_nme.track_fresh``, over the outer-eye distance) against the sound's level
  per frame period; the lag of the peak of their normalised cross-correlation within
  ``MAX_LAG_S`` (``lag_s``: of their frame-to-frame changes) is measured on the received
  video and on the source itself, and ``lip_lag_ms`` is the first less the second: how much
  later the sound comes, in what the viewer saw, than in the original.
  ``lip_lag_source_ms`` and ``lip_lag_received_ms`` are both lags, ``lip_corr_source`` and
  ``lip_corr_received`` the correlations at them: weak on talking heads (0.1-0.3 measured
  on retalk_2 and hdtf_edmarkey, the peak at one frame of lag in both), so read the lags
  with them; the playout skew above is the exact measure.
- Speech quality (``bench.speech``): PESQ-WB of the voice path at each loss in ``losses``
  (``pesq_wb``), with the source's and the codec's own scores beside it, and the voice
  packets' rate measured on the live run (``audio_kbps``).
- With ``page``, the same clip looped to the gateway's page in headless Chromium
  (``bench.pagesync``): the page's own skew, ``page_av_skew_ms_median``, ``_p95``, ``_p5``,
  over ``page_seconds``; without Chromium ``page_skipped`` says why.

The voice's glass-to-glass is ``voice_glass_to_glass_ms_median`` and ``_p95``: the file's
read (slot ``j``'s time on the sender's clock, when a microphone would have given its last
sample) to the frame's playout, through the receiver's jitter buffer and its wait for the
face (``receiver.voiceplayer``); ``voice_own_ms_median`` and ``_p95`` are the same less that
wait: the voice's own path. Timings depend on the
machine's load: ``load_average`` is the 1-minute load when the live run ended.
"""

from __future__ import annotations

import os
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np

from facewire.bench.chromium import ChromiumMissing
from facewire.bench.pagesync import page_sync
from facewire.bench.render_nme import track_fresh
from facewire.bench.speech import DEFAULT_LOSSES, speech_quality
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.sound import Sound, read_sound
from facewire.models.infra.video import read_frames
from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import SAMPLE_RATE
from facewire.protocol.transport import free_loopback_endpoint
from facewire.receiver.receiver import receive
from facewire.sender.sender import send
from facewire.sender.tracker import LandmarkTracker

MAX_LAG_S = 0.3
DRAIN_S = 3.0  # the receiver plays on this long after the sender's last frame
PAGE_SECONDS = 10.0


class SyncError(FacewireError, ValueError):
    """The clip cannot be measured (no sound, too few faces); the message says why."""


def mouth_openings(images: list[np.ndarray], progress: Progress = no_progress) -> np.ndarray:
    """(F,) the inner lips' gap over the outer-eye distance per image (NaN: no face).

    Args:
        images: F (H, W, 3) uint8 images (BGR or RGB: the tracker reads grey).
    """
    tracker = LandmarkTracker()
    out = np.full(len(images), np.nan)
    for k, image in enumerate(progress(images, "mouth", len(images))):
        points = track_fresh(tracker, image)
        if points is not None:
            eyes = float(np.linalg.norm(points[36] - points[45]))
            out[k] = float(np.linalg.norm(points[62] - points[66])) / max(eyes, 1e-6)
    return out


def levels(sound: Sound, times: np.ndarray, period: float) -> np.ndarray:
    """(F,) the sound's RMS level (dB) over ``[t, t + period)`` for each frame time ``t``."""
    out = np.empty(len(times))
    for k, t in enumerate(times):
        pcm = sound.between(t, t + period).astype(np.float64)
        out[k] = 20 * np.log10(np.sqrt(np.mean(pcm ** 2)) + 1.0) if len(pcm) else 0.0
    return out


def lag_s(opening: np.ndarray, level: np.ndarray, rate_hz: float
          ) -> tuple[float | None, float | None]:
    """The lag (s) by which ``level`` follows ``opening``, and the correlation there.

    Both are differenced first (the mouth's opening and closing against the sound's rise and
    fall: a talking face's slow drifts in either say nothing of sync), then the normalised
    cross-correlation is taken at each whole-frame lag within ``MAX_LAG_S`` over the frames
    with a face, and its peak refined between frames by a parabola through the peak and its
    neighbours. (None, None) with fewer than 20 frames with a face.

    Args:
        opening: (F,) per frame, NaN without a face.
        level: (F,) dB per frame.
    """
    a, b = np.diff(opening), np.diff(level)
    ok = np.isfinite(a)
    if ok.sum() < 20:
        return None, None
    most = int(round(MAX_LAG_S * rate_hz))
    lags = np.arange(-most, most + 1)
    r = np.full(len(lags), -np.inf)
    for i, lag in enumerate(int(v) for v in lags):
        x = a[max(0, -lag):len(a) - max(0, lag)]
        y = b[max(0, lag):len(b) - max(0, -lag)]
        m = ok[max(0, -lag):len(a) - max(0, lag)]
        if m.sum() >= 20 and np.std(x[m]) > 0 and np.std(y[m]) > 0:
            r[i] = float(np.corrcoef(x[m], y[m])[0, 1])
    i = int(np.argmax(r))
    if not np.isfinite(r[i]):
        return None, None
    shift = 0.0
    if 0 < i < len(r) - 1 and np.isfinite(r[i - 1]) and np.isfinite(r[i + 1]):
        bend = r[i - 1] - 2 * r[i] + r[i + 1]
        shift = 0.5 * (r[i - 1] - r[i + 1]) / bend if bend < 0 else 0.0
    return (lags[i] + shift) / rate_hz, r[i]


def _video_lag(path: Path, progress: Progress, frames_range: slice = slice(0, None),
               rate_hz: float | None = None) -> tuple[float | None, float | None, int]:
    """A video's lag of its sound behind its mouth and its correlation (``lag_s``), and its
    frame count on the grid of ``rate_hz`` (default: the median frame interval's): a file
    whose frames last several slots (a live receiver's holds, ``receiver.output``) has each
    frame's mouth on every slot it lasts."""
    frames = list(read_frames(path, frames_range))
    sound = read_sound(path)
    if sound is None or len(frames) < 2:
        return None, None, len(frames)
    times = np.array([f.time for f in frames])
    rate = rate_hz or 1.0 / float(np.median(np.diff(times)))
    shown = shown_per_slot(times, rate)
    opening = mouth_openings([f.image for f in frames], progress)[shown]
    grid = times[0] + np.arange(len(shown)) / rate
    return (*lag_s(opening, levels(sound, grid, 1.0 / rate), rate), len(shown))


def shown_per_slot(times: np.ndarray, rate_hz: float) -> np.ndarray:
    """(S,) int: for each slot of ``1 / rate_hz`` from the first frame to the last, the index
    of the frame on screen then (the last one at or before it).

    Args:
        times: (F,) increasing presentation times, s, F >= 1.
    """
    slots = np.round((times - times[0]) * rate_hz).astype(int)
    return np.searchsorted(slots, np.arange(slots[-1] + 1), side="right") - 1


def sync(model: str | os.PathLike[str], source: str | os.PathLike[str],
         losses: tuple[float, ...] = DEFAULT_LOSSES, frames: slice = slice(0, None),
         progress: Progress = no_progress, page: bool = False,
         page_seconds: float = PAGE_SECONDS) -> tuple[dict[str, Any], list[str]]:
    """The module docstring's measures, and their report lines.

    Raises:
        SyncError: the source has no sound track, or the receiver ended before the stream
            started.
        SpeechError, SoundError, ModelFileError, CaptureError: as their commands.
        PageSyncError: with ``page``, the page did not play the clip.
    """
    if read_sound(source) is None:
        raise SyncError(f"{os.fspath(source)}: has no sound track: nothing to sync")
    with tempfile.TemporaryDirectory(prefix="facewire-sync-") as scratch:
        out = Path(scratch) / "received.mp4"
        endpoint = free_loopback_endpoint()
        ready, stop, heard = threading.Event(), threading.Event(), threading.Event()
        got: dict[str, Any] = {}

        def run() -> None:
            try:
                got.update(receive(endpoint, model, out, ready=ready, audio=True,
                                   speaker=None, stop=heard, keep_up=True))
            except Exception as error:  # noqa: BLE001 - raised below as a SyncError
                got["error"] = f"{type(error).__name__}: {error}"
            finally:
                if not ready.is_set():  # the sender waits for it: let it go, and stop
                    stop.set()
                    ready.set()

        thread = threading.Thread(target=run, name="bench sync receiver", daemon=True)
        thread.start()
        sent = send(model, str(source), bind=endpoint, frames=frames, learn=False,
                    start=ready, stop=stop)
        heard.wait(DRAIN_S)  # the last packets played out, then the receiver stops
        heard.set()
        thread.join()
        if stop.is_set():
            raise SyncError(f"the receiver ended before it could play the stream: "
                            f"{got.get('error') or got.get('ended')}")
        load = round(os.getloadavg()[0], 1)
        received_lag, received_r, shown = _video_lag(out, progress, rate_hz=sent["rate_hz"]) \
            if out.is_file() else (None, None, 0)
        on_page: dict[str, Any] = {}
        skipped = None if page else "not asked for"
        if page:
            try:
                on_page = page_sync(model, source, frames, page_seconds, Path(scratch))
                on_page["page_load_average"] = round(os.getloadavg()[0], 1)
            except ChromiumMissing as missing:
                skipped = str(missing)
    source_lag, source_r, _ = _video_lag(Path(source), progress, frames)
    quality, _ = speech_quality(source, losses=losses)

    def ms(value: float | None) -> float | None:
        return None if value is None else round(value * 1000, 1)

    summary = {
        "source": os.fspath(source), "model": os.fspath(model),
        "frames_sent": sent["frames"], "frames_shown": shown,
        "frames_repeated": got.get("repeated"),
        "voice_packets": sent["voice_packets"], "audio_kbps": sent["audio_kbps"],
        "payload_kbps": sent["payload_kbps"],
        "total_kbps": round(sent["audio_kbps"] + sent["payload_kbps"], 3),
        **{k: got.get(k) for k in ("av_skew_ms_median", "av_skew_ms_p95", "av_skew_ms_p5",
                                  "voice_glass_to_glass_ms_median",
                                  "voice_glass_to_glass_ms_p95", "voice_own_ms_median",
                                  "voice_own_ms_p95", "voice_extra_ms", "voice_stretched",
                                  "voice_shrunk", "voice_played",
                                  "voice_concealed", "voice_late", "voice_corrupt",
                                  "voice_target_ms", "glass_to_glass_ms_median")},
        "load_average": load, **on_page, "page_skipped": skipped,
        "lip_lag_source_ms": ms(source_lag), "lip_lag_received_ms": ms(received_lag),
        "lip_corr_source": None if source_r is None else round(source_r, 3),
        "lip_corr_received": None if received_r is None else round(received_r, 3),
        "lip_lag_ms": ms(None if source_lag is None or received_lag is None
                         else received_lag - source_lag),
        "pesq_wb": quality["pesq_wb"], "pesq_wb_source": quality["pesq_wb_source"],
        "pesq_wb_opus": quality["pesq_wb_opus"], "sample_rate": SAMPLE_RATE,
    }
    lines = [
        f"{summary['source']}: {sent['frames']} frames and {sent['voice_packets']} voice packets "
        f"sent ({summary['payload_kbps']} + {summary['audio_kbps']} = {summary['total_kbps']} "
        f"kbit/s)",
        f"playout: sound behind the face by {summary['av_skew_ms_median']} ms median "
        f"({summary['av_skew_ms_p5']} to {summary['av_skew_ms_p95']} ms, 5-95 %); voice "
        f"capture to playout {summary['voice_glass_to_glass_ms_median']} ms median, "
        f"{summary['voice_glass_to_glass_ms_p95']} ms p95, of which the voice's own path "
        f"{summary['voice_own_ms_median']} ms median (load average {load})",
        *([f"page: sound behind the face by {on_page['page_av_skew_ms_median']} ms median "
           f"({on_page['page_av_skew_ms_p5']} to {on_page['page_av_skew_ms_p95']} ms, 5-95 %) "
           f"over {on_page['page_skews']} frames in {on_page['page_seconds']} s"]
          if on_page else [f"page: skipped: {skipped}"] if page else []),
        f"lip sync: sound after the mouth by {summary['lip_lag_received_ms']} ms received, "
        f"{summary['lip_lag_source_ms']} ms in the source: {summary['lip_lag_ms']} ms added",
        "PESQ-WB: " + ", ".join(f"{loss} % loss {score}" for loss, score in
                                quality["pesq_wb"].items())
        + f" (source {quality['pesq_wb_source']}, codec alone {quality['pesq_wb_opus']})",
    ]
    return summary, lines
