"""Reading video files frame by frame with PyAV (FFmpeg): any container and codec it knows.

Frames come out as (H, W, 3) uint8 BGR arrays (OpenCV's order, which dlib and cv2 expect),
upright, with their index in the file and their presentation time in seconds. ``frame_range``
parses the ``--frames A:B`` option (Python slice semantics, B exclusive, either side optional).

Rotation. A phone stores its frames as the sensor sees them (a portrait video as a sideways
landscape image) and says how to show them: the stream's display matrix (ISO/IEC 14496-12
``tkhd`` matrix; FFmpeg attaches it to every decoded frame, PyAV's ``VideoFrame.rotation``, the
angle in degrees by which it turns the stored image counter-clockwise, in [-180, 180]) or, in
files from older tools, a ``rotate`` stream tag (any case: Matroska writes ``ROTATE``; degrees
clockwise, ``rotate = -rotation``).
The display matrix wins when both are there. A file's rotation is read once, from its first
frame, and applied to every frame: ``upright = rot90(stored, k)`` (counter-clockwise quarter
turns, ``k = rotation / 90 mod 4``, ``cv2.rotate``), so a 90 or 270 degree file's frames are
(W, H) of the (H, W) stored. ``video_info`` reports the upright size. A rotation that is not a
multiple of 90 degrees is refused (``VideoError`` naming the file and the angle). A matrix's
mirroring (a flip) is not read.

Decoding once (``decoded_once``). A model build reads the same frames in several passes
(tracking, the base texture's views, the appearance step, the layers' frames, the
self-check), and decoding is a large share of its time. Inside ``with decoded_once(path)``,
``read_frames`` keeps the frames it decodes from that file in memory, up to
``CACHE_BYTES`` of images (the first frames decoded; past the budget frames are decoded
each time, as without it), and serves a later range from memory when it holds all of it.
The kept images are read-only, since every reader shares them.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import av
import cv2
import numpy as np

from facewire.protocol.errors import FacewireError

CACHE_BYTES = 1024**3

# cv2.rotate's code for k counter-clockwise quarter turns (k = 1, 2, 3)
_QUARTER_TURNS = {1: cv2.ROTATE_90_COUNTERCLOCKWISE, 2: cv2.ROTATE_180,
                  3: cv2.ROTATE_90_CLOCKWISE}


class VideoError(FacewireError, ValueError):
    """A video cannot be opened or decoded; the message names the file."""


@dataclass(frozen=True)
class VideoFrame:
    """One decoded frame: index in the file, time in seconds, (H, W, 3) uint8 BGR image."""

    index: int
    time: float
    image: np.ndarray


@dataclass(frozen=True)
class VideoInfo:
    """What the container says: the upright frames' size, nominal rate, frame count (0 when
    unknown) and the rotation applied to stand them upright (degrees counter-clockwise: 0, 90,
    180 or 270; module docstring)."""

    width: int
    height: int
    rate_hz: float
    frames: int
    rotation: int


def frame_range(text: str | None) -> slice:
    """Parse ``A:B`` (either side may be empty) into a slice of frame indices.

    Raises:
        ValueError: not of the form A:B with non-negative integers and A < B.
    """
    if text is None:
        return slice(0, None)
    start, sep, stop = text.partition(":")
    try:
        if not sep:
            raise ValueError
        a = int(start) if start.strip() else 0
        b = int(stop) if stop.strip() else None
    except ValueError:
        raise ValueError(f"--frames {text!r}: expected A:B, e.g. 0:180") from None
    if a < 0 or (b is not None and b <= a):
        raise ValueError(f"--frames {text!r}: need 0 <= A < B")
    return slice(a, b)


def range_text(frames: slice) -> str:
    """A frame range as ``--frames`` writes it: ``A:B``, or ``A:`` when it runs to the end."""
    return f"{frames.start or 0}:{'' if frames.stop is None else frames.stop}"


def frames_in_range(frames: slice, count: int) -> int | None:
    """How many of a video's ``count`` frames the range selects; None when the count is
    unknown (0: the container does not say)."""
    if not count:
        return None
    stop = count if frames.stop is None else min(frames.stop, count)
    return max(stop - (frames.start or 0), 0)


def video_info(path: str | os.PathLike[str]) -> VideoInfo:
    """Upright size, rate, frame count and rotation of a video file (decodes its first frame,
    which carries the display matrix).

    Raises:
        VideoError: as ``read_frames``; a rotation that is not a multiple of 90 degrees.
    """
    path = Path(path)
    with _open(path) as container:
        stream = container.streams.video[0]
        rate = float(stream.average_rate or stream.guessed_rate or 30)
        try:
            first = next(container.decode(stream), None)
        except av.FFmpegError as exc:
            raise VideoError(f"{path}: cannot decode its first frame: {exc}") from None
        turns = quarter_turns(path, 0 if first is None else first.rotation,
                              _rotate_tag(stream))
        width, height = stream.codec_context.width, stream.codec_context.height
        if turns % 2:
            width, height = height, width
        return VideoInfo(width, height, rate, int(stream.frames or 0), 90 * turns)


def quarter_turns(path: str | os.PathLike[str], rotation: float, rotate_tag: str | None = None
                  ) -> int:
    """The counter-clockwise quarter turns k (0..3) that stand a file's frames upright.

    Args:
        path: the file, for the error message.
        rotation: the display matrix's angle, degrees counter-clockwise (``VideoFrame.rotation``;
            0 when the file has none).
        rotate_tag: the stream's ``rotate`` tag (degrees clockwise), used when ``rotation``
            is 0; None when absent.

    Raises:
        VideoError: the angle (or the tag) is not a multiple of 90 degrees.
    """
    source, degrees = "display matrix", float(rotation)
    if not degrees and rotate_tag is not None:
        source = "rotate tag"
        try:
            degrees = -float(rotate_tag)
        except ValueError:
            degrees = float("nan")
    if not (np.isfinite(degrees) and degrees % 90 == 0):
        shown = repr(rotate_tag) if source == "rotate tag" else f"{degrees:g} degrees"
        raise VideoError(f"{path}: rotation {shown} ({source}) is not a multiple of 90 degrees; "
                         f"frames are stood upright by quarter turns only")
    return int(degrees // 90) % 4


def _rotate_tag(stream: av.video.stream.VideoStream) -> str | None:
    """The stream's ``rotate`` tag, its key in any case; None when absent."""
    return next((value for key, value in stream.metadata.items() if key.lower() == "rotate"),
                None)


