"""Guided enrollment: ``facewire model build --guided SOURCE``, the routine of prompts
(``sender.enroll.routine``) recorded from a camera, then the model built from the recording.

Recording (``record_routine``). The source's frames (``sender.capture.open_source``: a
camera, or a video file standing in for one) are read against the routine's schedule, in
frame time from the first frame: each prompt's lead-in ("get ready", not recorded), then its
take (recorded). Every frame is handed to ``show`` with the current ``Cue`` (the command
draws it on the terminal's status line and, with ``--view``, on the live page:
``overlay``); each prompt's start is announced through ``say``.

Where the frames go. A take's frames are written as they come to a temporary H.264 file
(the recording; not memory: the whole routine records about 830 frames, 0.8 GB raw at
640 x 480), by the writer the caller opens (``open_writer``: the command passes
``receiver.output.VideoWriter``, x264 crf 18, since ``sender`` may not import the receiver).
The build then reads that file like any enrollment video (``sender.enroll.build``), with the
takes' frames as its ``Guide``, and the file is deleted when the build is done.

Face lost. Each take's frames are tracked as they are recorded (``sender.tracker``). A take
in which fewer than ``MIN_FACE_FRACTION`` of the frames show a face is repeated (lead-in and
take again; the announcement says why), up to ``MAX_TRIES`` takes of a prompt; a repeated
take's frames stay in the recording without a prompt (the fit and texture may use them, no
region's states come from them). The last try is kept whatever it shows, and the report says
how many of its frames had a face; a region whose prompts' frames give too few usable
frames takes its other states from any frame (the layers' report says ``prompted: false``).
The camera is read on the routine's own thread (each take's frame is tracked before the
next is read), not on ``sender.framethread``'s: untried on a real camera.

A video file standing in. It is read as fast as it decodes (in real time with ``--view``,
so that the page can be watched), and the schedule runs in its frame time, so a file plays
exactly the routine a camera would have recorded over the same seconds; the person in it
does not follow the prompts, so the states come from whatever those seconds show. A file
that ends before the routine does is a ``GuidedError``.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import VideoFrame
from facewire.models.manifest import SourceRange
from facewire.protocol.errors import FacewireError
from facewire.sender.capture import Source
from facewire.sender.enroll.build import BuildResult, SelfCheckHook, build_model
from facewire.sender.enroll.routine import ROUTINE, Guide, Prompt, Schedule
from facewire.sender.tracker import LandmarkTracker

MIN_FACE_FRACTION = 0.5  # a take with a face in fewer of its frames is repeated
MAX_TRIES = 3  # takes of one prompt at most
READY, RECORD = "get ready", "recording"
DEFAULT_SCHEDULE = Schedule()
TIME_TOLERANCE_S = 1e-6  # a frame this close to a phase's end starts the next phase


class GuidedError(FacewireError, ValueError):
    """The guided routine cannot be recorded (a video standing in ended too soon), or its
    recording cannot give a model; the message names the source."""


class FrameWriter(Protocol):
    """Where the recording goes: ``receiver.output.VideoWriter``'s interface."""

    def write(self, rgb: np.ndarray) -> None: ...

    def __enter__(self) -> Any: ...

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None: ...


WriterFactory = Callable[[Path, int, int, float], FrameWriter]  # path, width, height, rate


@dataclass(frozen=True)
class Cue:
    """What the person is shown with one frame.

    Attributes:
        step: the prompt's number in ``ROUTINE``, from 1.
        prompt: the prompt.
        phase: ``READY`` (the lead-in) or ``RECORD`` (the take).
        left_s: seconds left in the phase.
        attempt: the take's number for this prompt, from 1.
        face: whether the frame shows a face (a take's frames only; None in a lead-in).
    """

    step: int
    prompt: Prompt
    phase: str
    left_s: float
    attempt: int
    face: bool | None

    def line(self) -> str:
        """The terminal's status line."""
        face = "" if self.face is None else f"  face {'yes' if self.face else 'no '}"
        return f"  {self.phase} {self.left_s:4.1f} s{face}"

    def stats(self) -> dict[str, Any]:
        """The live page's statistics."""
        return {"prompt": f"{self.step}/{len(ROUTINE)}: {self.prompt.text}",
                "phase": self.phase, "seconds_left": round(self.left_s, 1),
                "take": self.attempt, "face": self.face}


