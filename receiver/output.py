"""Where rendered frames go: an H.264 ``.mp4`` file, a folder of PNG images, side by side.

Both writers take frames as (H, W, 3) uint8 RGB arrays (the renderer's order) through the
same interface: ``write(rgb)``, ``hold()``, ``close()``, and ``with`` (which closes). Frame
``i`` of the file is the ``i``-th call of ``write`` or ``hold``; ``hold`` makes it the frame
before it again (a live picture that repeats a frame: ``receiver.receiver``'s ``keep_up``).

Threading. Encoding runs on one background thread per writer, fed by a bounded queue of
``QUEUE_FRAMES`` = 8 frames, so the render loop pays only for a copy of the frame (0.9 MB at
640x480; the caller may reuse its buffer at once). When the queue is full, ``write`` blocks
until the encoder has taken a frame: frames are never dropped, and the file holds every
frame written, in order (at 640x480, preset fast, the encoder keeps up with about 100
frames/s on the 2-core test machine; ``write`` took 0.3 ms median at 30 Hz; at 1080x1920,
17). ``backlog`` is how many frames are queued and not yet encoded: a live caller that must
not block holds instead of writing while it is high. If the
thread fails (disk full, folder removed), it keeps taking frames off the queue and
discarding them, so ``write`` never hangs; the next ``write`` and ``close`` raise
``OutputError`` naming the file, with the thread's exception as its cause. ``close``
flushes the encoder, joins the thread and closes the file; a writer must be closed (an
unclosed ``.mp4`` has no index and does not play). Writing after ``close`` raises
``ValueError``.

``VideoWriter``: MP4 container (whatever the file's suffix), H.264 by libx264, yuv420p
(4:2:0, BT.601 limited range, as FFmpeg converts RGB by default), constant quality
``crf`` 18 (visually near lossless) at preset ``fast``, x264's frame threading (PyAV would
otherwise pick slice threads, which cost x264 compression). A frame's presentation time is
its index over ``rate_hz``. A ``hold`` is not encoded: the frame before stays on screen
until the next frame's presentation time (an MP4 sample lasts until the next one), so
holding costs the encoder nothing and the file keeps its timeline with fewer frames in it
(variable frame rate); a file that ends on holds gets its last frame again at the last
index, so that it lasts to its end. With ``sound=True`` the file also gets a sound track:
48 kHz mono Opus at ``SOUND_BITRATE`` (FFmpeg's libopus; MP4 holds Opus, RFC 7845's mapping), fed
by ``write_sound(pcm, start_s)`` in the frames' order on the same queue: the first call
places its samples at ``start_s`` seconds of the file's timeline (the video's frame 0 at 0),
every later call's samples follow the last one's without a gap, so the caller keeps sound and
frames in sync by where it starts the sound. Sound is cut into Opus's 20-ms frames; a last
partial frame is padded with silence. 4:2:0 needs an even width and height: an odd one is padded by
repeating the last column or row, so the file is then one pixel wider or taller. No
frames written: ``close`` raises and no file is left.

``FrameFolderWriter``: ``frame_000000.png``, ``frame_000001.png``, ... (8-bit RGB PNG,
lossless, zlib level 1) in a folder that is created if missing; a path that exists and is
not a folder, or a folder already holding ``frame_*.png`` files (two runs would mix), is
refused. A ``hold`` writes the frame before again, under its own number. Every frame must
have the first frame's size.

``side_by_side``: two images scaled to a common height (by default the larger of the two;
area averaging when shrinking, bilinear when enlarging; each width scaled in proportion and
rounded) and placed left | right: the "input | reconstruction" evaluation video.
"""

from __future__ import annotations

import math
import os
import queue
import threading
import time
from collections import deque
from fractions import Fraction
from pathlib import Path
from typing import NamedTuple, Self

import av
import cv2
import numpy as np

from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import FRAME_SAMPLES, SAMPLE_RATE

QUEUE_FRAMES = 8
SOUND_BITRATE = 64_000
TIMED_FRAMES = 1000
CRF = 18
PRESET = "fast"
FRAME_PATTERN = "frame_{:06d}.png"

_STOP = None


class _Frame(NamedTuple):
    at: int  # its index in the file
    rgb: np.ndarray


class _Sound(NamedTuple):
    start_s: float | None
    pcm: np.ndarray


class OutputError(FacewireError, OSError):
    """A frame file or folder cannot be written; the message names it."""