def upright(image: np.ndarray, turns: int) -> np.ndarray:
    """``image`` (H, W, C) turned ``turns`` quarter turns counter-clockwise (0..3): itself for
    0, else a new (W, H, C) array (odd turns) or (H, W, C) one (a half turn)."""
    return image if not turns else cv2.rotate(image, _QUARTER_TURNS[turns])


@dataclass
class _Cache:
    """The frames of one file decoded so far, and where the file ends once known."""

    frames: dict[int, VideoFrame] = field(default_factory=dict)
    used: int = 0
    end: int | None = None

    def serves(self, frames: slice) -> range | None:
        """The indices of ``frames`` when every one of them is held, else None."""
        stop = frames.stop if self.end is None else min(frames.stop or self.end, self.end)
        if stop is None:
            return None
        wanted = range(frames.start or 0, stop)
        return wanted if all(i in self.frames for i in wanted) else None

    def keep(self, frame: VideoFrame) -> None:
        if frame.index not in self.frames and self.used + frame.image.nbytes <= CACHE_BYTES:
            frame.image.flags.writeable = False
            self.frames[frame.index] = frame
            self.used += frame.image.nbytes


_CACHES: dict[Path, _Cache] = {}


@contextmanager
def decoded_once(path: str | os.PathLike[str]) -> Iterator[None]:
    """Within the block, ``read_frames`` of ``path`` decodes each frame once (module
    docstring)."""
    key = Path(path).resolve()
    if key in _CACHES:  # already inside one for this file
        yield
        return
    _CACHES[key] = _Cache()
    try:
        yield
    finally:
        del _CACHES[key]


def read_frames(path: str | os.PathLike[str], frames: slice = slice(0, None)
                ) -> Iterator[VideoFrame]:
    """Decode the frames of a file whose index falls in ``frames`` (a step of 1); from memory
    inside ``decoded_once`` when it holds them all.

    Raises:
        VideoError: the file is missing, not a video, or undecodable (a corrupt frame: the
            message says how many frames were decoded before it).
    """
    cache = _CACHES.get(Path(path).resolve())
    if cache is None:
        yield from _decode(Path(path), frames)
        return
    held = cache.serves(frames)
    if held is not None:
        yield from (cache.frames[i] for i in held)
        return
    last = (frames.start or 0) - 1
    for frame in _decode(Path(path), frames):
        cache.keep(frame)
        last = frame.index
        yield frame
    if frames.stop is None or last + 1 < frames.stop:  # the file ended first
        cache.end = last + 1


def _decode(path: Path, frames: slice) -> Iterator[VideoFrame]:
    with _open(path) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        base = float(stream.time_base) if stream.time_base else 0.0
        rate = float(stream.average_rate or stream.guessed_rate or 30)
        index, turns = -1, 0
        try:
            for index, frame in enumerate(container.decode(stream)):
                if frames.stop is not None and index >= frames.stop:
                    break
                if not index:
                    turns = quarter_turns(path, frame.rotation, _rotate_tag(stream))
                if index < frames.start:
                    continue
                time = frame.pts * base if frame.pts is not None and base else index / rate
                yield VideoFrame(index, time, upright(frame.to_ndarray(format="bgr24"), turns))
        except av.FFmpegError as exc:
            raise VideoError(f"{path}: cannot decode it after {index + 1} frames: {exc}") from None


def _open(path: Path) -> av.container.InputContainer:
    if not path.is_file():
        raise VideoError(f"{path}: no such video file")
    try:
        container = av.open(str(path))
    except av.FFmpegError as exc:
        raise VideoError(f"{path}: not a readable video: {exc}") from None
    if not container.streams.video:
        container.close()
        raise VideoError(f"{path}: has no video stream")
    return container
