"""Frame sources for the sender: a camera, a video file, or a folder of images.

``open_source(spec)`` reads the ``--source`` option:

- ``camera:N``: OpenCV device N, its frames as the device delivers them (OpenCV's device
  back-ends, V4L2 on Linux, report no rotation). Frames are stamped with
  ``time.monotonic()`` when read, relative to the first frame. A camera cannot be slowed
  down, so pacing drops frames: a frame is kept when it falls in a new slot of the target
  rate (see ``RateLimiter``).
- a folder: its ``.png``, ``.jpg``, ``.jpeg`` and ``.bmp`` files in natural name order
  (``2.png`` before ``10.png``), frame ``i`` at time ``i / rate_hz``. An image that cannot
  be decoded is skipped and counted (``Source.skipped``, names in ``Source.skipped_names``);
  its index stays unused so indices still name files by position. Images must all have the
  first readable image's size (an error names the odd one out).
- anything else: a video file, decoded by ``models.infra.video.read_frames`` with the file's own
  timestamps and rate (``rate_hz`` does not apply to a file; its ``Source.rate_hz`` is the
  container's), upright (its display rotation applied; ``Source.width`` and ``height`` are
  the upright size). A file without a frame, or whose frame count (when the container gives
  one) ``frames`` selects none of, is refused when opened.

Files and folders run as fast as the consumer pulls unless ``pace=True``; then each frame is
released no earlier than its timestamp after the first frame (real time, as a live camera
would deliver it; see ``Pacer``). Cameras are paced unless ``pace=False``.

Every source yields ``models.infra.video.VideoFrame(index, time, image)``: ``image`` is (H, W, 3)
uint8 BGR, ``time`` in seconds (a file's presentation time, else from the start), ``index``
the frame's position in the file, folder, or camera stream (dropped camera frames keep their
numbers).

Intrinsics (``models.geometry.Intrinsics``). Without a calibration they are
``models.geometry.intrinsics_guess`` (the guess the model build makes, so enrollment and
sending agree): ``fx = fy = W`` pixels (a horizontal
field of view of 53 degrees), principal point at the image centre ``((W - 1) / 2,
(H - 1) / 2)`` (pixel centres at integers). ``--focal F`` replaces fx and fy.
``--calib FILE`` reads a JSON object::

    {"fx": 612.3, "fy": 611.8, "cx": 319.2, "cy": 241.7, "width": 640, "height": 480}

fx, fy > 0 and cx, cy in pixels of a ``width`` x ``height`` image, origin top-left, rows
down, the principal point within the image, and the bounds of ``Intrinsics``. When the
source's size differs from the calibrated one with the same aspect ratio (within 1 %), the
intrinsics are scaled (a camera delivering a resized image); a different aspect ratio means
a crop or another camera, and is refused.
"""

from __future__ import annotations

import json
import os
import re
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from facewire.models.geometry import MAX_FOCAL_PX, Intrinsics, intrinsics_guess
from facewire.models.infra.video import VideoError, VideoFrame, read_frames, video_info
from facewire.protocol.errors import FacewireError