class _QueuedWriter:
    """The writers' common part: validation, the bounded queue and the encoding thread.

    Subclasses implement ``_consume(index, rgb)`` (encode one frame) and ``_finish()``
    (flush and close the file); both run on the writer's thread only; ``_held`` (``hold``)
    queues the frame before again, unless a subclass does better. ``consume_seconds`` holds
    the wall time of the last ``TIMED_FRAMES`` frames' ``_consume`` (``bench speed``).
    """

    def __init__(self, target: Path, size: tuple[int, int] | None) -> None:
        self.target = target
        self._size = size  # (height, width); None until the first frame (folder writer)
        self._count = 0  # frames written or held: the next frame's index
        self._queued = self._taken = 0  # frames put on the queue, and encoded (or discarded)
        self._last: np.ndarray | None = None  # the last frame queued
        self._queue: queue.Queue[_Frame | _Sound | None] = queue.Queue(maxsize=QUEUE_FRAMES)
        self._error: BaseException | None = None
        self._closed = False
        self.consume_seconds: deque[float] = deque(maxlen=TIMED_FRAMES)
        self._thread = threading.Thread(target=self._run, name=f"output {target.name}",
                                        daemon=True)
        self._thread.start()

    @property
    def frames(self) -> int:
        """How many frames the file has: ``write``'s and ``hold``'s."""
        return self._count

    @property
    def backlog(self) -> int:
        """How many frames are queued and not yet encoded, at most ``QUEUE_FRAMES`` + 1."""
        return self._queued - self._taken

    def write(self, rgb: np.ndarray) -> None:
        """Queue one frame for encoding (a copy is taken); blocks while the queue is full.

        Args:
            rgb: (H, W, 3) uint8 RGB, the writer's size.

        Raises:
            ValueError: the writer is closed, or the frame is not of the expected kind.
            OutputError: the encoding thread has failed (names the file).
        """
        if self._closed:
            raise ValueError(f"{self.target}: write after close")
        self._raise_thread_error()
        if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 \
                or rgb.shape[2] != 3:
            got = rgb.shape if isinstance(rgb, np.ndarray) else type(rgb).__name__
            raise ValueError(f"{self.target}: frame: expected (H, W, 3) uint8 RGB, got {got}")
        if self._size is None:
            self._size = rgb.shape[:2]
        if rgb.shape[:2] != self._size:
            raise ValueError(f"{self.target}: frame {self._count}: expected "
                             f"{self._size[1]}x{self._size[0]}, got {rgb.shape[1]}x{rgb.shape[0]}")
        self._last = np.array(rgb, copy=True)
        self._put(_Frame(self._count, self._last))
        self._count += 1

    def hold(self) -> None:
        """The next frame is the frame before again (module docstring); no frame yet: no
        effect.

        Raises:
            ValueError: the writer is closed.
            OutputError: the encoding thread has failed (names the file).
        """
        if self._closed:
            raise ValueError(f"{self.target}: hold after close")
        self._raise_thread_error()
        if self._last is None:
            return
        self._held(self._last)
        self._count += 1

    def _held(self, last: np.ndarray) -> None:
        """Frame ``frames`` is ``last`` again: queued again, unless a subclass does better."""
        self._put(_Frame(self._count, last))

    def _put(self, frame: _Frame) -> None:
        self._queued += 1
        self._queue.put(frame)

    def close(self) -> None:
        """Flush what is queued, finish the file and join the thread (again: no effect).

        Raises:
            OutputError: the thread failed at any point (names the file).
        """
        if self._closed:
            return
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join()
        self._raise_thread_error()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
            return
        try:
            self.close()
        except OutputError:
            pass  # the exception already on its way out says more

    def _raise_thread_error(self) -> None:
        error = self._error
        if error is not None:
            text = str(error) if isinstance(error, OutputError) else f"{self.target}: {error}"
            raise OutputError(text) from error

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                break
            if isinstance(item, _Sound):  # VideoWriter.write_sound
                if self._error is None:
                    try:
                        self._consume_sound(*item)
                    except Exception as exc:  # noqa: BLE001 - reaches write/close
                        self._error = exc
                continue
            if self._error is None:
                tick = time.perf_counter()
                try:
                    self._consume(*item)
                except Exception as exc:  # noqa: BLE001 - any failure reaches write/close
                    self._error = exc
                self.consume_seconds.append(time.perf_counter() - tick)
            self._taken += 1
        try:
            self._finish(failed=self._error is not None)
        except Exception as exc:  # noqa: BLE001 - reported by close()
            if self._error is None:
                self._error = exc

    def _consume(self, index: int, rgb: np.ndarray) -> None:
        raise NotImplementedError

    def _consume_sound(self, start_s: float | None, pcm: np.ndarray) -> None:
        raise NotImplementedError

    def _finish(self, failed: bool) -> None:
        raise NotImplementedError


