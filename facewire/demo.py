"""``facewire demo``: the whole system on one machine, with no camera and no files.

Steps (``demo``):

1. Performer. Without ``--source``, ``facewire.performer.perform`` turns matplotlib's
   public-domain portrait into a video of a scripted performance (head turns, brow raises,
   mouth opening, blinks; what is synthetic is said there): ``demo-performer.mp4``. With
   ``--source VIDEO`` that video is the performer.
2. Model. ``models.build.build_model`` with ``sender.enroll.enroll_regions`` (what
   ``facewire model build`` does) on the performer's first ``ENROLL_S`` seconds:
   ``demo.fwm`` and its preview ``demo.preview.png``. The built-in script shows each
   movement once in those seconds, so enrollment sees brows up, an open mouth, a blink and
   head turns.
3. Stream (``loopback``). The frames after them go through the real sender pipeline
   (``sender.pipeline.SenderPipeline``, paced at the video's rate as a camera delivers
   them) on one thread, out of a real ZeroMQ PUB socket bound to tcp on 127.0.0.1, with the
   Hello answered on the control socket (port + 1); the receiver, on this thread,
   subscribes, asks for the Hello, checks that it announces the model's sha256 (both ends
   read the same ``demo.fwm``: the model is not transferred), and runs per packet what a
   receiver runs: ``receiver.playout.Playout``, ``models.rig.Rig`` morph and
   ``receiver.render.FaceRenderer`` from the sender's camera
   (``receiver.views.sender_view``). The sender records its packets to ``demo.fwlog``
   (``facewire replay`` / ``bench bandwidth`` read it).
4. Outputs in ``out_dir``: ``demo.mp4``, each streamed frame as performer | reconstruction
   (``receiver.output.side_by_side``, labelled), one frame per slot played;
   ``demo-bandwidth.png``, the bit rate the receiver measured on the link over time; and the
   summary (``DemoResult.summary``).

The demo's render clock. A live receiver plays each slot as soon as its packet is in and
conceals a missing one at a deadline on its clock (``receiver.receiver``); this one has no
clock: it plays each slot as soon as its packet is in (``Playout.ready``), conceals a missing
slot once ``depth`` packets behind it have arrived, and drains the buffer at the end, so the
output has exactly one frame per streamed frame, in step with the performer, even when this
machine cannot run the sender at the video's rate. The playout buffer still orders,
de-duplicates and conceals as it does live.

Bit rates. ``payload_kbps`` is the packet size at 30 Hz (the contract's number);
``wire_kbps`` adds ZeroMQ's 2 bytes of framing per message (``protocol.transport``).
``measured_payload_kbps`` is what arrived per second of the stream, at the rate the sender
actually ran. Latency is measured per packet from the moment the sender handed it to the
socket to the moment its frame was rendered (one process, one monotonic clock): the
transport, any wait behind a missing slot or a frame still rendering, and the render.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.performer import ENROLL_S, PerformanceResult, perform
from facewire.sender.enroll.build import BuildResult, build_model
from facewire.models.modelfile import PersonModel, load_model
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import read_frames, video_info
from facewire.protocol.control import ControlError, Hello, HelloRequest, decode_message
from facewire.protocol.log import LogWriter
from facewire.protocol.packet import PACKET_BYTES
from facewire.protocol.rate import NOMINAL_HZ
from facewire.protocol.transport import (WIRE_OVERHEAD, ControlClient, ControlServer, PacketPublisher,
                                PacketSubscriber, TransportError, control_endpoint)
from facewire.receiver.output import VideoWriter, side_by_side
from facewire.receiver.playout import Playout
from facewire.receiver.scene import StateRenderer, rest_q
from facewire.sender.capture import open_source
from facewire.sender.enroll.layers import enroll_regions
from facewire.sender.pipeline import SenderPipeline, sender_camera

DEFAULT_OUT = "facewire-demo"
HOST = "127.0.0.1"
BIND_TRIES = 5  # ephemeral ports tried for a free packet port whose port + 1 is free too
HELLO_TIMEOUT_S = 30.0  # the receiver's wait for the sender's Hello (the sender loads first)
SETTLE_S = 0.3  # after the Hello, before the first packet: the subscription reaches the PUB
IDLE_S = 0.05  # the receiver's poll while waiting for packets
WINDOW_S = 1.0  # the bandwidth plot's trailing window
LABEL_SCALE = 0.5
MIN_STREAM_FRAMES = 10
DEMO_CRF, DEMO_PRESET = 20, "veryfast"  # demo.mp4: the encoder shares 2 cores with both ends
Status = Callable[[str], None]


class DemoError(ValueError):
    """The demo cannot run as asked (a video too short, a link that failed); says why."""


@dataclass(frozen=True)
class LinkResult:
    """What ``loopback`` streamed, received and rendered.

    Attributes:
        frames: performer frame indices of the slots played, in order (one output frame each).
        seq: (F,) int the slots' sequence numbers.
        status: per slot, the playout status ("received", "held", ...).
        rotation: (F, 3, 3) float64 the head rotations rendered (model -> camera).
        q: (F, 8) float32 the Q values rendered.
        residuals: (F, 9, 2) float32 the tangent residuals rendered, mm.
        arrival_s: (P,) float64 arrival time of each packet received, s from the first.
        packet_bytes: (P,) int their sizes.
        latency_ms: (F',) float64 per received slot, sender's send to frame rendered, ms.
        sent: packets the sender published; face_frames: of them with a face tracked.
        playout: the playout buffer's counts (received, concealed, late, corrupt ...).
        sender_fps: frames the sender processed per second of its loop.
        render_fps: frames the receiver rendered per second of render time.
        seconds: wall time of the stream.
    """

    frames: np.ndarray
    seq: np.ndarray
    status: tuple[str, ...]
    rotation: np.ndarray
    q: np.ndarray
    residuals: np.ndarray
    arrival_s: np.ndarray
    packet_bytes: np.ndarray
    latency_ms: np.ndarray
    sent: int
    face_frames: int
    playout: dict[str, int]
    sender_fps: float
    render_fps: float
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
        link = self.link
        span = float(link.arrival_s[-1]) if len(link.arrival_s) > 1 else 0.0
        measured_hz = (len(link.arrival_s) - 1) / span if span > 0 else 0.0
        latency = link.latency_ms
        return {
            "video": str(self.video), "bandwidth_plot": str(self.plot),
            "performer": str(self.source), "model": str(self.model),
            "preview": str(self.build.preview), "log": str(self.log),
            "frames": len(link.frames), "enroll_frames": self.enroll_frames,
            "packets_sent": link.sent, "face_frames": link.face_frames,
            **{f"packets_{k}": v for k, v in link.playout.items()},
            "packet_bytes": PACKET_BYTES,
            "payload_kbps": _kbps(PACKET_BYTES, NOMINAL_HZ),
            "wire_kbps": _kbps(PACKET_BYTES + WIRE_OVERHEAD["plain"], NOMINAL_HZ),
            "measured_rate_hz": round(measured_hz, 2),
            "measured_payload_kbps": _kbps(PACKET_BYTES, measured_hz),
            "sender_fps": round(link.sender_fps, 1), "render_fps": round(link.render_fps, 1),
            "latency_ms_median": _round(np.median(latency)) if len(latency) else None,
            "latency_ms_p95": _round(np.percentile(latency, 95)) if len(latency) else None,
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
        progress: wraps an iterable to show progress: ``progress(items, label, total)``.
        status: called with one line of text at each step and about once a second while
            streaming; None: silent.

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
    rate = info.rate_hz or NOMINAL_HZ
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
                        progress=progress, appearance=enroll_regions)
    timings["build"] = time.perf_counter() - tick

    say("stream: sender -> ZeroMQ on 127.0.0.1 -> receiver")
    tick = time.perf_counter()
    out_video, log_path = out / "demo.mp4", out / "demo.fwlog"
    link = loopback(model_path, video, slice(enroll, stop), out_video, log_path,
                    progress=progress, status=say)
    timings["stream"] = time.perf_counter() - tick
    plot = out / "demo-bandwidth.png"
    plot_bandwidth(link.arrival_s, link.packet_bytes, plot)
    timings["total"] = time.perf_counter() - start
    return DemoResult(out, out_video, plot, model_path, log_path, video, performance, build,
                      link, enroll, timings)


def loopback(model_path: str | os.PathLike[str], video: str | os.PathLike[str], frames: slice,
             out_video: str | os.PathLike[str], record: str | os.PathLike[str] | None = None,
             progress: Progress = no_progress, status: Status | None = None) -> LinkResult:
    """Stream a video through the real sender, a ZeroMQ link on 127.0.0.1 and the receiver.

    The sender runs on its own thread; this thread is the receiver (module docstring, 3).

    Args:
        model_path: the person model (``.fwm``), the same file for both ends.
        video: the video to send, paced at its own rate.
        frames: which of its frames (indices, step 1).
        out_video: the ``.mp4`` to write: the video's frame | the reconstruction, per slot.
        record: a packet log the sender writes, or None.
        progress: wraps an iterable to show progress.
        status: called with a status line about once a second.

    Returns:
        The stream's record.

    Raises:
        DemoError: the sender failed, or no Hello arrived.
        TransportError: no free pair of ports on 127.0.0.1.
    """
    say = status or (lambda _: None)
    model = load_model(model_path)
    publisher, control = _bind()
    sender = _Sender(model, video, frames, publisher, control, record)
    thread = threading.Thread(target=sender.run, name="demo sender", daemon=True)
    thread.start()
    try:
        with PacketSubscriber(publisher.endpoint) as subscriber, \
                ControlClient(control.endpoint) as client:
            hello = _hello(client, model, sender)
            return _receive(model, hello, subscriber, sender, video, frames, out_video,
                            progress, say)
    finally:
        sender.stop.set()
        thread.join()
        publisher.close()
        control.close()


class _Sender:
    """The demo's sender thread: the real pipeline, paced, publishing every packet."""

    def __init__(self, model: PersonModel, video: str | os.PathLike[str], frames: slice,
                 publisher: PacketPublisher, control: ControlServer,
                 record: str | os.PathLike[str] | None) -> None:
        self.model, self.video, self.frames = model, str(video), frames
        self.publisher, self.control, self.record = publisher, control, record
        self.stop = threading.Event()
        self.done = threading.Event()
        self.sent_at: dict[int, float] = {}  # seq -> time.monotonic() at send
        self.sent = 0
        self.face_frames = 0
        self.loop_seconds = 0.0
        self.error: BaseException | None = None
        self.hello: Hello | None = None

    def run(self) -> None:
        try:
            self._run()
        except BaseException as exc:  # noqa: BLE001 - handed to the receiver thread
            self.error = exc
        finally:
            self.done.set()

    def _run(self) -> None:
        source = open_source(self.video, frames=self.frames, pace=True)
        with source:
            camera = sender_camera(source.width, source.height)
            pipeline = SenderPipeline(self.model, camera, rate_hz=source.rate_hz or NOMINAL_HZ)
            self.hello = pipeline.hello()
            while not self.stop.is_set() and not self._answer(100):
                pass  # no receiver has asked for the Hello yet
            deadline = time.monotonic() + SETTLE_S
            while time.monotonic() < deadline:
                self._answer(10)
            log = LogWriter(self.record, self.hello) if self.record is not None else None
            start = time.perf_counter()
            try:
                for frame in source:
                    if self.stop.is_set():
                        break
                    out = pipeline.process(frame.image, frame.time)
                    self.sent_at[out.frame.seq] = time.monotonic()
                    self.publisher.send(out.packet)
                    if log is not None:
                        log.write(out.packet, frame.time)
                    self.sent += 1
                    self.face_frames += out.points is not None
                    self._answer(0)
            finally:
                self.loop_seconds = time.perf_counter() - start
                if log is not None:
                    log.close()

    def _answer(self, timeout_ms: int) -> bool:
        """Answer one control request if one comes; True when it was a Hello request."""
        request = self.control.recv(timeout_ms)
        if request is None:
            return False
        peer, raw = request
        try:
            message = decode_message(raw)
        except ControlError:
            return False
        if isinstance(message, HelloRequest) and self.hello is not None:
            self.control.reply(peer, self.hello)
            return True
        return False


def _bind() -> tuple[PacketPublisher, ControlServer]:
    """A PUB socket on a free port of 127.0.0.1 and the control socket on the next port."""
    last: TransportError | None = None
    for _ in range(BIND_TRIES):
        publisher = PacketPublisher(f"tcp://{HOST}:*")
        try:
            return publisher, ControlServer(control_endpoint(publisher.endpoint))
        except TransportError as exc:
            last = exc
            publisher.close()
    raise TransportError(f"no free pair of ports on {HOST} after {BIND_TRIES} tries: {last}")


def _hello(client: ControlClient, model: PersonModel, sender: _Sender) -> Hello:
    """Ask for the Hello until it comes; check it announces this model."""
    deadline = time.monotonic() + HELLO_TIMEOUT_S
    while time.monotonic() < deadline:
        if sender.done.is_set():
            raise DemoError(f"the sender stopped before it said hello: {sender.error}") \
                from sender.error
        reply = client.request(HelloRequest(), 500)
        if isinstance(reply, Hello):
            if reply.model_sha256 != model.sha256:
                raise DemoError(f"the sender's model {reply.model_sha256[:16]}... is not the "
                                f"receiver's {model.sha256[:16]}...")
            return reply
    raise DemoError(f"no Hello from the sender within {HELLO_TIMEOUT_S:g} s")


def _receive(model: PersonModel, hello: Hello, subscriber: PacketSubscriber, sender: _Sender,
             video: str | os.PathLike[str], frames: slice, out_video: str | os.PathLike[str],
             progress: Progress, say: Status) -> LinkResult:
    """The receiver: packets in, one rendered slot per packet, side by side with the video."""
    start = time.perf_counter()
    width, height = hello.camera.width, hello.camera.height
    playout = Playout(hello.rate_hz, rest_q=rest_q(model))
    performer = read_frames(video, frames)
    arrivals: list[float] = []
    sizes: list[int] = []
    played: list[int] = []
    seqs: list[int] = []
    statuses: list[str] = []
    rotations: list[np.ndarray] = []
    qs: list[np.ndarray] = []
    residuals: list[np.ndarray] = []
    latency: list[float] = []
    render_seconds = 0.0
    left_label = "performer (sender's camera)"
    right_label = f"reconstruction ({PACKET_BYTES} bytes/frame)"
    last_status = time.monotonic()
    last_seq: int | None = None
    ext = 0  # the slot's sequence number, extended past 16 bits: the sender starts at 0

    def states():
        """Each slot the playout plays: as soon as it is ready (module docstring), then the
        drain."""
        while True:
            data = subscriber.recv(int(IDLE_S * 1000))
            if data is None:
                if sender.done.is_set():
                    break
                continue
            now = time.monotonic()
            arrivals.append(now)
            sizes.append(len(data))
            playout.push(data, now)
            while playout.ready or playout.ahead > playout.depth:
                state = playout.pop()
                if state.seq is not None:
                    yield state
        while not playout.drained:
            state = playout.pop()
            if state.seq is not None:
                yield state

    count = video_info(video).frames or None  # 0: the container does not say
    stop = count if frames.stop is None else min(frames.stop, count or frames.stop)
    total = None if stop is None else max(stop - frames.start, 0)
    with StateRenderer(model, width, height, hello.camera) as renderer, \
            VideoWriter(out_video, 2 * width, height, hello.rate_hz, crf=DEMO_CRF,
                        preset=DEMO_PRESET) as writer:
        for state in progress(states(), "streaming", total):
            ext = state.seq if last_seq is None else ext + (state.seq - last_seq) % 65536
            last_seq = state.seq
            frame = next(performer, None)
            while frame is not None and frame.index < frames.start + ext:
                frame = next(performer, None)
            if frame is None:
                raise DemoError(f"{video}: no frame {frames.start + ext} for slot {state.seq}")
            tick = time.perf_counter()
            image = renderer.render(state)
            render_seconds += time.perf_counter() - tick
            if state.status == "received" and state.seq in sender.sent_at:
                latency.append(1000.0 * (time.monotonic() - sender.sent_at[state.seq]))
            left = _label(np.ascontiguousarray(frame.image[..., ::-1]), left_label)
            writer.write(side_by_side(left, _label(image, right_label), height))
            played.append(frame.index)
            seqs.append(state.seq)
            statuses.append(state.status)
            rotations.append(state.rotation)
            qs.append(state.q.copy())
            residuals.append(state.residuals.copy())
            now = time.monotonic()
            if now - last_status >= 1.0:
                last_status = now
                span = arrivals[-1] - arrivals[0] if len(arrivals) > 1 else 0.0
                fps = (len(arrivals) - 1) / span if span > 0 else 0.0
                say(f"stream: {len(played)} frames, {fps:.1f} packets/s, "
                    f"{_kbps(PACKET_BYTES, fps):.2f} kbit/s, "
                    f"face {'present' if state.status == 'received' else state.status}")
    if sender.error is not None:
        raise DemoError(f"the sender failed: {sender.error}") from sender.error
    if not played:
        raise DemoError("no packet arrived from the sender")
    t = np.array(arrivals)
    return LinkResult(
        frames=np.array(played), seq=np.array(seqs), status=tuple(statuses),
        rotation=np.array(rotations), q=np.array(qs, np.float32),
        residuals=np.array(residuals, np.float32),
        arrival_s=t - t[0], packet_bytes=np.array(sizes), latency_ms=np.array(latency),
        sent=sender.sent, face_frames=sender.face_frames, playout=playout.stats,
        sender_fps=sender.sent / sender.loop_seconds if sender.loop_seconds else 0.0,
        render_fps=len(played) / render_seconds if render_seconds else 0.0,
        seconds=time.perf_counter() - start)


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
    return round(message_bytes * 8 * rate_hz / 1000, 3)


def _round(value: float) -> float:
    return round(float(value), 1)