__all__ = ["CaptureError", "Source", "VideoFrame", "open_source", "estimate_intrinsics",
           "read_calibration", "scale_intrinsics", "Pacer", "RateLimiter", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
MAX_CALIBRATION_BYTES = 64 * 1024
ASPECT_TOLERANCE = 0.01

Clock = Callable[[], float]
Sleep = Callable[[float], object]  # what it returns is ignored (Event.wait's bool)


class CaptureError(FacewireError, ValueError):
    """A source cannot be opened or read; the message names the source."""


class Pacer:
    """Release frames in real time: frame time ``t`` no earlier than ``origin + t - t0``.

    ``origin`` is the clock when the first frame (time ``t0``) was released. A consumer
    slower than real time is never made to wait more. Lateness up to ``catch_up_s`` is made
    up: the next frames are released at once until the schedule is met again (a live stream
    whose receivers play it on their own clock); beyond it, and always with the default 0,
    the schedule shifts by the lateness: it is not made up later.
    """

    def __init__(self, clock: Clock = time.monotonic, sleep: Sleep = time.sleep,
                 catch_up_s: float = 0.0) -> None:
        self._clock = clock
        self._sleep = sleep
        self._catch_up_s = catch_up_s
        self._origin: float | None = None

    def wait(self, t: float) -> None:
        """Sleep until the frame stamped ``t`` (seconds) is due."""
        now = self._clock()
        if self._origin is None:
            self._origin = now - t
            return
        delay = self._origin + t - now
        if delay > 0:
            self._sleep(delay)
        elif -delay > self._catch_up_s:
            self._origin -= delay  # too late to catch up: shift the schedule, do not rush


class RateLimiter:
    """Keep at most one frame per slot of ``1 / rate_hz`` seconds.

    With ``t0`` the first frame's time, a frame stamped ``t`` falls in slot
    ``floor((t - t0) rate_hz + 1/4)``; it is kept when its slot is later than the last kept
    frame's. A camera at the target rate keeps every frame (a frame may come up to a quarter
    period early or three quarters late; USB cameras deliver late, rarely early); at twice
    the rate, every other one (slot edges fall between its frames, not on them); at a lower
    rate, all of them.
    """

    def __init__(self, rate_hz: float) -> None:
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz: expected a positive number, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self._t0: float | None = None
        self._last = -1

    def keep(self, t: float) -> bool:
        """Whether the frame stamped ``t`` (seconds, non-decreasing) is kept."""
        if self._t0 is None:
            self._t0 = t
        slot = int(np.floor((t - self._t0) * self.rate_hz + 0.25))
        if slot <= self._last:
            return False
        self._last = slot
        return True


class Source:
    """An iterable of ``VideoFrame``s with the size, rate and name of its source.

    Attributes:
        name: the ``--source`` text.
        width, height: frame size, pixels.
        rate_hz: nominal frame rate (the target rate for a camera or folder, the container's
            for a file).
        frames: number of frames when known, else 0.
        live: a camera (frames arrive in real time; pacing drops instead of waiting).
        pace: whether frames are paced (module docstring).
        skipped: frames that could not be read and were left out (folders).
        skipped_names: their file names.
    """

    live = False

    def __init__(self, name: str, width: int, height: int, rate_hz: float, frames: int,
                 pace: bool, clock: Clock, sleep: Sleep) -> None:
        self.name = name
        self.width = width
        self.height = height
        self.rate_hz = rate_hz
        self.frames = frames
        self.pace = pace
        self.skipped = 0
        self.skipped_names: list[str] = []
        self._clock = clock
        self._sleep = sleep

    def __iter__(self) -> Iterator[VideoFrame]:
        pacer = Pacer(self._clock, self._sleep) if self.pace and not self.live else None
        for frame in self._frames():
            if pacer is not None:
                pacer.wait(frame.time)
            yield frame

    def _frames(self) -> Iterator[VideoFrame]:
        raise NotImplementedError

    def close(self) -> None:
        """Release the device or file (no-op for files and folders between iterations)."""

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.name!r}, {self.width}x{self.height}, "
                f"{self.rate_hz:g} Hz)")


class VideoSource(Source):
    """A video file; timestamps and rate from the container."""

    def __init__(self, path: Path, frames: slice, pace: bool, clock: Clock,
                 sleep: Sleep) -> None:
        try:
            info = video_info(path)
            # 0 frames: the container does not say, or it is empty (an interrupted
            # recording); refused here, before a consumer makes its log or binds a socket
            if not info.frames and next(read_frames(path, slice(0, 1)), None) is None:
                raise CaptureError(f"{path}: holds no frames")
        except VideoError as exc:
            raise CaptureError(str(exc)) from None
        count = len(range(*frames.indices(info.frames))) if info.frames else 0
        if info.frames and not count:
            raise CaptureError(f"{path}: --frames selects none of its {info.frames} frames")
        super().__init__(str(path), info.width, info.height, info.rate_hz, count, pace,
                         clock, sleep)
        self._path = path
        self._slice = frames

    def _frames(self) -> Iterator[VideoFrame]:
        try:
            yield from read_frames(self._path, self._slice)
        except VideoError as exc:
            raise CaptureError(str(exc)) from None