class VideoWriter(_QueuedWriter):
    """An H.264 ``.mp4`` file written on a background thread (see the module docstring).

    Args:
        path: the file to write (replaced if it exists); its folder must exist.
        width, height: frame size, pixels (>= 1).
        rate_hz: frame rate, > 0 (stored as a fraction, e.g. 29.97 as 2997/100).
        crf: x264 constant rate factor, 0 (lossless) to 51.
        preset: x264 preset name.
        sound: add a sound track (``write_sound``).

    Raises:
        OutputError: the file cannot be created.
        ValueError: bad size, rate, crf or preset.
    """

    def __init__(self, path: str | os.PathLike[str], width: int, height: int,
                 rate_hz: float, crf: int = CRF, preset: str = PRESET,
                 sound: bool = False) -> None:
        path = Path(path)
        if width < 1 or height < 1:
            raise ValueError(f"{path}: frame size: expected positive, got {width}x{height}")
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"{path}: rate_hz: expected > 0, got {rate_hz}")
        if not 0 <= crf <= 51:
            raise ValueError(f"{path}: crf: expected 0..51, got {crf}")
        if path.is_dir():
            raise OutputError(f"{path}: is a folder, not a video file")
        rate = Fraction(rate_hz).limit_denominator(1001)
        self._pad = (height % 2, width % 2)
        try:
            self._container = av.open(str(path), "w", format="mp4")
            self._stream = self._container.add_stream(
                "libx264", rate=rate, time_base=1 / rate,
                options={"crf": str(crf), "preset": preset})
            self._stream.width = width + self._pad[1]
            self._stream.height = height + self._pad[0]
            self._stream.pix_fmt = "yuv420p"
            self._stream.codec_context.thread_type = "FRAME"
            self._stream.codec_context.open()
            self._sound = self._container.add_stream(
                "libopus", rate=SAMPLE_RATE, layout="mono") if sound else None
            if self._sound is not None:
                self._sound.bit_rate = SOUND_BITRATE
                self._sound.codec_context.open()
        except (av.FFmpegError, ValueError) as exc:
            raise ValueError(f"{path}: cannot set up H.264 (crf {crf}, preset {preset!r}): "
                             f"{exc}") from None
        try:
            path.open("wb").close()  # PyAV itself opens the file only at the first packet
        except OSError as exc:
            raise OutputError(f"{path}: cannot create: {exc.strerror or exc}") from None
        self._time_base = 1 / rate
        self._held_at: int | None = None  # the last hold's index
        self._sound_at: int | None = None  # the next sound sample's place, in samples
        self._sound_rest = np.zeros(0, np.int16)
        super().__init__(path, (height, width))

    def _held(self, last: np.ndarray) -> None:
        self._held_at = self._count  # not encoded: the frame before lasts (module docstring)

    def close(self) -> None:
        """As ``_QueuedWriter.close``; a file that ends on holds gets its last frame again at
        the last index (module docstring)."""
        if not self._closed and self._last is not None and self._held_at == self._count - 1:
            self._put(_Frame(self._held_at, self._last))
        super().close()

    def write_sound(self, pcm: np.ndarray, start_s: float | None = None) -> None:
        """Queue sound for the file's sound track (module docstring).

        Args:
            pcm: (N,) int16, 48 kHz mono.
            start_s: where the first call's samples begin on the file's timeline, s (>= 0;
                None: 0); later calls' are ignored (their samples follow on).

        Raises:
            ValueError: no sound track, closed, or not (N,) int16.
            OutputError: the encoding thread has failed (names the file).
        """
        if self._sound is None or self._closed:
            raise ValueError(f"{self.target}: " + ("write after close" if self._closed else
                                                   "made without a sound track"))
        self._raise_thread_error()
        if not isinstance(pcm, np.ndarray) or pcm.dtype != np.int16 or pcm.ndim != 1:
            raise ValueError(f"{self.target}: sound: expected (N,) int16")
        if start_s is not None and not (math.isfinite(start_s) and start_s >= 0):
            raise ValueError(f"{self.target}: sound start: expected >= 0 s, got {start_s}")
        self._queue.put(_Sound(start_s, pcm.copy()))

    def _consume_sound(self, start_s: float | None, pcm: np.ndarray) -> None:
        assert self._sound is not None  # write_sound checked
        if self._sound_at is None:
            self._sound_at = round((start_s or 0.0) * SAMPLE_RATE)
        pcm = np.concatenate([self._sound_rest, pcm])
        whole = len(pcm) // FRAME_SAMPLES * FRAME_SAMPLES
        self._sound_rest = pcm[whole:]
        for k in range(0, whole, FRAME_SAMPLES):
            self._encode_sound(pcm[k:k + FRAME_SAMPLES])

    def _encode_sound(self, pcm: np.ndarray | None) -> None:
        assert self._sound is not None and self._sound_at is not None
        frame = None
        if pcm is not None:
            frame = av.AudioFrame.from_ndarray(pcm.reshape(1, -1), format="s16", layout="mono")
            frame.sample_rate, frame.pts = SAMPLE_RATE, self._sound_at
            frame.time_base = Fraction(1, SAMPLE_RATE)
            self._sound_at += len(pcm)
        for packet in self._sound.encode(frame):
            self._container.mux(packet)

    def _consume(self, index: int, rgb: np.ndarray) -> None:
        if any(self._pad):
            rgb = np.pad(rgb, ((0, self._pad[0]), (0, self._pad[1]), (0, 0)), mode="edge")
        frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
        frame.pts, frame.time_base = index, self._time_base
        for packet in self._stream.encode(frame):
            self._container.mux(packet)

    def _finish(self, failed: bool) -> None:
        try:
            if not failed and self.frames:
                for packet in self._stream.encode():
                    self._container.mux(packet)
                if self._sound is not None and self._sound_at is not None:
                    if len(self._sound_rest):
                        self._encode_sound(np.pad(self._sound_rest,
                                                  (0, FRAME_SAMPLES - len(self._sound_rest))))
                    self._encode_sound(None)
        finally:
            try:
                self._container.close()
            except (av.FFmpegError, OSError):
                if not failed and self.frames:
                    raise
        if not self.frames:
            self.target.unlink(missing_ok=True)
            raise OutputError(f"{self.target}: no frames were written; no file made")