@dataclass(frozen=True)
class Take:
    """One prompt's kept take.

    Attributes:
        prompt: the prompt.
        frames: [start, stop) its frames' indices in the recording.
        source_frames: [start, stop) the source's frame indices (a file's own; a camera's
            count of frames read).
        face_frames: how many of its frames showed a face.
        tries: takes of this prompt (more than 1: the face was lost).
    """

    prompt: Prompt
    frames: tuple[int, int]
    source_frames: tuple[int, int]
    face_frames: int
    tries: int

    def as_dict(self) -> dict[str, Any]:
        return {"prompt": self.prompt.name, "text": self.prompt.text,
                "feeds": list(self.prompt.feeds), "frames": list(self.frames),
                "source_frames": list(self.source_frames), "face_frames": self.face_frames,
                "tries": self.tries}


@dataclass(frozen=True)
class Recording:
    """The recorded routine: the kept takes in ``ROUTINE`` order, per recorded frame its
    prompt (None: a repeated take's), and [start, stop) the source's frame indices from the
    first frame recorded to the last."""

    takes: tuple[Take, ...]
    labels: tuple[str | None, ...]
    source_frames: tuple[int, int]

    def guide(self, source: Source) -> Guide:
        """The build's guide; of a video file standing in, the range of its frames the
        recording spans (first take to last)."""
        if source.live:
            return Guide.of_labels(self.labels, source.name)
        return Guide.of_labels(self.labels, Path(source.name).name,
                               SourceRange.of_file(source.name, *self.source_frames))


@dataclass(frozen=True)
class GuidedResult:
    """What ``build_guided`` made: the build and the recording it was built from."""

    build: BuildResult
    recording: Recording
    source: str

    def summary(self) -> dict[str, Any]:
        """``BuildResult.summary`` with ``guided``: the source and each prompt's take."""
        return {**self.build.summary(), "guided": {
            "source": self.source, "recorded_frames": len(self.recording.labels),
            "prompts": [t.as_dict() for t in self.recording.takes]}}


def record_routine(frames: Iterable[VideoFrame], write: Callable[[np.ndarray], None],
                   schedule: Schedule = DEFAULT_SCHEDULE,
                   show: Callable[[Cue, np.ndarray], None] | None = None,
                   say: Callable[[str], None] | None = None, name: str = "the source"
                   ) -> Recording:
    """Run the routine over a stream of frames (module docstring, "Recording").

    Args:
        frames: the source's frames, (H, W, 3) uint8 BGR images with times in seconds.
        write: takes each recorded frame, (H, W, 3) uint8 BGR, in recording order.
        schedule: the lead-in and take lengths.
        show: called with every frame read and its cue.
        say: called with each prompt's announcement (one line).
        name: the source, for errors.

    Raises:
        GuidedError: the frames end before the routine does.
    """
    tracker = LandmarkTracker()
    labels: list[str | None] = []
    takes: list[Take] = []
    step, attempt, phase = 0, 1, READY
    leads = takes_run = 0  # phases ended so far: their lengths sum to the phase's start
    first, faces, source_start, source_end = len(labels), 0, -1, -1
    first_read = -1  # the first recorded frame's source index
    t0: float | None = None

    def phase_end() -> float:
        """The current phase's end, seconds from the first frame."""
        return schedule.end(leads + (phase == READY), takes_run + (phase == RECORD))

    def announce(why: str = "") -> None:
        if say is not None:
            say(f"[{step + 1}/{len(ROUTINE)}] {ROUTINE[step].text}{why}")

    announce()
    for frame in frames:
        if t0 is None:
            t0 = frame.time
        t = frame.time - t0
        while t >= phase_end() - TIME_TOLERANCE_S:
            if phase == READY:
                phase, leads = RECORD, leads + 1
                first, faces, source_start = len(labels), 0, -1
                continue
            takes_run += 1
            count = len(labels) - first
            phase = READY
            if faces < MIN_FACE_FRACTION * count or not count:
                if attempt < MAX_TRIES:
                    labels[first:] = [None] * count
                    attempt += 1
                    announce(f" (again: a face in {faces} of {count} frames)")
                    continue
            takes.append(Take(ROUTINE[step], (first, len(labels)),
                              (source_start, source_end), faces, attempt))
            step, attempt = step + 1, 1
            if step == len(ROUTINE):
                return Recording(tuple(takes), tuple(labels), (first_read, source_end))
            announce()
        face = None
        if phase == RECORD:
            face = tracker.track(frame.image).points is not None
            faces += face
            if source_start < 0:
                source_start = frame.index
            if first_read < 0:
                first_read = frame.index
            source_end = frame.index + 1
            labels.append(ROUTINE[step].name)
            write(frame.image)
        if show is not None:
            show(Cue(step + 1, ROUTINE[step], phase, phase_end() - t, attempt, face),
                 frame.image)
    raise GuidedError(f"{name}: ended {0.0 if t0 is None else t:.1f} s into the routine, "
                      f"during prompt {step + 1}/{len(ROUTINE)} ({ROUTINE[step].text}); the "
                      f"routine takes at least {schedule.seconds:.1f} s (shorten it with "
                      f"--prompt-seconds and --lead-seconds)")