class FolderSource(Source):
    """A folder of images in natural name order; frame ``i`` at ``i / rate_hz``."""

    def __init__(self, path: Path, rate_hz: float, frames: slice, pace: bool, clock: Clock,
                 sleep: Sleep) -> None:
        files = sorted((p for p in path.iterdir()
                        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                       key=_natural_key)
        if not files:
            raise CaptureError(f"{path}: no images in this folder (expected "
                               f"{', '.join(IMAGE_SUFFIXES)} files)")
        indexed = list(enumerate(files))[frames]
        if not indexed:
            raise CaptureError(f"{path}: --frames selects none of its {len(files)} images")
        self._files = indexed
        first = None
        bad: list[str] = []
        for _, file in indexed:
            first = cv2.imread(str(file), cv2.IMREAD_COLOR)
            if first is not None:
                break
            bad.append(file.name)
        if first is None:
            raise CaptureError(f"{path}: none of its {len(indexed)} images can be read")
        height, width = first.shape[:2]
        super().__init__(str(path), width, height, rate_hz, len(indexed), pace, clock, sleep)

    def _frames(self) -> Iterator[VideoFrame]:
        self.skipped, self.skipped_names = 0, []
        for index, file in self._files:
            image = cv2.imread(str(file), cv2.IMREAD_COLOR)
            if image is None:
                self.skipped += 1
                self.skipped_names.append(file.name)
                continue
            if image.shape[:2] != (self.height, self.width):
                raise CaptureError(
                    f"{file}: image is {image.shape[1]}x{image.shape[0]}, the folder's "
                    f"first image is {self.width}x{self.height}; all images must match")
            yield VideoFrame(index, index / self.rate_hz, image)


class CameraSource(Source):
    """An OpenCV capture device; frames stamped with the monotonic clock when read.

    Attributes:
        origin_s: the clock's reading at frame time 0 (the first frame read), None before.
    """

    live = True

    def __init__(self, name: str, device: int, rate_hz: float, pace: bool, clock: Clock,
                 sleep: Sleep) -> None:
        missing = (f"{name}: no camera could be opened (is one connected? try "
                   f"camera:{device + 1})")
        # On Linux a device is a /dev/videoN node; checking it first avoids a slow probe of
        # every capture backend for a camera that is not there.
        if sys.platform.startswith("linux") and not Path(f"/dev/video{device}").exists():
            raise CaptureError(missing)
        capture = cv2.VideoCapture(device)
        if not capture.isOpened():
            capture.release()
            raise CaptureError(missing)
        capture.set(cv2.CAP_PROP_FPS, rate_hz)
        ok, image = capture.read()
        if not ok or image is None:
            capture.release()
            raise CaptureError(f"{name}: the camera opened but delivers no frames")
        height, width = image.shape[:2]
        super().__init__(name, width, height, rate_hz, 0, pace, clock, sleep)
        self._capture = capture
        self._first: np.ndarray | None = image
        self._limiter = RateLimiter(rate_hz) if pace else None
        self.origin_s: float | None = None
        self._index = 0

    def _frames(self) -> Iterator[VideoFrame]:
        while True:
            if self._first is not None:
                image, self._first = self._first, None
            else:
                ok, image = self._capture.read()
                if not ok or image is None:
                    raise CaptureError(f"{self.name}: the camera stopped delivering frames")
            now = self._clock()
            if self.origin_s is None:
                self.origin_s = now
            t = now - self.origin_s
            index = self._index
            self._index += 1
            if self._limiter is None or self._limiter.keep(t):
                yield VideoFrame(index, t, _as_bgr(image, self.name))

    def close(self) -> None:
        self._capture.release()


def open_source(spec: str, rate_hz: float = 30.0, pace: bool | None = None,
                frames: slice = slice(0, None), *, clock: Clock = time.monotonic,
                sleep: Sleep = time.sleep) -> Source:
    """Open ``camera:N``, a video file, or a folder of images (module docstring).

    Args:
        spec: the ``--source`` text.
        rate_hz: target rate of a camera, frame rate of a folder (> 0, <= 1000).
        pace: release frames in real time; None means yes for a camera, no otherwise.
        frames: which frames of a file or folder (``models.infra.video.frame_range("A:B")``), by
            index; a camera ignores it.
        clock, sleep: time functions (seconds), replaceable in tests.

    Raises:
        CaptureError: no such camera, file or folder; unreadable file; empty folder or
            video, or none of its frames selected.
    """
    if not (isinstance(rate_hz, (int, float)) and np.isfinite(rate_hz) and 0 < rate_hz <= 1000):
        raise ValueError(f"rate_hz: expected a number in (0, 1000], got {rate_hz!r}")
    if frames.step not in (None, 1):
        raise ValueError("frames: step must be 1")
    if spec.startswith("camera:"):
        match = re.fullmatch(r"camera:(\d{1,3})", spec)
        if match is None:
            raise CaptureError(f"{spec}: expected camera:N with N a device number, e.g. camera:0")
        return CameraSource(spec, int(match.group(1)), float(rate_hz),
                            True if pace is None else pace, clock, sleep)
    path = Path(spec)
    if path.is_dir():
        return FolderSource(path, float(rate_hz), frames, bool(pace), clock, sleep)
    if not path.exists():
        raise CaptureError(f"{spec}: no such file or folder (or use camera:N for a camera)")
    return VideoSource(path, frames, bool(pace), clock, sleep)


def estimate_intrinsics(width: int, height: int, focal: float | None = None) -> Intrinsics:
    """Pinhole intrinsics of an uncalibrated camera (guess in the module docstring).

    Args:
        width, height: image size, pixels.
        focal: focal length in pixels (``--focal``), for fx and fy; None for the guess.

    Raises:
        ValueError: a size or focal length out of range (naming it).
    """
    guess = intrinsics_guess(width, height)
    if focal is None:
        return guess
    if not (np.isfinite(focal) and 0 < focal < MAX_FOCAL_PX):
        raise ValueError(f"--focal: expected a focal length in pixels in (0, {MAX_FOCAL_PX:g}), "
                         f"got {focal}")
    return replace(guess, fx=float(focal), fy=float(focal))


def read_calibration(path: str | os.PathLike[str]) -> Intrinsics:
    """Read a calibration JSON file (format in the module docstring).

    Raises:
        CaptureError: missing, too large, not JSON, or a field missing, unknown, or invalid
            (the message names the file and the field).
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: no such calibration file")
    if path.stat().st_size > MAX_CALIBRATION_BYTES:
        raise CaptureError(f"{path}: too large for a calibration file "
                           f"(> {MAX_CALIBRATION_BYTES} bytes)")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{path}: not a JSON calibration file: {exc}") from None
    if not isinstance(doc, dict):
        raise CaptureError(f"{path}: expected a JSON object with fx, fy, cx, cy, width, height")
    want = ("fx", "fy", "cx", "cy", "width", "height")
    unknown = sorted(set(doc) - set(want))
    if unknown:
        raise CaptureError(f"{path}: unknown field {unknown[0]!r} (expected {', '.join(want)})")
    missing = [name for name in want if name not in doc]
    if missing:
        raise CaptureError(f"{path}: field {missing[0]!r} is missing")
    try:
        camera = Intrinsics(**{name: doc[name] for name in want})
    except ValueError as exc:
        raise CaptureError(f"{path}: field {exc}") from None
    for name, size in (("cx", "width"), ("cy", "height")):
        if not 0 <= getattr(camera, name) <= getattr(camera, size):
            raise CaptureError(f"{path}: field {name}: {getattr(camera, name)} lies outside the "
                               f"image (0 .. {size} = {getattr(camera, size)})")
    return camera


def scale_intrinsics(camera: Intrinsics, width: int, height: int, name: str = "calibration"
                     ) -> Intrinsics:
    """The intrinsics of ``camera`` for an image resized to ``width`` x ``height``
    (``Intrinsics.resized``).

    Raises:
        CaptureError: the aspect ratios differ by more than 1 % (a crop, not a resize).
    """
    sx, sy = width / camera.width, height / camera.height
    if abs(sx / sy - 1.0) > ASPECT_TOLERANCE:
        raise CaptureError(
            f"{name}: calibrated for {camera.width}x{camera.height}, the source is "
            f"{width}x{height}; a different aspect ratio cannot be scaled (recalibrate)")
    if (width, height) == (camera.width, camera.height):
        return camera
    return camera.resized(width, height)


def _natural_key(path: Path) -> list[object]:
    """Sort key comparing runs of digits as numbers: ``2.png`` before ``10.png``."""
    return [(0, int(part), "") if part.isdigit() else (1, 0, part.lower())
            for part in re.split(r"(\d+)", path.name)]


def _as_bgr(image: np.ndarray, name: str) -> np.ndarray:
    """A camera frame as (H, W, 3) uint8 BGR (some devices deliver gray or BGRA)."""
    if image.dtype != np.uint8:
        raise CaptureError(f"{name}: the camera delivers {image.dtype} frames, expected uint8")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image