class FrameFolderWriter(_QueuedWriter):
    """A PNG sequence ``frame_000000.png``... written on a background thread.

    Args:
        folder: the folder to write into; created (with its parents) if missing.

    Raises:
        OutputError: the path exists and is not a folder, already holds ``frame_*.png``
            files, or cannot be created.
    """

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        folder = Path(folder)
        if folder.exists() and not folder.is_dir():
            raise OutputError(f"{folder}: exists and is not a folder")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{folder}: cannot create folder: {exc.strerror or exc}") from None
        if next(folder.glob("frame_*.png"), None) is not None:
            raise OutputError(f"{folder}: already holds frame_*.png files; "
                              "choose an empty or new folder")
        super().__init__(folder, None)

    def _consume(self, index: int, rgb: np.ndarray) -> None:
        path = self.target / FRAME_PATTERN.format(index)
        if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OutputError(f"{path}: cannot write PNG")

    def _finish(self, failed: bool) -> None:
        return


def side_by_side(left: np.ndarray, right: np.ndarray, height: int | None = None
                 ) -> np.ndarray:
    """Two RGB images at one height, left | right.

    Args:
        left: (H1, W1, 3) uint8.
        right: (H2, W2, 3) uint8.
        height: the common height, pixels; default ``max(H1, H2)``.

    Returns:
        (height, W1' + W2', 3) uint8, ``Wi' = max(round(Wi * height / Hi), 1)``.
    """
    for name, image in (("left", left), ("right", right)):
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 \
                or image.shape[2] != 3 or 0 in image.shape:
            got = image.shape if isinstance(image, np.ndarray) else type(image).__name__
            raise ValueError(f"{name}: expected a non-empty (H, W, 3) uint8 image, got {got}")
    if height is None:
        height = max(left.shape[0], right.shape[0])
    if height < 1:
        raise ValueError(f"height: expected >= 1, got {height}")
    return np.concatenate([_to_height(left, height), _to_height(right, height)], axis=1)


def _to_height(image: np.ndarray, height: int) -> np.ndarray:
    h, w = image.shape[:2]
    if h == height:
        return image
    width = max(round(w * height / h), 1)
    interpolation = cv2.INTER_AREA if height < h else cv2.INTER_LINEAR
    return cv2.resize(image, (width, height), interpolation=interpolation)
