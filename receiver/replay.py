"""Replay: a recorded packet log rendered to an H.264 video or a PNG sequence.

``facewire replay LOG --model M --out OUT`` is the receiver without the network: the log's
packets go through the same playout buffer as live ones (``receiver.playout.replay_states``:
each packet arrives at its recorded time, the render clock ticks at the Hello's rate, a
missing packet is concealed), and every frame slot from the first sequence number to the
last becomes one output frame:

    state     = the slot's pose, tangent residuals r and Q (held or eased when concealed)
    image     = receiver.scene.StateRenderer.render(state)   morphed mesh, base texture and
                                                              region volumes, from the view

The rendering runs in a process of its own (``receiver.renderprocess.RenderProcess``), two
frames in flight: the playout, the side-by-side composition and the encoder work on one frame
while the next is drawn. ``render_fps`` is the output frames per second of the child's
drawing time (morph, draw, readback).

Views (``VIEWS``): ``camera`` is the sender's camera with the received pose and the Hello's
intrinsics (the output lines up with the sender's frame; its size is the Hello's unless
given), ``front`` and ``three-quarter`` are virtual cameras framing the head, which turns by
the received rotation (640 x 480 unless given). ``side_by_side`` puts the source video's
frame at the slot's time (the nearest frame, as the log's times come from the source) on
the left: input | reconstruction, for evaluation videos.

Model updates (``models.update``): the log holds each update where the sender issued it
(``protocol.log``). The replay takes an update when the playout reaches its place, i.e. for
the first state whose packet's time is at or after the update record's, and shows each
frame with the model version its packet's ``serial`` names, as a live receiver does
(``models.update.ModelVersions``): once the update is held, the frames that refer to it
show its state; a frame that refers to an update the replay does not hold (its record lost
to damage, ``missing_serials``) is shown with the newest version held, whose regions clamp
Q to the layers they have, and counted (``clamped_frames``). A face lost after a version is
taken eases to that version's rest states (``Playout.rest_q``): an update that inserts a
state before a region's rest state moves it. An intact update record that
does not decode against the version it applies to is refused (``UpdateError``, naming the
log).

Output: a path ending in ``.mp4`` is an H.264 video (``receiver.output.VideoWriter``, encoded
on its own thread); any other path is a folder of PNG frames.

Sound: a log with voice records (``protocol.log``) gives the video a sound track. The voice
frames are decoded in their order (``log_sound``), a missing one rebuilt from the next's FEC
or concealed (``protocol.opus.Decoder``), and frame ``j`` is placed at the first voice
record's start (its record time less 20 ms: a sender logs a frame once captured) plus ``j -
j0`` frames, on the file's timeline whose frame ``k`` is the log's first packet time plus ``k
/ rate``: both on the log's record times, so the sound keeps the sync the log has (exact for
a log of ``encode``, whose times are the source's; within the sender's processing delay for
one of ``send --record``). The model must be the one the
log was made with (its sha256 is in the log's Hello).
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import VideoFrame, read_frames
from facewire.models.modelfile import PersonModel, load_model
from facewire.models.update import ModelVersions
from facewire.protocol.errors import FacewireError
from facewire.protocol.log import PacketLog, read_log
from facewire.protocol.opus import FRAME_S, SAMPLE_RATE, Decoder
from facewire.protocol.voice import decode as decode_voice
from facewire.protocol.voice import unwrap
from facewire.receiver.output import FrameFolderWriter, VideoWriter, side_by_side
from facewire.receiver.playout import FrameState, Playout, replay_states
from facewire.receiver.renderprocess import RenderProcess
from facewire.receiver.scene import VIEWS, rest_q

VIRTUAL_SIZE = (640, 480)


class ReplayError(FacewireError, ValueError):
    """The log and the model do not belong together, or an option is wrong."""


def replay_log(log_path: str | os.PathLike[str], model_path: str | os.PathLike[str],
               out: str | os.PathLike[str], view: str = "camera",
               size: tuple[int, int] | None = None,
               source: str | os.PathLike[str] | None = None,
               progress: Progress = no_progress) -> dict[str, Any]:
    """Render every frame slot of a packet log (module docstring).

    Args:
        log_path: the ``.fwlog``.
        model_path: the person model the log was made with.
        out: ``OUT.mp4`` or a folder for PNG frames.
        view: one of ``VIEWS``.
        size: (width, height) of the rendering; default as in the module docstring.
        source: the video the log was encoded from, for a side-by-side output.
        progress: wraps an iterable to show progress.

    Returns:
        A summary: ``frames`` written, the playout's counts (``received``, ``concealed``,
        ``corrupt`` ...), ``lost_records`` (damaged packet records), ``updates`` (the log's
        intact update records), ``updates_applied``, ``lost_updates`` (damaged update
        records), ``missing_serials``, ``clamped_frames`` (frames shown with an older
        version than the one they refer to), ``voice_frames`` (the log's voice records),
        ``sound_s`` (the sound track written, s), ``width``, ``height``, ``view``, ``out``,
        ``seconds``, ``render_fps``.

    Raises:
        ReplayError: a bad view or size, the model is not the log's, the log holds no
            intact packet, or its record times span more than the playout replays.
        LogError / ModelFileError / VideoError / OutputError / UpdateError: unreadable
            inputs or output.
    """
    start = time.perf_counter()
    if view not in VIEWS:
        raise ReplayError(f"--view: expected one of {', '.join(VIEWS)}, got {view!r}")
    log = read_log(log_path)
    if not len(log.packets):
        raise ReplayError(f"{log_path}: no intact packet to replay ({log.lost} damaged "
                          f"records)")
    model = load_model(model_path)
    hello = log.hello
    if hello.model_sha256 != model.sha256:
        raise ReplayError(f"{model_path}: sha256 {model.sha256[:16]}... is not the model of "
                          f"{log_path} ({hello.model_sha256[:16]}...)")
    if size is None:
        size = (hello.camera.width, hello.camera.height) if view == "camera" else VIRTUAL_SIZE
    width, height = size
    if not (0 < width <= 4096 and 0 < height <= 4096):
        raise ReplayError(f"--size: expected a width and height in [1, 4096], got {size}")
    playout = Playout(hello.rate_hz, rest_q=rest_q(model))
    try:
        states = replay_states(log.packets, log.times, hello.rate_hz, playout=playout)
    except ValueError as exc:  # the record times (e.g. a span of weeks): the log's fault
        raise ReplayError(f"{log_path}: {exc}") from None
    versions = _Versions(model, log, Path(log_path))  # a bad update refused before any output
    frames = _SourceFrames(source) if source is not None else None
    out = Path(out)
    out_width = width + (0 if frames is None else frames.width(height))
    t0 = float(np.min(log.times)) if len(log.times) else 0.0
    sound = log_sound(log, t0) if out.suffix == ".mp4" else None
    writer = VideoWriter(out, out_width, height, hello.rate_hz, sound=sound is not None) \
        if out.suffix == ".mp4" else FrameFolderWriter(out)
    if sound is not None and isinstance(writer, VideoWriter):
        writer.write_sound(*sound)
    clamped = written = 0
    drawn: deque[int] = deque()  # the output index of each frame in flight
    with RenderProcess(model, width, height, hello.camera, view) as renderer, writer:

        def write_oldest() -> None:
            nonlocal written
            image = renderer.collect()
            k = drawn.popleft()
            if frames is not None:
                image = side_by_side(frames.at(t0 + k / hello.rate_hz), image, height)
            writer.write(image)
            written += 1

        for k, state in enumerate(progress(states, "rendering", None)):
            shown = versions.model(state)
            if shown is not renderer.model:
                renderer.set_model(shown)  # frames in flight keep the version they had
                playout.rest_q = rest_q(shown)  # a lost face eases to this version's rest
            clamped += versions.held < state.serial
            if renderer.in_flight == renderer.depth:
                write_oldest()
            renderer.submit(state)
            drawn.append(k)
        while drawn:
            write_oldest()
        timed, render_seconds = len(renderer.render_seconds), sum(renderer.render_seconds)
    elapsed = time.perf_counter() - start
    return {"out": str(out), "view": view, "width": width, "height": height,
            "frames": written, **playout.stats, "lost_records": log.lost,
            "updates": len(log.updates), "updates_applied": versions.applied,
            "lost_updates": log.lost_updates, "missing_serials": list(log.missing_serials),
            "clamped_frames": clamped, "voice_frames": len(log.voice),
            "sound_s": 0.0 if sound is None else round(len(sound[0]) / SAMPLE_RATE, 3),
            "seconds": round(elapsed, 2),
            "render_fps": round(timed / render_seconds, 1) if render_seconds else None}


def log_sound(log: PacketLog, t0: float) -> tuple[np.ndarray, float] | None:
    """The log's voice as one sound track (module docstring, "Sound"): (N,) int16 at 48 kHz
    and where it starts after ``t0`` (s, >= 0; sound before ``t0`` is cut); None without
    voice records."""
    if not log.voice:
        return None
    packets: dict[int, bytes] = {}
    last = None
    for record in log.voice:
        packet = decode_voice(record.data)
        last = unwrap(packet.seq, last)
        packets.setdefault(last, packet.opus)
    first = min(packets)
    start = log.voice[0].time - FRAME_S - (next(iter(packets)) - first) * FRAME_S
    decoder, frames = Decoder(), []
    for j in range(first, max(packets) + 1):
        if j in packets:
            frames.append(decoder.decode(packets[j]))
        elif j + 1 in packets:
            frames.append(decoder.recover(packets[j + 1]))
        else:
            frames.append(decoder.conceal())
    pcm = np.concatenate(frames)
    skip = max(0, round((t0 - start) * SAMPLE_RATE))
    return pcm[skip:], max(0.0, start - t0)


class _Versions:
    """The model versions a replay holds as it goes (module docstring, "Model updates").

    Every intact update record is decoded at the start, in file order, so that a bad one is
    refused before any output is written; update n is then held from the first state whose
    packet's time is at or after the records of updates 1 .. n.
    """

    def __init__(self, model: PersonModel, log: PacketLog, path: Path) -> None:
        self._versions = ModelVersions(model)
        issued: dict[int, float] = {}
        for record in log.updates:
            self._versions.add(record.serial, record.data, f"{path}: update record "
                                                           f"{record.serial}")
            issued.setdefault(record.serial, record.time)
        # version n is held once every record up to n is: the running maximum of their times
        self._ready = np.maximum.accumulate([issued[n] for n in range(1, self.applied + 1)])
        self._clock = -math.inf
        self.held = 0

    @property
    def applied(self) -> int:
        """The updates the log lets a replay apply (every serial up to it intact)."""
        return self._versions.held

    def model(self, state: FrameState) -> PersonModel:
        """The model to show ``state`` with (``held`` is its version's newest possible)."""
        if state.arrival_s is not None:
            self._clock = max(self._clock, state.arrival_s)
        self.held = int(np.searchsorted(self._ready, self._clock, side="right"))
        return self._versions.model(min(state.serial, self.held))


class _SourceFrames:
    """The source video's frames, read forward, the nearest to a time (RGB)."""

    def __init__(self, source: str | os.PathLike[str]) -> None:
        self._frames = read_frames(source)
        current = next(self._frames, None)
        if current is None:
            raise ReplayError(f"{source}: no frames to put beside the rendering")
        self._current: VideoFrame = current
        self._next = next(self._frames, None)

    def width(self, height: int) -> int:
        h, w = self._current.image.shape[:2]
        return int(round(w * height / h))

    def at(self, t: float) -> np.ndarray:
        while self._next is not None and abs(self._next.time - t) <= abs(
                self._current.time - t):
            self._current, self._next = self._next, next(self._frames, None)
        return np.ascontiguousarray(self._current.image[..., ::-1])
