"""The live receive loop: ``facewire receive --connect tcp://HOST:5555``.

Session
-------
1. Sockets. A SUB socket for packets at ``connect`` and a DEALER for control requests at
   ``protocol.transport.control_endpoint(connect)`` (port + 1), both under CURVE when a key
   folder is given (``protocol.keys.client_keys``). ZeroMQ connects in the background and
   reconnects by itself: a sender may start after the receiver, stop, and come back. The
   packet socket is opened anew after ``REOPEN_S`` without a packet, since libzmq does not
   reconnect one whose peer broke the protocol (a frame over its size limit).
2. Hello (``receiver.link.SenderLink``: the Hello, and when to ask it again). Asked until a
   sender answers; meanwhile the status says that the receiver waits, where, and for how
   long. ``idle_timeout_s`` ends the wait. From here on the sender's clock is estimated on a
   thread of its own (``receiver.clocksync``).
3. Model (``receiver.acquire.ModelAcquirer``): with ``model_path``, the file's sha256 must
   be the Hello's, or ``ReceiveError``; without, the model cache by the Hello's sha256, else
   the sender's file, fetched in chunks over the control channel by its sha256 and verified
   before it is cached and used. A sender that stops answering mid-transfer sends the
   receiver back to step 2; a model that keeps failing its sha256 ends the session.
4. Play (below), until ``stop`` is set, ``max_frames`` frames are out, or no packet (and
   no control reply) has come for ``idle_timeout_s``.

Control requests follow ZeroMQ's "lazy pirate" pattern (``receiver.acquire.ControlChannel``):
one at a time, each with a timeout, the socket reopened after a timeout or a bad reply.

Model updates (``receiver.updates``): once a model is adopted, a thread of its own (with its
own control socket) fetches the session's updates up to the newest serial the Hello or a
packet names, in order, verified and applied. Each slot is rendered with the newest version
fetched that is no newer than its packet's serial (``FrameState.serial``): a version is taken
at the first packet that refers to it (the changed regions uploaded again,
``StateRenderer.set_model``; the playout's rest Q follows it), and a slot whose version is
still on the way is rendered with the layers held, its Q clamped, counted (``clamped``) and
said on the status line. A Hello rechecked after a restart whose ``model_serial`` is below the
receiver's version starts the updates anew from the model file (a new session of the same
model; a restarted sender that has already issued more updates than the receiver holds is
not told apart: the Hello carries no session identity).

Threads, packets and playing on arrival
---------------------------------------
Two threads, so that the network never waits for rendering nor rendering for the network:

- the reader thread owns the SUB socket; it stamps each packet with its arrival time (one
  monotonic clock), appends it to a queue of at most ``QUEUE_PACKETS`` (beyond that,
  dropped: ``overflow``) and wakes the render loop;
- the render loop (the calling thread) owns the playout buffer (``receiver.playout.Playout``),
  the renderer and the outputs; a video file is encoded on the writer's own thread
  (``receiver.output.VideoWriter``), so encoding does not hold up the next frame either.

The render loop moves the queued packets into the playout in arrival order and pops a
``FrameState`` as soon as the playout is ``ready`` (the next slot's packet is in): a packet on
time is rendered as soon as it arrives, with no buffering delay. A slot whose packet is
missing waits until ``Playout.due()`` (its expected arrival plus the adaptive margin, one slot
period or more) and is then concealed; in between the loop sleeps until a packet arrives or
the deadline passes. A renderer slower than the stream:

- with a live ``view``, every packet that has arrived is pushed, and the playout's skip rule
  gives up the slots in excess (``skipped``, ``discarded``), so the picture stays at most a
  few slots late;
- without one (a file, or nothing), every slot is output: the playout's skip rule is off,
  packets stay in the reader's queue while the playout holds half its window ahead (so a
  packet is never far enough ahead to look like a restarted stream), and
  - by default every slot is rendered: the latency grows as far as it must (bounded by the
    queue) and the loop catches up when the stream pauses or ends (a recording: every
    frame drawn);
  - with ``keep_up`` (a live picture that is written, as the demo's receiver), a slot is not
    drawn when the render process has ``depth`` frames in flight and the next slot's packet
    is already in, or when the video file's encoder is behind (``WRITER_BEHIND`` frames
    waiting for it: a phone's 1080x1920 encodes at about 17 frames/s here): its output
    frame repeats the frame out before it (``repeated``), with that frame's arrival and
    capture times (its latency is what the viewer sees, and the voice keeps to it), and in
    the file it is a hold (``receiver.output``: not encoded, the frame before lasts a slot
    longer), so the file keeps the stream's timeline, and the latency stays within a few
    draws (the frames in flight and the one in hand) however far the renderer or the
    encoder falls behind.

The same holds for the packets that arrive before the loop starts (the reader runs from the
start, while the Hello is asked, the model fetched and the renderer set up): without a view
they are played, late; with a view they are dropped (``ignored``), since the picture is to be
live.

Per slot: ``receiver.scene.StateRenderer`` (morph, sender's view, render), as in replay, run
in a process of its own (``receiver.renderprocess.RenderProcess``): the render loop waits for
each frame without the GIL, so the reader thread and the encoder run while it is drawn.

Two frames in flight. A slot popped is submitted to the render process and the loop goes on:
it takes packets, and submits the next slot if it is ready, while the child draws. A frame
is out (shown, written, handed to ``on_frame``) as soon as it is back if the loop has nothing
else to do (it waits on the render pipe, at most until the next deadline), or, when a second
frame is in flight and a third is ready, once the third is submitted: so a loop that is
behind (a backlog of slots) spends its own time on frame n (the copy out, the view, the file,
``on_frame``) while frames n + 1 and n + 2 are drawn, and keeps the stream's rate when the
draw and its own work each take less than a period, not only their sum. Frames go out in
slot order; a frame is never held back for the next slot's packet. Before the renderer or
the playout changes (a new Hello), and at the end, the frames in flight go out first.

Output frames (the file, and ``frames`` in the summary)
------------------------------------------------------
A *stream* is what the playout plays between two resyncs (a restarted sender starts a new
one). The output holds one frame per slot of each stream from its first played packet to its
last: one frame per packet played, and one per slot concealed between two played packets of
the same stream (its packet lost, or late: ``lost``). Slots before a stream's first packet
(the playout's countdown) and after its last (the sender stopped, or restarted and its new
stream has not started) are not written. A concealed slot is therefore written when the next
packet of its stream plays, and rendered then; the live view shows it at its tick. A gap of
more than ``MAX_GAP_S`` is not written at all: the stream counts as ended where the gap
began, and its next packet starts a new one (this also bounds the slots held back). When the
loop ends on ``stop`` or on the idle timeout, the packets already received are played first
(ticks without waiting, a bounded number of them), so every packet received is in the output:
on a link without loss, ``frames == received``. ``max_frames`` ends at once, after that many
frames. The output size is ``size``, or the first Hello's camera size (scaled down to at
most ``MAX_SIZE`` on its longer side: a Hello may announce up to 16384; for a live picture,
a ``view`` or ``keep_up``, to at most ``LIVE_SIZE``: a phone's 1080x1920 took 78 ms a draw
on the 2-core test machine beside its sender, over a 25 Hz slot, and 540x960 34 ms); a later
Hello with another camera is rendered at that size (its intrinsics scaled, ``sender_view``).

Sender restart
--------------
A restarted sender numbers its packets from 0 again (or from anywhere): the playout resyncs
(``receiver.playout``, restart rules) and the receiver asks for the Hello again, as it does at
the other signs of ``receiver.link`` (packets resuming after a silence, a Hello without the
clock). An identical Hello changes nothing; another camera or clock is used from the next
frame (``Change.DETAILS``). Another rate means a new playout; a new model sha256 means that
model (cache, else fetched; with ``model_path``: ``ReceiveError``), a new renderer and a new
playout. A new playout starts like the first one: the packets the old one still held count as
``discarded``, and those that arrived meanwhile (while the model was fetched) are played late
or ``ignored``, as above. Until the Hello is answered the loop goes on rendering with what it
has, asking again as ``receiver.link`` says.

Glass-to-glass latency (``protocol.clock``): for each frame played from a packet, the time it
is out (written, shown and handed to ``on_frame``) minus its capture time, which the Hello's
clock and the packet's seq give on the sender's clock, moved to this host's by the
``receiver.clocksync`` estimate. None while either is missing (a sender that announces no
clock, or answers no time request).

Voice (``receiver.voiceplayer``): with ``audio`` the packet thread hands voice packets to the
player before the face's queue; its jitter buffer is pulled by the speaker (``speaker``) or a
clock of its own, each frame played goes into the video file's sound track where it was
heard beside the frames (``--out``: the first sound at its out time less the first frame's),
and the summary carries the voice's counts and the sync (``av_skew_ms_*``).

Statistics (the summary, the live statistics): ``receiver.stats``. The callbacks see what it
counts: ``on_packet`` each packet entering the playout, ``on_frame`` each output frame.

Size: this module is over 750 lines because the docstring above states the whole session's
contract (about 120 lines) beside about 620 lines of code that keep it; model acquisition,
the model updates, the statistics and the render process already live apart
(``receiver.acquire``, ``receiver.updates``, ``receiver.stats``,
``receiver.renderprocess``).
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facewire.models.modelfile import PersonModel, load_model
from facewire.protocol.clock import capture_s
from facewire.protocol.control import Hello
from facewire.protocol.keys import CurveClient, client_keys
from facewire.protocol.transport import PacketSubscriber, control_endpoint
from facewire.receiver.acquire import ModelAcquirer, ReceiveError
from facewire.receiver.clocksync import ClockSync
from facewire.receiver.link import RECHECK_EVERY_S, RECHECK_TIMEOUT_S, Change, SenderLink
from facewire.receiver.modelcache import ModelCache
from facewire.receiver.output import QUEUE_FRAMES, FrameFolderWriter, OutputError, VideoWriter
from facewire.receiver.packetreader import PacketReader
from facewire.receiver.playout import FrameState, Playout
from facewire.receiver.renderprocess import RenderProcess
from facewire.receiver.scene import rest_q
from facewire.receiver.stats import ReceiveStats
from facewire.receiver.updates import UpdateFetcher
from facewire.receiver.voiceplayer import VoicePlayer, voice_capture

REOPEN_S = 8.0
MAX_GAP_S = 10.0
QUEUE_PACKETS = 4096
MAX_SIZE = 4096
LIVE_SIZE = 960  # the longer side of a live picture by default (module docstring)
WRITER_BEHIND = QUEUE_FRAMES // 2  # frames waiting for the file's encoder: it is behind
_POLL_MS = 50
_POLL_S = _POLL_MS / 1000

Status = Callable[[str], None]
View = Callable[[np.ndarray, dict[str, Any]], None]
OnFrame = Callable[[np.ndarray, FrameState], None]
OnPacket = Callable[[bytes, float], None]


def receive(connect: str, model_path: str | os.PathLike[str] | None = None,
            out: str | os.PathLike[str] | None = None,
            frames_dir: str | os.PathLike[str] | None = None, view: View | None = None,
            curve_dir: str | os.PathLike[str] | None = None,
            cache_dir: str | os.PathLike[str] | None = None,
            size: tuple[int, int] | None = None, status: Status | None = None,
            stop: threading.Event | None = None, max_frames: int | None = None,
            idle_timeout_s: float | None = None, on_frame: OnFrame | None = None,
            on_packet: OnPacket | None = None,
            ready: threading.Event | None = None, audio: bool = True,
            speaker: str | None = None, keep_up: bool = False) -> dict[str, Any]:
    """Receive a sender's stream and render it until stopped (module docstring).

    Args:
        connect: the sender's packet address, ``tcp://HOST:PORT`` (control: port + 1).
        model_path: the person model; its sha256 must be the sender's. Fetched when None.
        out: an H.264 ``.mp4`` to write (``receiver.output.VideoWriter``).
        frames_dir: a folder for PNG frames (``FrameFolderWriter``); not with ``out``.
        view: called with each rendered frame ((H, W, 3) uint8 RGB) and the live statistics
            (``receiver.stats.LIVE_KEYS``), e.g. ``LiveView.publish``; plays live.
        curve_dir: a CURVE key folder (``protocol.keys.client_keys``).
        cache_dir: the model cache folder (``receiver.modelcache.default_folder`` if None).
        size: (width, height) of the output; the sender camera's size by default (module
            docstring: at most ``MAX_SIZE``, ``LIVE_SIZE`` for a live picture).
        status: called with one line of text when the state changes, and every
            ``receiver.stats.STATUS_EVERY_S`` while playing.
        stop: set it (from another thread) to end the session cleanly, after playing the
            packets already received.
        max_frames: end after this many output frames.
        idle_timeout_s: end when no packet and no control reply came for this long (also
            while waiting for a sender); None waits for ever.
        on_frame: called with each output frame ((H, W, 3) uint8 RGB) and its slot's state,
            in output order: the frames ``out`` would hold (module docstring, "Output
            frames").
        on_packet: called with each message's bytes (corrupt ones too) and arrival time
            (``time.monotonic()`` s) as it enters the playout, in arrival order.
        ready: set once the receiver can play (a model, a renderer and a playout), e.g. the
            ``start`` of a ``sender.sender.send`` in the same process.
        audio: play the voice (module docstring, "Voice"); False: voice packets are ignored.
        speaker: the output device (index or name; "" the default output), or None to play
            into the file (and the sync measure) only.
        keep_up: a renderer slower than the stream repeats the last frame out instead of
            drawing a slot already overtaken (module docstring); False: every slot drawn.

    Returns:
        The summary (``receiver.stats``, and ``connect``, ``out``, ``width``, ``height`` and
        the model's keys, ``receiver.acquire``).

    Raises:
        ReceiveError: bad arguments; the model file is not the sender's; the sender's model
            is not a valid model file or keeps failing its sha256.
        ModelFileError / KeyFileError / TransportError / OutputError / EGLUnavailable: a
            missing or bad model file or key folder, a bad address, an unwritable output,
            no headless OpenGL.
    """
    size = _check_options(out, frames_dir, view, size, max_frames, idle_timeout_s,
                          on_frame, on_packet, ready)
    local = load_model(model_path) if model_path is not None else None
    curve = client_keys(curve_dir) if curve_dir is not None else None
    session = _Session(connect, curve, local, ModelCache(cache_dir), out, frames_dir,
                       view or None, size, status, stop, max_frames, idle_timeout_s,
                       on_frame, on_packet, ready, audio, speaker, keep_up)
    return session.run()


def _check_options(out: str | os.PathLike[str] | None,
                   frames_dir: str | os.PathLike[str] | None, view: object, size: object,
                   max_frames: object, idle_timeout_s: object, on_frame: object,
                   on_packet: object, ready: object) -> tuple[int, int] | None:
    """Validate ``receive``'s options (``ReceiveError`` names the first that is not valid);
    the size as a tuple of ints, or None."""
    if out is not None and frames_dir is not None:
        raise ReceiveError("--out and --frames: give one or the other, not both")
    for name, path in (("--out", out), ("--frames", frames_dir)):
        if path is not None and Path(path).exists() and \
                Path(path).is_dir() != (name == "--frames"):
            raise ReceiveError(f"{name} {path}: exists and is "
                               f"{'not ' if name == '--frames' else ''}a folder")
    if out is not None and not Path(out).resolve().parent.is_dir():
        raise ReceiveError(f"--out {out}: its folder does not exist")
    if view is not None and view is not False and not callable(view):
        raise ReceiveError(f"view: expected a callable (frame, stats) or None, got "
                           f"{type(view).__name__}")
    for name, callback in (("on_frame", on_frame), ("on_packet", on_packet)):
        if callback is not None and not callable(callback):
            raise ReceiveError(f"{name}: expected a callable or None, got "
                               f"{type(callback).__name__}")
    if ready is not None and not isinstance(ready, threading.Event):
        raise ReceiveError(f"ready: expected a threading.Event or None, got "
                           f"{type(ready).__name__}")
    if max_frames is not None and (isinstance(max_frames, bool) or
                                   not isinstance(max_frames, (int, np.integer))
                                   or max_frames < 1):
        raise ReceiveError(f"max_frames: expected an integer >= 1, got {max_frames!r}")
    if idle_timeout_s is not None and not (
            isinstance(idle_timeout_s, (int, float, np.integer, np.floating))
            and math.isfinite(idle_timeout_s) and idle_timeout_s > 0):
        raise ReceiveError(f"idle_timeout_s: expected a number > 0, got {idle_timeout_s!r}")
    if size is None:
        return None
    if not isinstance(size, (tuple, list)) or len(size) != 2 or not all(
            isinstance(v, (int, np.integer)) and 0 < v <= MAX_SIZE for v in size):
        raise ReceiveError(f"size: expected a width and height in [1, {MAX_SIZE}], "
                           f"got {size!r}")
    return int(size[0]), int(size[1])


class _End(Exception):
    """Unwinds the session: why it ends (``ended`` in the summary)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class _Job:
    """A frame on its way out (module docstring, "Two frames in flight").

    Attributes:
        state: the slot played.
        show: handed to the live view.
        out: an output frame (``_Session._emit``).
        drawn: submitted to the render process (else out with the last frame's image and
            times if ``repeat``, else without an image: a concealed slot when output frames
            go nowhere).
        capture: its capture time on this host's clock (a played packet's), or None.
        repeat: not drawn, out as the frame out before it (``keep_up``, behind).
    """

    state: FrameState
    show: bool
    out: bool
    drawn: bool
    capture: float | None = None
    repeat: bool = False


class _Session:
    """One ``receive`` call: its sockets, model, renderer, playout, output and counts."""

    def __init__(self, connect: str, curve: CurveClient | None, local: PersonModel | None,
                 cache: ModelCache, out: str | os.PathLike[str] | None,
                 frames_dir: str | os.PathLike[str] | None, view: View | None,
                 size: tuple[int, int] | None, status: Status | None,
                 stop: threading.Event | None, max_frames: int | None,
                 idle_timeout_s: float | None, on_frame: OnFrame | None,
                 on_packet: OnPacket | None, ready: threading.Event | None,
                 audio: bool = True, speaker: str | None = None, keep_up: bool = False) -> None:
        self.connect = connect
        self.keep_up = keep_up
        self.curve, self.local, self.cache = curve, local, cache
        self.out, self.frames_dir, self.view, self.size = out, frames_dir, view, size
        self.on_frame, self.on_packet, self.ready = on_frame, on_packet, ready
        self.say = status or (lambda _: None)
        self.stop = stop if stop is not None else threading.Event()
        self.max_frames, self.idle_timeout_s = max_frames, idle_timeout_s
        # what is played: set by _adopt, before anything is played
        self.hello: Hello | None = None
        self.scene: RenderProcess | None = None
        self.playout: Playout | None = None
        self.writer: VideoWriter | FrameFolderWriter | None = None
        self.pending: list[FrameState] = []  # concealed slots awaiting the stream's next packet
        self.flight: deque[_Job] = deque()  # frames on their way out, in output order
        # the last frame out with an image: it, its packet's arrival and its capture time
        self.last_out: tuple[np.ndarray | None, float | None, float | None] = (None, None, None)
        self.played = 0  # packets played by the current playout
        self.restarts_seen = 0  # the current playout's restarts already handled
        self.stream_played = False  # a stream is open: its next packet writes the pending
        self.playing_since = 0.0  # when the current playout was set up
        self.last_contact = time.monotonic()  # the last control reply or ready loop
        self.stats = ReceiveStats()
        self.updates: UpdateFetcher | None = None  # the current session's model updates
        self.base: PersonModel | None = None  # its model file (version 0)
        self.version = 0  # the model version rendered
        self.started = time.monotonic()
        self.first_out: float | None = None  # when the first output frame was out
        self.sound_started = False
        control_endpoint(connect)  # a malformed address is refused before any socket opens
        # the links to the sender: open from here, closed by run() (at once if one fails)
        with contextlib.ExitStack() as links:
            self.voice = VoicePlayer(speaker, self._sound, self.say, self._voice_capture) \
                if audio else None
            if self.voice is not None:
                links.callback(self.voice.close)
            self.reader = PacketReader(lambda: PacketSubscriber(self.connect, self.curve),
                                       QUEUE_PACKETS, REOPEN_S,
                                       divert=None if self.voice is None else self.voice.push)
            links.callback(self.reader.close)
            self.link = SenderLink(self.connect, self.curve)
            links.callback(self.link.close)
            self._links = links.pop_all()
        self.clock: ClockSync | None = None  # from the first Hello
        self.acquirer = ModelAcquirer(self.connect, self.link.control, self.cache, self.local,
                                      self.say, self._check_end, self._touch)

    # -- the session -----------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        with self._links as stack:
            stack.callback(self._release)
            try:
                while True:  # until _End: _play returns only by raising it
                    hello = self._await_hello()
                    if self.clock is None:
                        self.clock = ClockSync(self.link.endpoint, self.curve)
                    model = self.acquirer.obtain(hello)
                    if model is not None:
                        self._adopt(hello, model)
                        self._play()
            except _End as end:
                ended = end.reason
            if self.voice is not None:
                self.voice.close()  # no sound after the file is closed
            if self.writer is not None:
                self.writer.close()
        return self._summary(ended, time.monotonic() - self.started)

    def _release(self) -> None:
        if self.clock is not None:
            self.clock.close()
        if self.updates is not None:
            self.updates.close()
        if self.writer is not None:
            with contextlib.suppress(Exception):
                self.writer.close()  # closed already on a normal end (then no effect)
        if self.scene is not None:
            self.scene.release()

    def _touch(self) -> None:
        """A sign of the sender: a control reply."""
        self.last_contact = time.monotonic()

    def _idle_s(self) -> float:
        """Seconds since the last sign of a sender (packet, control reply) or ready loop."""
        return time.monotonic() - max(self.last_contact, self.reader.last_arrival or 0.0)

    def _check_end(self) -> None:
        if self.stop.is_set():
            raise _End("stop")
        if self.idle_timeout_s is not None and self._idle_s() > self.idle_timeout_s:
            raise _End("idle_timeout")

    def _await_hello(self) -> Hello:
        """Ask until a sender answers, saying that the receiver waits (``receiver.link``)."""

        def timeout() -> float:
            if self.idle_timeout_s is None:
                return float("inf")
            return max(0.05, self.idle_timeout_s - self._idle_s())

        answer = self.link.await_hello(self._check_end, timeout, self.say)
        self._touch()
        self.stats.counts["hellos"] += 1
        return answer.hello

    # -- playing ---------------------------------------------------------------------------

    def _adopt(self, hello: Hello, model: PersonModel) -> None:
        """Play this Hello with this model: a renderer if the model is new, a new playout
        and clock; the packets queued meanwhile are played or ignored (module docstring)."""
        if self.size is None:  # the sender's camera, at most MAX_SIZE (live: LIVE_SIZE)
            cam, live = hello.camera, self.keep_up or self.view is not None
            scale = min(1.0, (LIVE_SIZE if live else MAX_SIZE) / max(cam.width, cam.height))
            self.size = (max(1, round(cam.width * scale)), max(1, round(cam.height * scale)))
        self._flush()  # the frames in flight out with the renderer and playout they had
        if self.scene is not None and self.scene.model is not model:
            self.scene.release()
            self.scene = None
        if self.scene is None:
            self.scene = RenderProcess(model, *self.size, hello.camera)
        if self.updates is None or self.updates.base_sha256 != hello.model_sha256:
            self._start_updates(model)
        assert self.updates is not None  # just started
        self.updates.want(hello.model_serial)
        self.scene.hello_camera = hello.camera
        if self.playout is not None:
            self.stats.retire(self.playout, self.played)
        self.hello = hello
        self.link.take(hello)
        self.playout = Playout(hello.rate_hz, rest_q=rest_q(model), skip=self.view is not None)
        self.played, self.restarts_seen, self.stream_played = 0, 0, False
        self.pending.clear()
        now = time.monotonic()
        self.playing_since = now
        if self.view is not None:
            self.stats.counts["ignored"] += self.reader.discard()
        self.last_contact = now  # the idle timeout counts from a ready loop
        self.say(f"playing {self.connect} at {hello.rate_hz:g} Hz, {self.size[0]}x"
                 f"{self.size[1]}: waiting for packets")
        if self.ready is not None:
            self.ready.set()

    def _play(self) -> None:
        """Play until the session ends: raises ``_End``, after playing what was received
        (not after ``max_frames``)."""
        assert self.playout is not None  # _adopt came first
        try:
            while True:
                self._check_end()
                self.reader.arrived.clear()  # before taking: a packet after it wakes the wait
                self._feed()
                now = time.monotonic()
                due = self.playout.due()
                if self.playout.ready or (due is not None and now >= due):
                    self._tick(live=True)
                else:
                    wait = _POLL_S if due is None else min(due - now, _POLL_S)
                    if self.scene is not None and self.scene.in_flight:
                        if self.scene.wait(wait):  # a frame drawn: out at once
                            self._finish(*self._collect())
                    else:
                        self.reader.arrived.wait(wait)
                line = self.stats.status_line(time.monotonic(), self.playout, self.connect,
                                              self.reader.last_arrival, self.playing_since,
                                              self.version, self.updates)
                if line is not None:
                    self.say(line)
        except _End as end:
            if end.reason != "max_frames":
                self._drain()
            raise

    def _drain(self) -> None:
        """Play what was received, concealing missing slots without waiting (module
        docstring)."""
        self.reader.close()
        if self.playout is None:
            return
        per_packet = self.playout.window + self.playout.depth + 1  # pops, at most
        for _ in range((self.reader.queued() + self.playout.ahead + 64) * per_packet):
            self._feed()
            if self.reader.queued() == 0 and self.playout.drained:
                break
            self._tick(live=False)
        self._flush()

    def _feed(self) -> None:
        """Move the queued packets into the playout, in arrival order (without a view only
        while it holds less than half its window ahead: module docstring), and notice a
        restarted stream."""
        assert self.playout is not None  # _adopt came first
        limit = None if self.view is not None else self.playout.window // 2
        while limit is None or self.playout.ahead < limit:
            item = self.reader.take()
            if item is None:
                break
            self._note_packet(*item)
            self.playout.push(*item)
        restarts = self.playout.stats["restarts"]
        if restarts > self.restarts_seen:
            self.restarts_seen = restarts
            self.pending.clear()
            self.stream_played = False
            self.link.note_restart()
            self.say(f"the stream from {self.connect} restarted: asking for its Hello")

    def _tick(self, live: bool) -> None:
        """Check the Hello if due (only ``live``: not while draining), pop one state and
        show it. A changed Hello adopted (a new playout) ends the tick without a pop."""
        assert self.hello is not None and self.scene is not None and self.playout is not None
        if live and self.link.check_due(time.monotonic()) and self._recheck():
            return
        state = self.playout.pop()
        if state.seq is None:
            return
        self._follow(state.serial)
        if state.arrival_s is None:  # concealed: shown now, written if the stream goes on
            if self.view is not None:
                self._draw(_Job(state, show=True, out=False, drawn=True))
            if self.stream_played:
                self.pending.append(state)
                if len(self.pending) > MAX_GAP_S * self.hello.rate_hz:
                    self.pending.clear()  # too long a gap: the stream ends here
                    self.stream_played = False
            return
        self.played += 1
        if not self.stream_played:
            self.stream_played = True
            self.stats.counts["streams"] += 1
        capture = self._capture(state)
        if capture is not None:  # a sender that moved its clock's origin (receiver.link)
            self.link.note_lateness(state.arrival_s - capture, time.monotonic())
        outputs, behind = self._outputs(), self._behind()
        for concealed in self.pending:
            self.stats.counts["lost"] += 1
            self._draw(_Job(concealed, show=False, out=True, drawn=outputs and not behind,
                            repeat=outputs and behind))
        self.pending.clear()
        self._draw(_Job(state, show=self.view is not None and not behind, out=True,
                        drawn=not behind, capture=capture, repeat=behind))

    def _behind(self) -> bool:
        """With ``keep_up``: whether the slot just popped is overtaken (module docstring):
        the render process full (so a frame drawn goes out before this one) and the next
        slot's packet in, or the video file's encoder behind."""
        assert self.scene is not None and self.playout is not None  # _adopt came first
        return self.keep_up and (
            self.scene.in_flight == self.scene.depth and self.playout.ready
            or self.writer is not None and self.writer.backlog >= WRITER_BEHIND)

    def _outputs(self) -> bool:
        """Whether output frames go anywhere (a file, a folder, ``on_frame``): else a
        concealed slot is counted, not drawn."""
        return self.out is not None or self.frames_dir is not None or self.on_frame is not None

    # -- frames in flight (module docstring, "Two frames in flight") ---------------------------

    def _draw(self, job: _Job) -> None:
        """Send a frame on its way out, behind those in flight: drawn by the render process
        (when the ring is full, the oldest is collected first and sent out after this one is
        submitted, so the child draws while this thread writes), else out in its turn."""
        assert self.scene is not None  # _adopt came first
        done = None
        if job.drawn and self.scene.in_flight == self.scene.depth:
            done = self._collect()
        if job.drawn:
            self.scene.submit(job.state)
        self.flight.append(job)
        if done is not None:
            self._finish(*done)
        while self.flight and not self.flight[0].drawn:
            self._finish(self.flight.popleft(), None)

    def _collect(self) -> tuple[_Job, np.ndarray | None]:
        """The oldest frame drawn (waiting for it), the frames not drawn before it out first.
        """
        assert self.scene is not None  # _adopt came first
        while not self.flight[0].drawn:
            self._finish(self.flight.popleft(), None)
        return self.flight.popleft(), self.scene.collect()

    def _flush(self) -> None:
        """Every frame in flight out, in order (before the renderer or the playout changes,
        and at the end)."""
        while self.flight:
            if self.flight[0].drawn:
                self._finish(*self._collect())
            else:
                self._finish(self.flight.popleft(), None)

    def _finish(self, job: _Job, image: np.ndarray | None) -> None:
        """A frame out: to the live view, and as an output frame. A repeat is out with the
        image it repeats and that image's arrival and capture times: the latency and the
        glass-to-glass latency (and the voice's sync) are those of what is shown."""
        if job.repeat:
            image, arrival, capture = self.last_out
            self.stats.counts["repeated"] += 1
        else:
            arrival, capture = job.state.arrival_s, job.capture
            if image is not None:
                self.last_out = (image, arrival, capture)
        latency = None if arrival is None else time.monotonic() - arrival
        if job.show and self.view is not None and image is not None:
            self.view(image, self._live(job.state))
        if job.out:
            self._emit(job.state, image, latency, capture, job.repeat)

    def _recheck(self) -> bool:
        """Ask for the Hello again (``receiver.link``: a restart, a stream resumed, a Hello
        without the clock); True when a changed one was adopted."""
        assert self.hello is not None and self.scene is not None  # _adopt came first
        fetched = self.updates.fetched if self.updates is not None else None
        answer = self.link.ask(RECHECK_TIMEOUT_S, fetched)
        if answer is None:
            return False
        self._touch()
        self.stats.counts["hellos"] += 1
        hello = answer.hello
        if answer.change is not Change.MODEL and self.updates is not None \
                and self.base is not None:
            if answer.new_session:
                self.say(f"the sender at {self.connect} is at model version "
                         f"{hello.model_serial}, this receiver at {self.updates.fetched}: "
                         f"a new session, its updates fetched anew")
                self._start_updates(self.base)
                self.scene.set_model(self.base)
                if self.playout is not None:
                    self.playout.rest_q = rest_q(self.base)
            self.updates.want(hello.model_serial)
        if answer.change in (Change.SAME, Change.DETAILS):
            self.hello = hello  # at most another camera or clock: the next frames use it
            self.link.take(hello)
            self.scene.hello_camera = hello.camera
            return False
        self.say(f"the sender at {self.connect} now sends model {hello.model_sha256[:12]} "
                 f"at {hello.rate_hz:g} Hz")
        model = self.scene.model if answer.change is Change.RATE \
            else self.acquirer.obtain(hello)
        if model is None:
            self.link.due, self.link.next_check = True, time.monotonic() + RECHECK_EVERY_S
            return False
        self._adopt(hello, model)
        return True

    def _start_updates(self, model: PersonModel) -> None:
        """A new session's updates: fetched from ``model``, its model file (version 0)."""
        if self.updates is not None:
            self.stats.retire_updates(self.updates)
            self.updates.close()
        self.base, self.version = model, 0
        self.updates = UpdateFetcher(self.link.endpoint, self.curve, model, self.say)

    def _follow(self, serial: int) -> None:
        """Render the slot with the model version its packet's Q values refer to: the newest
        version fetched up to ``serial`` is taken (its changed regions uploaded again); a
        newer one still on the way leaves the Q clamped to the layers held, counted and
        said (``receiver.updates``)."""
        assert self.updates is not None and self.scene is not None and self.playout is not None
        if serial <= self.version:
            return
        self.updates.want(serial)
        taken = self.updates.take(serial)
        if taken is not None:
            model, self.version = taken
            self.scene.set_model(model)
            self.playout.rest_q = rest_q(model)
        if serial > self.version:
            self.stats.clamped(serial, self.version)

    def _note_packet(self, data: bytes, arrival: float) -> None:
        self.link.note_packet(arrival, clocked=self.clock is None or
                              self.clock.answers is not False)
        self.stats.packet(len(data), arrival)
        if self.on_packet is not None:
            self.on_packet(data, arrival)

    def _capture(self, state: FrameState) -> float | None:
        """A played slot's capture time on this host's clock (``protocol.clock``), or None
        without the Hello's clock or an offset estimate."""
        assert self.hello is not None and state.seq is not None and state.arrival_s is not None
        best = self.clock.best() if self.clock is not None else None
        origin = self.hello.clock_origin_s
        if best is None or origin is None:
            return None
        return capture_s(state.seq, origin, self.hello.rate_hz,
                         state.arrival_s + best.offset_s) - best.offset_s

    def _emit(self, state: FrameState, image: np.ndarray | None,
              latency: float | None, capture: float | None, repeat: bool = False) -> None:
        """One output frame: written if there is a file (a ``repeat`` held: the frame before
        lasts, ``receiver.output``) and handed to ``on_frame`` (``image`` None: it goes
        nowhere, only counted), counted, and the end of the session at ``max_frames``."""
        assert self.hello is not None and self.size is not None
        if image is not None:  # drawn when output frames go somewhere (_outputs)
            if self.writer is None and self.out is not None:
                width, height = self.size
                self.writer = VideoWriter(self.out, width, height, self.hello.rate_hz,
                                          sound=self.voice is not None)
            elif self.writer is None and self.frames_dir is not None:
                self.writer = FrameFolderWriter(self.frames_dir)
            if self.writer is not None and repeat:
                self.writer.hold()
            elif self.writer is not None:
                self.writer.write(image)
            if self.on_frame is not None:
                self.on_frame(image, state)
        now = time.monotonic()
        self.first_out = now if self.first_out is None else self.first_out
        if self.voice is not None and capture is not None:
            self.voice.face(capture, now)
        frames = self.stats.frame(now, latency, None if capture is None else now - capture)
        if self.max_frames is not None and frames >= self.max_frames:
            raise _End("max_frames")

    def _voice_capture(self, seq: int, near: float) -> float | None:
        """Voice frame ``seq``'s capture time on this host's clock (``receiver.voiceplayer``),
        or None without the Hello's voice origin or an offset estimate."""
        hello = self.hello
        best = self.clock.best() if self.clock is not None else None
        if hello is None or hello.voice_origin_s is None or best is None:
            return None
        return voice_capture(seq, hello.voice_origin_s, near + best.offset_s) - best.offset_s

    def _sound(self, pcm: np.ndarray, out: float) -> None:
        """A voice frame heard at ``out``: into the video file's sound track, placed where it
        was heard beside the frames (module docstring, "Voice"); before the first frame, none.
        """
        writer, first = self.writer, self.first_out
        if not isinstance(writer, VideoWriter) or first is None or out < first:
            return
        with contextlib.suppress(ValueError, OutputError):  # the file closing: the end
            writer.write_sound(pcm, None if self.sound_started else out - first)
            self.sound_started = True

    def _live(self, state: FrameState | None) -> dict[str, Any]:
        return self.stats.live(time.monotonic(), state, self.playout)

    def _summary(self, ended: str, seconds: float) -> dict[str, Any]:
        width, height = self.size if self.size is not None else (None, None)
        out = self.out if self.out is not None else self.frames_dir
        return {
            "connect": self.connect, "out": None if out is None else str(out),
            "width": width, "height": height,
            **self.stats.summary(self.playout, ended, seconds, self.reader.overflow,
                                 self.link.control.timeouts, self.link.control.errors,
                                 self.scene.render_seconds if self.scene else ()),
            **self.stats.update_summary(self.updates, self.version),
            **self.acquirer.info,
            **(self.clock.summary() if self.clock is not None else ClockSync.EMPTY),
            **(self.voice.summary() if self.voice is not None else {}),
        }
