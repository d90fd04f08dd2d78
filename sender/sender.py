"""The live send loop (``facewire send``): frames in, one packet per frame out to any receivers.

Threads. Capture, processing and output do not stall each other:

- the capture thread (``sender.framethread.FrameThread``) reads the source: a camera's
  newest frame is held and older ones dropped, so a slow tracker gets the current frame;
  a file is decoded up to a few frames ahead;
- the frame loop (the calling thread), per frame: take the next frame (a video file released
  in real time, below), run ``sender.pipeline.SenderPipeline``, publish the 43-byte packet
  on the PUB socket (``protocol.transport.PacketPublisher``; ZeroMQ's own I/O thread sends
  it, and a slow receiver's queue drops rather than blocks) and, with a record path, append
  it to a packet log (``protocol.log``; each record stamped with the time it was published:
  the Unix time at the start plus the monotonic clock since, so that a wall-clock change
  during a recording cannot make the log's times step back or jump); a model update the
  pipeline learned on the frame (``sender.learn``), in its bytes (encoded by the learner
  against the version it applies to), is handed to the control thread
  (``UpdateStore.publish_update``) and logged, after the frame's packet, which still names
  the version before it;
- the control thread answers receivers' requests (below);
- with a model that stores its person's descriptors, the identity process
  (``sender.identity``, ``identify_apart``) computes the tracker's identity checks, so a
  check (about 100 ms of CPU) never holds up a frame.

The stream's rate is the smaller of the target rate and the source's: a 25 Hz file sent at
``--rate 30`` goes out at 25 Hz, and the Hello says so. A camera limits itself to the rate
(``sender.capture``). A file is resampled to the rate's slots: slot ``k``, at ``t_0 + k /
rate_hz`` (``t_0`` the first frame's time), gets the latest frame stamped at most a quarter
period after it, so frames are dropped where the file has several per slot and repeated where
it has none (a variable-rate file whose container states 15 Hz but holds stretches at
12.5 Hz still goes out at 15 Hz). Slot ``k`` is released at ``origin + k / rate_hz`` on the
sender's clock, ``origin`` fixed at the first frame (``sender.slots.SlotClock``). Receivers
play one slot per ``1 / rate_hz`` on their own clock, so the sender keeps that schedule: a
frame that is late (the machine was busy) is sent at once and the next ones catch up, rather
than every later frame being shifted (which would leave the stream slower than announced and
the receivers' buffers running dry). A frame more than ``MAX_LAG_S`` late (a stalled machine)
starts the slots' clock again at itself, and the Hello announces the new origin
(``sender.slots``): seqs stay consecutive.

Capture time (``sender.slots``, ``protocol.clock``). Each packet's seq is its slot, captured
at ``origin + seq / rate_hz`` on the sender's clock (``clock``, the monotonic clock); once the
first frame has set ``origin`` the Hello carries it (``clock_origin_s``), and the control
thread answers time requests, so that a receiver measures glass-to-glass latency.

Control requests (``protocol.control``) are answered on a second thread, at the control
endpoint (the bind port plus one), by ``sender.responder.Responder``: the Hello, the model
file's chunks, and the chunks of the session's model updates (``sender.updates.UpdateStore``:
``publish_update(serial, data)``, from any thread), shaped per receiver; errors are counted
(``control.errors``). A thread of its own because a receiver fetches the model one chunk per
round trip: answered between frames, every chunk would wait for a frame's tracking and pacing,
one frame period each, and a Hello would wait behind the tracker. Its work (a lookup and a
send) is small beside the frame loop's. Each thread uses only its own sockets.

Holding the start (``start``): the frame loop holds the first frame until the event is set
(or ``stop`` is), while the control thread answers: e.g. until a receiver in the same process,
which fetches the model first, is ready to play (``receiver.receiver.receive(ready=)``), so
that it gets a file from its first frame without a backlog to catch up.

Receiver count: TCP connections open to the packet socket (``protocol.transport.PeerCounter``):
a relay counts as one, a peer still in its handshake counts too.

Encryption: with a key folder, both sockets are CURVE servers admitting only the receivers
in ``DIR/authorized`` (``protocol.keys``), each with its own authenticator (and so its own
ZeroMQ context: ``protocol.transport``). Without keys, binding to anything but loopback
would send the face stream in the clear and let any peer grow the process without bound (one
message of endless frames: ``protocol.transport``), so it is refused unless ``insecure``,
and then ``protocol.transport.unencrypted_warning`` says so loudly.

Stopping: the source ends (a file, unless ``loop``), ``stop`` is set, or Ctrl-C
(KeyboardInterrupt, caught): the control thread is stopped and joined, the log closed (every
finished record is on disk, so ``protocol.log.read_log`` reads it), and the sockets closed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from facewire.models.infra.sound import SoundError, read_sound
from facewire.models.modelfile import ModelFileError, load_model
from facewire.protocol.clock import MAX_LAG_S
from facewire.protocol.control import Hello, model_chunks
from facewire.protocol.keys import server_keys
from facewire.protocol.log import LogError, LogWriter
from facewire.protocol.opus import DEFAULT_BITRATE, Encoder
from facewire.protocol.rate import MAX_RATE_HZ, MIN_RATE_HZ, NOMINAL_HZ, payload_kbps
from facewire.protocol.transport import (
    ControlServer,
    PacketPublisher,
    PeerCounter,
    check_plaintext,
    control_endpoint,
    unencrypted_warning,
)
from facewire.sender.capture import CameraSource, CaptureError, Source, open_source
from facewire.sender.framethread import FrameThread
from facewire.sender.pipeline import SenderPipeline, identity_warning, sender_camera
from facewire.sender.responder import Responder
from facewire.sender.slots import Clock, SlotClock, camera_slot
from facewire.sender.updates import UpdateStore
from facewire.sender.voice import (
    FileVoice,
    MicVoice,
    VoiceSource,
    VoiceSourceError,
    VoiceThread,
)

DEFAULT_BIND = "tcp://127.0.0.1:5555"
STATUS_PERIOD_S = 1.0
CONTROL_POLL_MS = 100

Status = Callable[[dict[str, Any]], None]


def _read_model(path: str | os.PathLike[str]) -> tuple[Any, bytes]:
    """The model and the exact bytes it was loaded from (served to receivers by hash)."""
    model = load_model(path)
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ModelFileError(f"{os.fspath(path)}: cannot read ({exc})") from None
    if hashlib.sha256(data).hexdigest() != model.sha256:
        raise ModelFileError(f"{os.fspath(path)}: the file changed while it was being read")
    return model, data


def _log_writer(path: str | os.PathLike[str], hello: Hello) -> LogWriter:
    try:
        return LogWriter(path, hello)
    except OSError as exc:
        raise LogError(f"{os.fspath(path)}: cannot write the log: {exc.strerror or exc}"
                       ) from None


def _frames(source: Source, slots: SlotClock, loop: bool, stop: threading.Event,
            passes: list[float] | None = None) -> Iterator[tuple[np.ndarray, float, int]]:
    """(image, time s, slot) of the frames to send, released in real time (module
    docstring); ``slots.origin_s`` is set by the first frame (``sender.slots``).

    A camera delivers in real time and limits its own rate; its frames are numbered by
    ``sender.slots.camera_slot``. A file is resampled to the slots of the rate, slot ``k``
    released at ``origin + k / rate_hz`` and numbered (``SlotClock.release``: a frame
    more than ``MAX_LAG_S`` late starts the clock again at itself) and stamped with its media
    time ``t_0 + k / rate_hz``;
    a slot's frame is known once a frame stamped beyond its quarter-period tolerance has been
    read, or the file has ended. A looped file's times keep increasing across passes (each
    pass's start offset is appended to ``passes``, for the voice: ``sender.voice``). Waits
    end early when ``stop`` is set (the caller checks it).

    Raises:
        CaptureError: a pass yields no frame (an empty video).
    """
    if isinstance(source, CameraSource):
        with FrameThread(source, latest=True) as frames:
            for frame in frames:
                if slots.origin_s is None:
                    assert source.origin_s is not None  # set by the first frame read
                    slots.origin_s = source.origin_s + slots.skew_s()
                yield frame.image, frame.time, camera_slot(frame.time, slots.rate_hz)
        return
    period = 1.0 / slots.rate_hz
    offset, t0, slot = 0.0, 0.0, 0
    held: np.ndarray | None = None  # the latest frame read: the current slot's
    while True:
        last = None
        with FrameThread(source, latest=False) as frames:
            for frame in frames:
                last = frame.time
                t = offset + frame.time
                if held is None:
                    t0 = t
                while held is not None and t0 + (slot + 0.25) * period < t:
                    yield held, t0 + slot * period, slots.release(slot)
                    slot += 1
                held = frame.image
        if last is None:
            raise CaptureError(f"{source.name}: holds no frames")
        if not loop:
            break
        offset += last + 1.0 / source.rate_hz
        if passes is not None:
            passes.append(offset)
    assert held is not None  # the source held frames (above)
    while t0 + (slot - 0.25) * period <= offset + last:  # the slots of the last frame
        yield held, t0 + slot * period, slots.release(slot)
        slot += 1


def send(model_path: str | os.PathLike[str], source: str, bind: str = DEFAULT_BIND,
         record: str | os.PathLike[str] | None = None, rate_hz: float = NOMINAL_HZ,
         curve_dir: str | os.PathLike[str] | None = None, status: Status | None = None,
         stop: threading.Event | None = None, loop: bool = False,
         frames: slice = slice(0, None), start: threading.Event | None = None,
         learn: bool = True, updates: UpdateStore | None = None, heal: bool = True,
         insecure: bool = False,
         warn: Callable[[str], None] | None = None,
         clock: Clock = time.monotonic, audio: bool = True, mic: str | None = None,
         voice_bitrate: int = DEFAULT_BITRATE) -> dict[str, Any]:
    """Run the live sender until the source ends, ``stop`` is set, or Ctrl-C.

    Args:
        model_path: the person model (``.fwm``), announced and served by its sha256.
        source: ``camera:N``, a video file or a folder of images
            (``sender.capture.open_source``; files are sent in real time).
        bind: the packet endpoint ``tcp://HOST:PORT``; control is on PORT + 1.
        record: a packet log to write (replaced if it exists), or None.
        rate_hz: the target rate, in [1, 1000] (``protocol.rate.MIN_RATE_HZ``,
            ``MAX_RATE_HZ``: what a Hello may announce); a slower file sets the stream's rate.
        curve_dir: a key folder (``facewire keys generate``) to encrypt and admit only
            authorised receivers, or None for plain TCP.
        status: called about once per second from this thread with ``seconds``, ``frames``,
            ``fps``, ``payload_kbps`` (measured over the last period), ``face`` (the last
            frame had one), ``receivers`` and ``updates`` (model updates learned so far).
        stop: set it (from another thread) to stop cleanly.
        loop: start a video file again when it ends (until stopped).
        frames: which frames of a file or folder, by index (step 1; a camera ignores it).
        start: hold the first frame until it is set, or None to start at once (module
            docstring).
        learn: learn unseen appearance as model updates (``sender.learn``).
        updates: the session's model updates as served to receivers, or None for a store of
            the sender's own; the updates the pipeline learns are published into it, and
            others may be from any thread (``UpdateStore.publish_update``).
        heal: while learning, heal the base texture too (``sender.heal``: texture patches).
        insecure: listen without CURVE beyond loopback all the same (module docstring).
        warn: called once, before streaming (the model, source and sockets accepted),
            with ``sender.pipeline.identity_warning``'s line when the model cannot hold its
            person (no face descriptors).
        clock: the sender's clock (``protocol.clock``): capture times and the answers to
            time requests; ``time.monotonic`` but in tests.
        audio: send the voice (module docstring, "Voice"); False: the face alone.
        mic: the microphone to take the voice from (``sender.voice.MicVoice``), or None for
            the file's own sound track (a camera without one sends no voice).
        voice_bitrate: Opus's rate, bit/s (``protocol.opus``).

    Returns:
        ``frames``, ``packets``, ``face_frames``, ``seconds`` (first frame to stop), ``fps``,
        ``payload_kbps``, ``cpu_percent`` (the process's CPU time over ``seconds``; 100 is
        one core), ``receivers_max``, ``updates`` (model updates learned), ``log`` (path or
        None), ``model_sha256``,
        ``model_bytes``, ``model_chunks``, ``rate_hz`` (the stream's), ``endpoint``,
        ``control_endpoint``, ``encrypted``, ``warning`` (``unencrypted_warning`` or None),
        ``control`` (``hello_requests``, ``chunk_requests``, ``update_requests``,
        ``update_bytes``, ``errors``), ``update_bytes_total`` (the updates' bytes),
        ``voice`` (``"file"``, the mic's name, or None), ``voice_packets``, ``audio_kbps``
        (voice packets' bytes over ``seconds``) and ``stopped`` (``end``, ``stop`` or
        ``interrupt``).

    Raises:
        ValueError: rate out of range, or a frame range with a step.
        TransportError: a bad endpoint, a port in use, or beyond loopback without keys or
            ``insecure``.
        ModelFileError, KeyFileError: a missing or invalid model or key folder (named).
        LogError: the log cannot be written (named).
        CaptureError: no such camera, an unreadable or empty video (named).
    """
    _check_rate(rate_hz)
    control_at = control_endpoint(bind)
    check_plaintext(bind, curve_dir, insecure)
    stop = stop if stop is not None else threading.Event()
    report = status if status is not None else (lambda _: None)
    model, data = _read_model(model_path)
    curve = server_keys(curve_dir) if curve_dir is not None else None
    with ExitStack() as stack:
        src = stack.enter_context(open_source(str(source), rate_hz, frames=frames))
        rate = float(min(rate_hz, src.rate_hz))
        # bound before the model's pipeline is set up: a port in use fails at once
        publisher = stack.enter_context(PacketPublisher(bind, curve))
        server = stack.enter_context(ControlServer(control_at, curve))
        peers = stack.enter_context(PeerCounter(publisher))
        pipeline = SenderPipeline(model, sender_camera(src.width, src.height), rate,
                                  learn=learn, background=True, heal=heal,
                                  identify_apart=True)
        stack.callback(pipeline.close)
        identity = identity_warning(model, model_path)
        if identity is not None and warn is not None:  # once the source and sockets are up
            warn(identity)
        voice = _voice_source(source, src, audio, mic, warn or (lambda _: None))
        encoder = None if voice is None else Encoder(voice_bitrate)
        hello = pipeline.hello()
        if voice is not None:
            hello = dataclasses.replace(hello, voice_bitrate=voice_bitrate)
        chunks = model_chunks(data, hello.model_sha256)
        log = stack.enter_context(_log_writer(record, hello)) if record is not None else None
        store = updates if updates is not None else UpdateStore(hello.model_sha256)
        if store.model_sha256 != hello.model_sha256:
            raise ValueError(f"updates: a store of model {store.model_sha256[:12]}, this "
                             f"sender's model is {hello.model_sha256[:12]}")
        responder = Responder(server, hello, chunks, store, clock=clock)
        responder.start()
        stack.callback(responder.stop)
        slots = SlotClock(rate, MAX_LAG_S, clock, stop.wait)
        try:
            counts, stopped = _stream(src, pipeline, publisher, log, peers, slots, loop, stop,
                                      report, start, store, responder, encoder, voice)
        except CaptureError:
            if log is not None and log.records == 0:
                log.close()
                log.path.unlink(missing_ok=True)
            raise
    return {**_rates(counts), "log": None if record is None else str(record),
            "model_sha256": hello.model_sha256, "model_bytes": len(data),
            "model_chunks": len(chunks), "rate_hz": rate, "endpoint": bind,
            "control_endpoint": control_at, "encrypted": curve is not None,
            "warning": unencrypted_warning(bind, curve_dir),
            "control": dict(responder.counts), "update_bytes_total": store.bytes_total,
            "voice": None if voice is None else mic or "file", "stopped": stopped}


def _check_rate(rate_hz: object) -> None:
    if isinstance(rate_hz, bool) or not (isinstance(rate_hz, (int, float)) and
                                         MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ):
        raise ValueError(f"rate_hz: expected a number in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}], "
                         f"got {rate_hz!r}")


def _rates(counts: dict[str, Any]) -> dict[str, Any]:
    """The frame loop's counts, with its seconds and CPU time turned into rates."""
    counts = dict(counts)
    seconds, cpu = counts.pop("seconds"), counts.pop("cpu_seconds")
    per_second = 1.0 / seconds if seconds > 0 else 0.0
    voice_bytes = counts.pop("voice_bytes")
    return {**counts, "seconds": round(seconds, 3),
            "fps": round(counts["frames"] * per_second, 2),
            "payload_kbps": round(payload_kbps(counts["packets"] * per_second), 3),
            "audio_kbps": round(voice_bytes * 8 * per_second / 1000, 3),
            "cpu_percent": round(100 * cpu * per_second, 1)}


def _stream(src: Source, pipeline: SenderPipeline, publisher: PacketPublisher,
            log: LogWriter | None, peers: PeerCounter, slots: SlotClock, loop: bool,
            stop: threading.Event, report: Status, hold: threading.Event | None,
            store: UpdateStore, responder: Responder, encoder: Encoder | None = None,
            voice: VoiceSource | None = None) -> tuple[dict[str, Any], str]:
    """The frame loop of ``send``: returns the counts and why it stopped. With ``hold``,
    the first frame waits until it is set (or ``stop`` is). Each packet's seq is its slot
    (``sender.slots``); once the first frame has set the slots' origin, the Hello announces
    it (``clock_origin_s``). An update the pipeline learns on a frame is published to the
    receivers (``store``) in its bytes and logged, after that frame's packet (which still
    names the version before it). The voice, when there is one, starts on its own thread once
    the slots' origin is settled (``_start_voice``)."""
    counts: dict[str, Any] = {"frames": 0, "packets": 0, "face_frames": 0, "receivers_max": 0,
                              "updates": 0, "voice_packets": 0, "voice_bytes": 0}
    passes = [0.0]
    talker: VoiceThread | None = None
    start = cpu = None
    window = (0.0, 0)  # (start of the status period, frames up to its first)
    face = False
    epoch = time.time() - time.monotonic()  # log times: Unix, but never stepping back
    stopped = "end"
    try:
        while hold is not None and not hold.wait(CONTROL_POLL_MS / 1000) \
                and not stop.is_set():
            pass
        for image, t, slot in _frames(src, slots, loop, stop, passes):
            if stop.is_set():
                stopped = "stop"
                break
            if start is None:  # the stream's time counts from its first frame's arrival
                start, cpu = time.monotonic(), time.process_time()
                window = (start, 0)
            if responder.hello.clock_origin_s != slots.origin_s:
                responder.announce(dataclasses.replace(responder.hello,
                                                       clock_origin_s=slots.origin_s))
            pipeline.set_slot(slot)
            out = pipeline.process(image, t)
            publisher.send(out.packet)
            if log is not None:
                log.write(out.packet, epoch + time.monotonic())
            if out.update is not None and out.update_bytes is not None:
                store.publish_update(out.update.serial, out.update_bytes)
                if log is not None:
                    log.write_update(epoch + time.monotonic(), out.update.serial,
                                     out.update_bytes)
            if talker is None and voice is not None and encoder is not None \
                    and counts["frames"] >= (0 if isinstance(src, CameraSource) else 1):
                talker = _start_voice(voice, encoder, t - slot / slots.rate_hz, passes,
                                      slots, publisher, log, responder, epoch)
            if isinstance(voice, FileVoice) and talker is not None \
                    and slots.origin_s is not None:
                voice.lag_s = slots.origin_s - talker.origin_s  # the face's clock moved
            now = time.monotonic()
            face = out.points is not None
            counts["frames"] += 1
            counts["packets"] += 1
            counts["face_frames"] += face
            counts["updates"] += out.update is not None
            if now - window[0] >= STATUS_PERIOD_S:
                report(_status(counts, peers, now - start, now - window[0],
                               counts["frames"] - window[1], face))
                window = (now, counts["frames"])
        else:
            stopped = "stop" if stop.is_set() else "end"
    except KeyboardInterrupt:
        stopped = "interrupt"
    if talker is not None:
        talker.stop()
        counts["voice_packets"], counts["voice_bytes"] = talker.packets, talker.bytes
    peers.count()
    counts["receivers_max"] = peers.most
    counts["seconds"] = 0.0 if start is None else time.monotonic() - start
    counts["cpu_seconds"] = 0.0 if cpu is None else time.process_time() - cpu
    return counts, stopped


def _voice_source(source: str, src: Source, audio: bool, mic: str | None,
                  warn: Callable[[str], None]) -> VoiceSource | None:
    """Where the voice comes from (module docstring, "Voice"), or None, said in one line."""
    if not audio:
        return None
    try:
        if mic is not None:
            return MicVoice(mic)
        if isinstance(src, CameraSource) or Path(source).is_dir():
            warn(f"{source} has no sound: the face goes without voice (give --mic DEVICE)")
            return None
        sound = read_sound(source)
    except (VoiceSourceError, SoundError) as error:
        warn(f"{error}; the face goes on without voice")
        return None
    if sound is None:
        warn(f"{source} has no sound track: the face goes without voice")
        return None
    return FileVoice(sound)


def _start_voice(voice: VoiceSource, encoder: Encoder, t0: float, passes: list[float],
                 slots: SlotClock, publisher: PacketPublisher, log: LogWriter | None,
                 responder: Responder, epoch: float) -> VoiceThread:
    """Start the voice thread; its frames numbered from the slots' origin (a file's, cut
    from ``t0``, the stream time of slot 0) or, for a microphone, from now; the Hello
    announces the origin."""
    if isinstance(voice, FileVoice):
        assert slots.origin_s is not None  # set by the first frame
        origin = slots.origin_s
        voice.t0, voice.passes = t0, passes
    else:
        origin = time.monotonic()

    def publish(data: bytes) -> None:
        publisher.send(data)
        if log is not None:
            log.write_voice(data, epoch + time.monotonic())

    talker = VoiceThread(voice, encoder, origin, publish)
    responder.announce(dataclasses.replace(responder.hello, voice_origin_s=origin))
    talker.start()
    return talker


def _status(counts: dict[str, Any], peers: PeerCounter, elapsed: float, period: float,
            frames: int, face: bool) -> dict[str, Any]:
    return {"seconds": round(elapsed, 1), "frames": counts["frames"],
            "fps": round(frames / period, 1),
            "payload_kbps": round(payload_kbps(frames / period), 2),
            "face": face, "receivers": peers.count(), "updates": counts["updates"]}
