"""``facewire demo``: the whole system on one machine, with no camera and no files.

Steps (``demo``):

1. Performer. Without ``--source``, ``facewire.performer.perform`` turns matplotlib's
   public-domain portrait into a video of a scripted performance (head turns, brow raises,
   mouth opening, blinks; what is synthetic is said there): ``demo-performer.mp4``. With
   ``--source VIDEO`` that video is the performer.
2. Model. ``sender.enroll.build.build_model`` (what ``facewire model build`` does: geometry,
   texture and appearance regions) on the performer's first ``ENROLL_S`` seconds:
   ``demo.fwm`` and its preview ``demo.preview.png``. The built-in script shows each
   movement once in those seconds, so enrollment sees brows up, an open mouth, a blink and
   head turns.
3. Stream (``loopback``). What ``facewire send`` and ``facewire receive`` run, over ZeroMQ
   on 127.0.0.1, in two processes as on two hosts: ``sender.sender.send``, in a process of
   its own (spawned), sends the frames after them (in real time, at the video's rate),
   bound to a free pair of ports, with ``demo.fwm``, and records its packets to
   ``demo.fwlog`` (``facewire replay`` / ``bench bandwidth`` read it);
   ``receiver.receiver.receive``, in this process on a thread of its own (its renderer in a
   third process, ``receiver.renderprocess``), is not given the model: it asks for the
   Hello, fetches the model from the sender by its sha256 in chunks over the control channel
   into a temporary cache (not the user's), and plays every packet (``receiver.playout``,
   morph, render from the sender's camera) as a live picture: with ``keep_up``, so that a
   draw slower than the stream (the two ends, the recording and its encoder share 2
   cores) repeats the last frame out for a slot already overtaken (``packets_repeated``)
   instead of falling further behind. The sender holds its first frame until the
   receiver is ready to play (one event shared by the processes: the receiver's ``ready``,
   the sender's ``start``), so the receiver has no backlog to catch up on. When the sender
   has sent its last frame and the receiver has taken every packet (or none came for
   ``QUIET_S``), the receiver is stopped: it plays what it received, and ends.
4. Outputs in ``out_dir``: ``demo.mp4``, each output frame of the receiver (its
   ``on_frame``) as performer | reconstruction (``receiver.output.side_by_side``,
   labelled), the performer's frame being the one the sender sent for that slot;
   ``demo-bandwidth.png``, the bit rate the receiver measured on the link over time (its
   ``on_packet``); and the summary (``DemoResult.summary``): the sender's and the
   receiver's own summaries, among them the model's source ("fetched") and the packets the
   receiver took from the socket.

The output has one frame per slot from the first packet played to the last (the receiver's
"Output frames"): on a link without loss, one per streamed frame. A sender this machine
cannot run at the video's rate sends its packets late, and the receiver conceals the slots it
gives up (``packets_lost``) as it would live.

Speeds. ``render_fps`` is what the receiver's render process could draw (1000 / its median
time for a frame); ``output_fps`` is the rate the receiver handed out its frames, from the
first to the last: the stream's rate when it keeps up, less when it falls behind.

Bit rates. ``payload_kbps`` is the packet size at 30 Hz (the contract's number);
``wire_kbps`` adds ZeroMQ's 2 bytes of framing per message (``protocol.transport``).
``measured_payload_kbps`` is what arrived per second of the stream, at the rate the sender
actually ran. Latency is the receiver's: a packet's arrival to its frame rendered.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from facewire.models.infra.childpipe import receive_from
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import VideoFrame, read_frames, video_info
from facewire.performer import ENROLL_S, PerformanceResult, perform
from facewire.protocol.errors import FacewireError
from facewire.protocol.packet import PACKET_BYTES
from facewire.protocol.rate import NOMINAL_HZ, kbps, stream_rate
from facewire.protocol.transport import WIRE_OVERHEAD, free_loopback_endpoint
from facewire.receiver.output import VideoWriter, side_by_side
from facewire.receiver.playout import FrameState
from facewire.receiver.receiver import receive
from facewire.sender.enroll.build import BuildResult, build_model
from facewire.sender.sender import send

DEFAULT_OUT = "facewire-demo"
QUIET_S = 2.0  # the sender done, the receiver stops when no packet came for this long
WINDOW_S = 1.0  # the bandwidth plot's trailing window
LABEL_SCALE = 0.5
MIN_STREAM_FRAMES = 10
DEMO_CRF, DEMO_PRESET = 20, "veryfast"  # demo.mp4: the encoder shares 2 cores with both ends
RECORD_QUEUE = 64  # frames the recorder may hold behind the receiver (59 MB at 512 x 600)
_RECEIVER_COUNTS = ("received", "lost", "late", "corrupt", "duplicates", "stray", "discarded",
                    "restarts", "overflow", "repeated")
Status = Callable[[str], None]


class DemoError(FacewireError, ValueError):
    """The demo cannot run as asked (a video too short, a link that failed); says why."""


@dataclass(frozen=True)
class LinkResult:
    """What ``loopback`` streamed, received and rendered.

    Attributes:
        frames: (F,) int performer frame index of each output frame (the one its slot sent).
        seq: (F,) int the slots' sequence numbers.
        status: per slot, the playout status ("received", "held", ...).
        rotation: (F, 3, 3) float64 the slots' head rotations (model -> camera), as played;
            a repeated frame (``receiver["repeated"]``) shows the picture before it instead.
        q: (F, 8) float32 the slots' Q values, as played.
        residuals: (F, 9, 2) float32 the slots' tangent residuals, as played, mm.
        arrival_s: (P,) float64 arrival time of each packet received, s from the first.
        shown_s: (F,) float64 the time each output frame was handed out, s from the first
            packet's arrival.
        packet_bytes: (P,) int their sizes.
        sender: ``sender.sender.send``'s summary.
        receiver: ``receiver.receiver.receive``'s summary.
        seconds: wall time of the stream.
    """

    frames: np.ndarray
    seq: np.ndarray
    status: tuple[str, ...]
    rotation: np.ndarray
    q: np.ndarray
    residuals: np.ndarray
    arrival_s: np.ndarray
    shown_s: np.ndarray
    packet_bytes: np.ndarray
    sender: dict[str, Any]
    receiver: dict[str, Any]
    seconds: float


@dataclass(frozen=True)
class DemoResult:
    """What ``demo`` made and measured (``summary()`` is the printed report).

    Attributes:
        out_dir: the output folder; video, plot, model, log: its files.
        source: the performer video: ``demo-performer.mp4`` there, or ``--source``.
        performance: the built-in performance's script values, or None with ``--source``.
        build: the model's build.
        link: the stream's record.
        seconds: wall time per step ("perform", "build", "stream") and "total".
    """

    out_dir: Path
    video: Path
    plot: Path
    model: Path
    log: Path
    source: Path
    performance: PerformanceResult | None
    build: BuildResult
    link: LinkResult
    enroll_frames: int
    seconds: dict[str, float]

    def script(self) -> np.ndarray | None:
        """(F, 5) the built-in script's channels at each slot played (``CHANNELS`` order),
        or None with ``--source``."""
        if self.performance is None:
            return None
        return self.performance.values[self.link.frames]

    def summary(self) -> dict[str, Any]:
        """The report: bit rates, speeds, counts, where the files are."""
        link, sent, got = self.link, self.link.sender, self.link.receiver
        span = float(link.arrival_s[-1]) if len(link.arrival_s) > 1 else 0.0
        measured_hz = (len(link.arrival_s) - 1) / span if span > 0 else 0.0
        shown = float(link.shown_s[-1] - link.shown_s[0]) if len(link.shown_s) > 1 else 0.0
        render_ms = got["render_ms_median"]
        return {
            "video": str(self.video), "bandwidth_plot": str(self.plot),
            "performer": str(self.source), "model": str(self.model),
            "preview": str(self.build.preview), "log": str(self.log),
            "frames": len(link.frames), "enroll_frames": self.enroll_frames,
            "packets_sent": sent["packets"], "face_frames": sent["face_frames"],
            **{f"packets_{k}": got[k] for k in _RECEIVER_COUNTS},
            "model_source": got["model_source"], "model_fetch_s": got["model_fetch_s"],
            "packet_bytes": PACKET_BYTES,
            "payload_kbps": _kbps(PACKET_BYTES, NOMINAL_HZ),
            "wire_kbps": _kbps(PACKET_BYTES + WIRE_OVERHEAD["plain"], NOMINAL_HZ),
            "measured_rate_hz": round(measured_hz, 2),
            "measured_payload_kbps": _kbps(PACKET_BYTES, measured_hz),
            "sender_fps": sent["fps"],
            "render_fps": round(1000 / render_ms, 1) if render_ms else None,
            "output_fps": round((len(link.shown_s) - 1) / shown, 2) if shown > 0 else None,
            "latency_ms_median": got["latency_ms_median"],
            "latency_ms_p95": got["latency_ms_p95"],
            "glass_to_glass_ms_median": got["glass_to_glass_ms_median"],
            "glass_to_glass_ms_p95": got["glass_to_glass_ms_p95"],
            "model_bytes": self.build.model.file_bytes, "regions": len(self.build.model.regions),
            "seconds": {k: round(v, 1) for k, v in self.seconds.items()},
        }


def demo(out_dir: str | os.PathLike[str] = DEFAULT_OUT,
         source: str | os.PathLike[str] | None = None, seconds: float | None = None,
         enroll_s: float = ENROLL_S, progress: Progress = no_progress,
         status: Status | None = None) -> DemoResult:
    """Run the demo (module docstring).

    Args:
        out_dir: the output folder (created if missing; the demo's files in it are replaced).
        source: a video of one person to use instead of the built-in performance; its first
            ``enroll_s`` seconds build the model, the rest is streamed.
        seconds: stream at most this many seconds after the enrollment part (all by default).
        enroll_s: how many seconds at the start build the model (> 0).
        progress: wraps an iterable to show progress: ``progress(items, label, total)``
            (the performer, the model build).
        status: called with one line of text at each step, and with the receiver's status
            lines while streaming; None: silent.

    Returns:
        What was made (``DemoResult.summary()`` for the report).

    Raises:
        DemoError: the video is too short, or the link failed.
        PerformerError: the built-in portrait cannot be used.
        BuildError, VideoError, EnrollError: the model cannot be built from the video.
        TransportError: no free port on 127.0.0.1.
        EGLUnavailable: headless OpenGL is missing (the message says how to install it).
    """
    say = status or (lambda _: None)
    start = time.perf_counter()
    if not (np.isfinite(enroll_s) and enroll_s > 0):
        raise DemoError(f"enroll_s: expected a positive number of seconds, got {enroll_s!r}")
    if seconds is not None and not (np.isfinite(seconds) and seconds > 0):
        raise DemoError(f"--seconds: expected a positive number, got {seconds!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    performance = None
    if source is None:
        say("performer: the scripted performance of the sample portrait")
        tick = time.perf_counter()
        performance = perform(out / "demo-performer.mp4", progress=progress)
        timings["perform"] = time.perf_counter() - tick
        video = performance.path
    else:
        video = Path(source)
        if not video.is_file():
            raise DemoError(f"{video}: no such video file")
    info = video_info(video)
    rate = stream_rate(info.rate_hz)
    enroll = int(round(enroll_s * rate))
    stop = None if seconds is None else enroll + int(round(seconds * rate))
    available = info.frames - enroll if info.frames else None
    if available is not None and available < MIN_STREAM_FRAMES:
        raise DemoError(f"{video}: {info.frames} frames ({info.frames / rate:.1f} s); the demo "
                        f"needs {enroll_s:g} s to build the model and at least "
                        f"{MIN_STREAM_FRAMES} frames after them to stream")

    say(f"model: building from frames 0:{enroll} of {video}")
    tick = time.perf_counter()
    model_path = out / "demo.fwm"
    build = build_model(video, model_path, slice(0, enroll), name=video.stem,
                        progress=progress)
    timings["build"] = time.perf_counter() - tick

    say("stream: facewire send -> ZeroMQ on 127.0.0.1 -> facewire receive (model by sha256)")
    tick = time.perf_counter()
    out_video, log_path = out / "demo.mp4", out / "demo.fwlog"
    link = loopback(model_path, video, slice(enroll, stop), rate, out_video, log_path,
                    status=say)
    timings["stream"] = time.perf_counter() - tick
    plot = out / "demo-bandwidth.png"
    plot_bandwidth(link.arrival_s, link.packet_bytes, plot)
    timings["total"] = time.perf_counter() - start
    return DemoResult(out, out_video, plot, model_path, log_path, video, performance, build,
                      link, enroll, timings)


def loopback(model_path: str | os.PathLike[str], video: str | os.PathLike[str], frames: slice,
             rate_hz: float, out_video: str | os.PathLike[str],
             record: str | os.PathLike[str] | None = None,
             status: Status | None = None) -> LinkResult:
    """Stream a video with the real ``send`` and ``receive`` over ZeroMQ on 127.0.0.1.

    ``send`` runs in a spawned process, ``receive`` on a thread of this one; the receiver
    fetches the model from the sender by its sha256 into a temporary cache (module
    docstring, 3).

    Args:
        model_path: the person model (``.fwm``), the sender's.
        video: the video to send, in real time.
        frames: which of its frames (indices, step 1).
        rate_hz: the stream's rate, Hz (the video's).
        out_video: the ``.mp4`` to write: the video's frame | the reconstruction, per slot.
        record: a packet log the sender writes, or None.
        status: called with the receiver's status lines.

    Returns:
        The stream's record.

    Raises:
        DemoError: the receiver failed, or played nothing; the sender's process died.
        TransportError: no free pair of ports on 127.0.0.1, or it was taken meanwhile.
        ModelFileError, CaptureError, LogError: from ``send``.
    """
    say = status or (lambda _: None)
    endpoint = free_loopback_endpoint()
    recorder = _Recorder(_Performer(video, frames, rate_hz), out_video, rate_hz)
    processes = multiprocessing.get_context("spawn")
    sender_stop, ready = processes.Event(), processes.Event()
    receiver_stop = threading.Event()
    outcome: dict[str, Any] = {}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="facewire-demo-cache-") as cache:

        def run_receiver() -> None:
            try:
                outcome["summary"] = receive(
                    endpoint, cache_dir=cache, status=lambda line: say(f"receiver: {line}"),
                    stop=receiver_stop, on_frame=recorder.frame, on_packet=recorder.packet,
                    ready=_Ready(ready), keep_up=True)
            except BaseException as exc:  # noqa: BLE001 - raised on this thread below
                outcome["error"] = exc
                sender_stop.set()

        thread = threading.Thread(target=run_receiver, name="facewire demo receiver")
        thread.start()
        results, results_in = processes.Pipe(duplex=False)
        sender = processes.Process(
            target=_run_sender, name="facewire demo sender",
            args=(results_in, str(model_path), str(video), endpoint,
                  None if record is None else str(record), rate_hz, frames, ready,
                  sender_stop))
        try:
            sender.start()
            results_in.close()
            sent = _sender_result(sender, results)
            recorder.wait_packets(sent["packets"], QUIET_S)
        finally:
            sender_stop.set()
            if sender.pid is not None:
                sender.join()
            results.close()
            receiver_stop.set()
            thread.join()
            recorder.close()
    if "error" in outcome:
        raise DemoError(f"the receiver failed: {outcome['error']}") from outcome["error"]
    if not recorder.seq:
        raise DemoError("no packet arrived from the sender")
    t = np.array(recorder.arrivals)
    return LinkResult(
        frames=np.array(recorder.frames), seq=np.array(recorder.seq),
        status=tuple(recorder.status), rotation=np.array(recorder.rotation),
        q=np.array(recorder.q, np.float32), residuals=np.array(recorder.residuals, np.float32),
        arrival_s=t - t[0], shown_s=np.array(recorder.shown) - t[0],
        packet_bytes=np.array(recorder.sizes), sender=sent,
        receiver=outcome["summary"], seconds=time.perf_counter() - start)


class _Ready(threading.Event):
    """The receiver's ``ready`` (a ``threading.Event``), which also sets the sender's
    ``start``: an event shared with the sender's process."""

    def __init__(self, shared: Any) -> None:
        super().__init__()
        self._shared = shared

    def set(self) -> None:
        super().set()
        self._shared.set()