def build_guided(source: Source, out: str | os.PathLike[str], open_writer: WriterFactory,
                 schedule: Schedule = DEFAULT_SCHEDULE,
                 show: Callable[[Cue, np.ndarray], None] | None = None,
                 say: Callable[[str], None] | None = None, progress: Progress = no_progress,
                 check: Callable[[Path], SelfCheckHook] | None = None) -> GuidedResult:
    """Record the routine from ``source`` and build the model from the recording (module
    docstring).

    Args:
        source: an open camera or video file (``sender.capture.open_source``).
        out: the ``.fwm`` file to write; the preview goes beside it.
        open_writer: opens the temporary recording: ``open_writer(path, width, height,
            rate_hz)``, a context manager whose ``write`` takes (H, W, 3) uint8 RGB.
        schedule, show, say: as for ``record_routine``.
        progress: wraps an iterable to show the build's progress.
        check: makes the self-check hook for the recording's path (``bench.selfcheck``'s
            ``video_check``), or None: no self-check.

    Raises:
        GuidedError: the source ended before the routine did, or the recording cannot give
            a model (``build_model``'s error, naming the source).
    """
    with tempfile.TemporaryDirectory(prefix="facewire-guided-") as folder:
        path = Path(folder) / "guided.mp4"
        with open_writer(path, source.width, source.height, source.rate_hz) as writer:
            recording = record_routine(source, lambda bgr: writer.write(bgr[..., ::-1]),
                                       schedule, show, say, source.name)
        try:
            build = build_model(path, out, name=Path(out).stem, progress=progress,
                                check=None if check is None else check(path),
                                guide=recording.guide(source))
        except FacewireError as exc:  # named by the recording's path: name the source
            text = str(exc).replace(str(path), f"{source.name} (its guided recording)")
            if text == str(exc):
                raise
            raise GuidedError(text) from None
    return GuidedResult(build, recording, source.name)


def overlay(image: np.ndarray, cue: Cue) -> np.ndarray:
    """The frame with its cue drawn on it, for the live page.

    Args:
        image: (H, W, 3) uint8 BGR frame.
        cue: the frame's cue.

    Returns:
        (H, W, 3) uint8 RGB: a dark band along the top with the prompt and, below it, the
        phase and seconds left (red while recording; "no face" when the take's frame has
        none).
    """
    out = image.copy()
    h, w = out.shape[:2]
    scale = max(0.5, w / 640)
    band = int(70 * scale)
    out[:band] = (out[:band] * 0.35).astype(np.uint8)
    cv2.putText(out, f"{cue.step}/{len(ROUTINE)}  {cue.prompt.text}", (int(10 * scale),
                int(28 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, (255, 255, 255),
                max(1, round(2 * scale)), cv2.LINE_AA)
    colour = (60, 60, 255) if cue.phase == RECORD else (200, 200, 200)
    text = f"{cue.phase}  {cue.left_s:.1f} s" + (f" (take {cue.attempt})"
                                                 if cue.attempt > 1 else "")
    if cue.face is False:
        text += "  no face"
    cv2.putText(out, text, (int(10 * scale), int(58 * scale)), cv2.FONT_HERSHEY_SIMPLEX,
                0.7 * scale, colour, max(1, round(2 * scale)), cv2.LINE_AA)
    return np.ascontiguousarray(out[..., ::-1])
