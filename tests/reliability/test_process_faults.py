"""Process faults with real processes: ``facewire send`` and ``facewire receive`` on loopback.

One scene, each fault recovered from without a manual step (tests/test_live.py covers a
sender killed mid-stream and restarted, and a sender that goes on when its receiver is
killed):

1. the receiver starts before the sender: it says that it waits for a sender;
2. the sender starts (``--loop``, so that it streams until Ctrl-C): the receiver fetches the
   model, caches it and plays;
3. the receiver is killed (SIGKILL) and a new one started while the sender runs (a receiver
   started after its sender): it finds the model in the cache and plays;
4. the network pauses for ``PAUSE_S``: a ``lossy.LossyRelay`` between the two stops
   forwarding (what the sender sends meanwhile is lost). The receiver says that it waits,
   conceals the missing slots (the last frame held, then eased to the neutral face) and
   plays on when the packets come back; neither process is restarted.

The receiver's counts must then be consistent with what the relay forwarded: it received
every packet forwarded while it was there, and each one was played or counted (late,
duplicate, stray, discarded), one frame per packet played and per concealed slot; the slots
concealed are the packets the relay dropped (and any late ones), as the pause is shorter
than ``receiver.receiver.MAX_GAP_S``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from cliprocess import Facewire
from conftest import free_endpoint
from lossy import LossyRelay, Record

from facewire.protocol.log import read_log
from facewire.receiver.playout import EASE_S, HOLD_S

PAUSE_S = 5.0
IDLE_S = "60"  # s without packets that end a receiver: only a fallback, Ctrl-C ends them
WAIT_S = 120  # at most, for a condition (a loaded 2-core machine starts processes slowly)


def _pngs(folder: Path) -> int:
    return len(list(folder.glob("frame_*.png")))


def _wait_frames(folder: Path, count: int, process: Facewire) -> float:
    """Wait until ``folder`` holds ``count`` frames; the time it did."""
    deadline = time.monotonic() + WAIT_S
    while _pngs(folder) < count:
        assert time.monotonic() < deadline and process.process.poll() is None, \
            f"{_pngs(folder)} frames in {folder}, not {count}:\n{process.text()[-3000:]}"
        time.sleep(0.05)
    return time.monotonic()


@dataclass(frozen=True)
class _Scene:
    """What the scene left: the summaries of the sender and of the second receiver, what the
    relay forwarded and dropped, and when (``time.monotonic``) the second receiver was
    started, was ready, the network paused and resumed, and the receiver was interrupted."""

    sent: dict
    got: dict
    record: Record
    started: float
    ready: float
    paused: float
    resumed: float
    interrupted: float


def test_receiver_killed_started_before_and_after_the_sender_and_a_network_pause(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    scene = _play(person_model, shared_data / "video" / "lp_d0.mp4", tmp_path, cache)
    sent, got, record = scene.sent, scene.got, scene.record
    # the sender ran on through everything, and its log holds every packet it sent
    assert sent["stopped"] == "interrupt" and sent["receivers_max"] >= 1, sent
    assert sent["packets"] == len(read_log(tmp_path / "sent.fwlog").packets)
    assert (cache / f"{sent['model_sha256']}.fwm").read_bytes() == person_model.read_bytes()
    # the second receiver: model from the cache, one stream through the pause
    assert got["ended"] == "stop" and got["model_source"] == "cache", got
    assert got["streams"] == 1 and got["restarts"] == 0 and got["hellos"] >= 2, got
    # it received every packet the relay forwarded while it was connected...
    times = [t for _, t in record.forwarded]
    assert sum(scene.ready + 0.5 <= t <= scene.interrupted - 0.2 for t in times) \
        <= got["received"] <= sum(t >= scene.started for t in times), got
    assert got["corrupt"] == got["duplicates"] == got["stray"] == got["overflow"] == 0, got
    # ...and concealed exactly the slots whose packet the relay dropped (or came late)
    rate = sent["rate_hz"]
    assert abs(len(record.dropped) - PAUSE_S * rate) <= 0.2 * PAUSE_S * rate
    assert got["lost"] == len(record.dropped) + got["late"], got
    played = got["received"] - got["late"] - got["discarded"]
    frames = sorted((tmp_path / "second").glob("frame_*.png"))
    assert got["frames"] == len(frames) == played + got["lost"], got
    assert got["late"] + got["discarded"] <= 3, got  # nothing else went missing
    _check_the_pause_in_the_video(frames, rate)
    assert scene.resumed - scene.paused >= PAUSE_S


def _play(model: Path, video: Path, tmp_path: Path, cache: Path) -> _Scene:
    """The scene of the module docstring, steps 1 to 4, through a ``LossyRelay``; the
    receivers write their frames to ``tmp_path / "first"`` and ``"second"``, the sender its
    log to ``tmp_path / "sent.fwlog"``."""
    sender_at, receivers_at = free_endpoint(), free_endpoint()
    relay = LossyRelay(sender_at, receivers_at)
    processes: list[Facewire] = []

    def receiver(name: str) -> Facewire:
        processes.append(Facewire(
            "receive", "--connect", receivers_at, "--frames", str(tmp_path / name), "--size",
            "160x120", "--idle-timeout", IDLE_S, "--json", cache=cache))
        return processes[-1]

    try:
        # 1. a receiver with no sender yet waits, and says so
        first = receiver("first")
        first.wait_for("waiting for a sender")
        # 2. the sender comes: the model is fetched through the relay, cached, and played
        sender = Facewire("send", "--model", str(model), "--source", str(video), "--loop",
                          "--bind", sender_at, "--record", str(tmp_path / "sent.fwlog"),
                          "--json", cache=cache)
        processes.append(sender)
        first.wait_for("fetched")
        _wait_frames(tmp_path / "first", 15, first)
        # 3. killed: no summary, no clean-up; a new receiver takes the model from the cache
        first.kill()
        started = time.monotonic()
        second = receiver("second")
        ready = second.wait_for("waiting for packets")
        assert second.seen("from the cache") is not None, second.text()[-2000:]
        _wait_frames(tmp_path / "second", 15, second)
        # 4. the network pauses: the receiver waits, and plays again when packets come back
        paused = time.monotonic()
        relay.pause(PAUSE_S)
        second.wait_for("waiting for the sender", after=paused)
        before = _pngs(tmp_path / "second")  # the concealed slots wait for the next packet
        while relay.holding:
            time.sleep(0.05)
        resumed = time.monotonic()
        # a second of the stream after the pause: 30 packets more, each one a frame, and the
        # concealed slots of the pause written when the first of them plays
        while sum(t > resumed for _, t in relay.record().forwarded) < 30:
            assert time.monotonic() < resumed + WAIT_S, "the sender stopped sending"
            time.sleep(0.05)
        _wait_frames(tmp_path / "second", before + len(relay.record().dropped) + 30, second)
        assert second.process.poll() is None and sender.process.poll() is None
        interrupted = time.monotonic()
        second.interrupt()
        got = second.summary()
        sender.interrupt()
        sent = sender.summary()
    finally:
        record = relay.stop()
        for process in processes:
            process.close()
    return _Scene(sent, got, record, started, ready, paused, resumed, interrupted)


def _check_the_pause_in_the_video(frames: list[Path], rate: float) -> None:
    """The pause in the second receiver's video: the last frame held, then eased to a
    neutral face that stays."""
    runs = _still_runs([cv2.imread(str(f)) for f in frames])
    longest = max(range(len(runs)), key=lambda i: runs[i][1])
    assert runs[longest][1] >= (PAUSE_S - HOLD_S - EASE_S) * rate - 5, runs
    held = [(start, n) for start, n in runs[longest - 20:longest] if n >= HOLD_S * rate]
    assert held, runs[longest - 20:longest + 1]
    easing = runs[longest][0] - sum(held[-1])  # frames from the held one to the neutral one
    assert 0 < easing <= EASE_S * rate + 2, runs[longest - 20:longest + 1]


def _still_runs(images: list[np.ndarray]) -> list[tuple[int, int]]:
    """(first index, length) of each run of consecutive identical images, in order."""
    runs = [(0, 1)]
    for i in range(1, len(images)):
        if (images[i] == images[i - 1]).all():
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((i, 1))
    return runs