def _run_sender(results: Connection, model_path: str, video: str, endpoint: str,
                record: str | None, rate_hz: float, frames: slice, start: Any,
                stop: Any) -> None:
    """The sender process: ``send``, its summary (or its exception) sent back on
    ``results``; ``start`` and ``stop`` are the parent's process-shared events."""
    try:
        # no healing: the embedded performance (one photo made to move) moves its cap and
        # folds unlike the mesh, and the healing made 8 patches in 7 s chasing them
        # (docs/DESIGN.md, "Texture patches")
        summary = send(model_path, video, endpoint, record, rate_hz, stop=stop,
                       frames=frames, start=start, heal=False)
    except BaseException as exc:  # noqa: BLE001 - raised in the parent (_sender_result)
        try:
            results.send(("error", exc))
        except Exception:  # noqa: BLE001 - an exception that does not pickle: its text
            results.send(("error", DemoError(f"the sender failed: {type(exc).__name__}: "
                                             f"{exc}")))
        return
    results.send(("ok", summary))


def _sender_result(process: Any, results: Connection) -> dict[str, Any]:
    """The sender process's summary, once it has sent its last frame; its exception raised
    here; ``DemoError`` if it died without a word."""
    try:
        kind, value = receive_from(process, results)
    except EOFError:
        process.join()
        raise DemoError(f"the sender's process (pid {process.pid}) died (exit code "
                        f"{process.exitcode}) before it reported") from None
    if kind == "error":
        raise value
    return cast(dict[str, Any], value)


class _Performer:
    """The performer's frame of each slot of the stream, as ``send`` picks it: slot ``k`` gets
    the latest frame stamped at most a quarter period after ``t_0 + k / rate_hz`` (``t_0``
    the first frame's time; ``sender.sender``)."""

    def __init__(self, video: str | os.PathLike[str], frames: slice, rate_hz: float) -> None:
        self._video = video
        self._frames: Iterator[VideoFrame] = read_frames(video, frames)
        first = next(self._frames, None)
        if first is None:
            raise DemoError(f"{video}: no frame in {frames.start}:{frames.stop or ''}")
        self._held = first
        self._next = next(self._frames, None)
        self._t0 = self._held.time
        self._period = 1.0 / rate_hz

    def at(self, slot: int) -> VideoFrame:
        """The frame sent in slot ``slot`` (slots in increasing order)."""
        limit = self._t0 + (slot + 0.25) * self._period
        while self._next is not None and self._next.time <= limit:
            self._held, self._next = self._next, next(self._frames, None)
        return self._held


class _Recorder:
    """The demo receiver's callbacks: each packet's arrival (``on_packet``), and each output
    frame (``on_frame``) written side by side with the performer's frame of its slot.

    ``on_frame`` only notes the frame and queues it (at most ``RECORD_QUEUE`` frames, then it
    waits): a thread of the recorder's own reads the performer's frame, composes the two and
    hands them to the encoder, so the receiver's loop is not held up by the demo's recording
    (the performer's decode, the labels, the scaling: about 10 ms a frame at 512 x 600 on the
    2-core machine, as much as a draw). A failure there is raised by ``close``.
    """

    def __init__(self, performer: _Performer, out_video: str | os.PathLike[str],
                 rate_hz: float) -> None:
        self._performer, self._out, self._rate_hz = performer, out_video, rate_hz
        self._writer: VideoWriter | None = None
        self._queue: queue.Queue[tuple[np.ndarray, int] | None] = queue.Queue(RECORD_QUEUE)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._record, name="facewire demo recorder",
                                        daemon=True)
        self._thread.start()
        self._ext: int | None = None  # the slot: the sequence number extended past 16 bits
        self._last_seq = 0
        self.arrivals: list[float] = []
        self.shown: list[float] = []
        self.sizes: list[int] = []
        self.frames: list[int] = []
        self.seq: list[int] = []
        self.status: list[str] = []
        self.rotation: list[np.ndarray] = []
        self.q: list[np.ndarray] = []
        self.residuals: list[np.ndarray] = []

    def packet(self, data: bytes, arrival: float) -> None:
        self.arrivals.append(arrival)
        self.sizes.append(len(data))

    def frame(self, image: np.ndarray, state: FrameState) -> None:
        """Write one output frame ((H, W, 3) uint8 RGB) beside the performer's; the sender
        numbers its slots from 0."""
        self.shown.append(time.monotonic())
        seq = state.seq
        assert seq is not None  # the receiver outputs the slots it plays
        ext = seq if self._ext is None else self._ext + (seq - self._last_seq) % 65536
        self._ext, self._last_seq = ext, seq
        self.seq.append(seq)
        self.status.append(state.status)
        self.rotation.append(state.rotation)
        self.q.append(state.q.copy())
        self.residuals.append(state.residuals.copy())
        if self._error is None:  # after a failure the thread only empties the queue
            self._queue.put((image, ext))

    def _record(self) -> None:
        """The recorder's thread: each queued frame beside its performer's, encoded."""
        while (item := self._queue.get()) is not None:
            if self._error is not None:
                continue
            image, ext = item
            try:
                performer = self._performer.at(ext)
                left = _label(np.ascontiguousarray(performer.image[..., ::-1]),
                              "performer (sender's camera)")
                right = _label(image, f"reconstruction ({PACKET_BYTES} bytes/frame)")
                both = side_by_side(left, right, image.shape[0])
                if self._writer is None:
                    self._writer = VideoWriter(self._out, both.shape[1], both.shape[0],
                                               self._rate_hz, crf=DEMO_CRF,
                                               preset=DEMO_PRESET)
                self._writer.write(both)
                self.frames.append(performer.index)
            except BaseException as exc:  # noqa: BLE001 - raised by close()
                self._error = exc

    def wait_packets(self, count: int, quiet_s: float) -> None:
        """Return once ``count`` packets were taken, or none for ``quiet_s``."""
        seen, since = len(self.arrivals), time.monotonic()
        while seen < count and time.monotonic() - since < quiet_s:
            time.sleep(0.05)
            if len(self.arrivals) > seen:
                seen, since = len(self.arrivals), time.monotonic()

    def close(self) -> None:
        """Record what is queued, close the video; the recorder's failure raised here."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        if self._writer is not None:
            self._writer.close()
        if self._error is not None:
            raise DemoError(f"{self._out}: the recording failed: {self._error}") \
                from self._error


def plot_bandwidth(arrival_s: np.ndarray, packet_bytes: np.ndarray,
                   path: str | os.PathLike[str]) -> None:
    """Plot the bit rate received over time: payload and wire, trailing ``WINDOW_S`` window.

    Args:
        arrival_s: (P,) packet arrival times, s.
        packet_bytes: (P,) their sizes, bytes (the wire adds ZeroMQ's framing to each).
        path: the PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(arrival_s, np.float64)
    size = np.asarray(packet_bytes, np.float64)
    cumulative = np.concatenate([[0.0], np.cumsum(size)])
    first = np.searchsorted(t, t - WINDOW_S, side="right")
    count = np.arange(1, len(t) + 1) - first
    payload = (cumulative[1:] - cumulative[first]) * 8 / 1000 / WINDOW_S
    wire = payload + count * WIRE_OVERHEAD["plain"] * 8 / 1000 / WINDOW_S
    warm = t >= t[0] + WINDOW_S if len(t) else t  # a full window behind it
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(t[warm], wire[warm], lw=1.5, label="wire (payload + ZeroMQ framing)")
    ax.plot(t[warm], payload[warm], lw=1.5, label=f"payload ({PACKET_BYTES} B per packet)")
    ax.axhline(_kbps(PACKET_BYTES, NOMINAL_HZ), color="grey", ls=":",
               label=f"payload at {NOMINAL_HZ:g} Hz")
    ax.axhline(12.0, color="red", ls="--", label="12 kbit/s target")
    ax.set_xlabel("time since the first packet (s)")
    ax.set_ylabel(f"kbit/s over the last {WINDOW_S:g} s")
    ax.set_ylim(0, 14)
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title("facewire demo: bit rate received on the ZeroMQ link (127.0.0.1)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """A copy of an RGB image with ``text`` in its top-left corner, on a dark band."""
    out = image.copy()
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, LABEL_SCALE, 1)
    out[:h + base + 8, :w + 12] //= 3
    cv2.putText(out, text, (6, h + 4), cv2.FONT_HERSHEY_SIMPLEX, LABEL_SCALE,
                (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _kbps(message_bytes: float, rate_hz: float) -> float:
    return round(kbps(message_bytes, rate_hz), 3)
