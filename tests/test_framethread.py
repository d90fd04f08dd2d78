"""Tests for sender.framethread: capture on its own thread, queued or newest-only."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from facewire.sender.capture import open_source
from facewire.sender.framethread import AHEAD, FrameThread


def test_a_file_is_read_ahead_in_order_and_nothing_is_dropped(grey_video) -> None:
    video: Path = grey_video(frames=12)
    with open_source(str(video)) as source:
        expected = [frame.index for frame in source]
        with FrameThread(source, latest=False) as frames:
            got = [frame.index for frame in frames]
    assert got == expected == list(range(12))


def test_the_reader_runs_at_most_ahead_items_in_front() -> None:
    produced: list[int] = []

    def items():
        for i in range(20):
            produced.append(i)
            yield i

    with FrameThread(items(), latest=False) as frames:
        for i in range(5):
            assert next(frames) == i
            time.sleep(0.05)  # the reader has had time to fill the queue
            # taken i + 1 items, queued AHEAD, and one more read and waiting for room
            assert len(produced) <= i + 1 + AHEAD + 1
        assert list(frames) == list(range(5, 20))


def test_latest_hands_a_slow_consumer_the_newest_item_and_counts_the_dropped() -> None:
    go = threading.Event()

    def camera():
        yield from range(10)
        go.set()
        yield 10

    with FrameThread(camera(), latest=True) as frames:
        assert go.wait(5)
        time.sleep(0.05)
        got = list(frames)
    assert got[-1] == 10 and got == sorted(got)
    assert frames.dropped == 11 - len(got) and frames.dropped >= 9


def test_the_readers_error_comes_after_the_items_read_before_it() -> None:
    def broken():
        yield 1
        yield 2
        raise OSError("camera unplugged")

    with FrameThread(broken(), latest=False) as frames:
        assert next(frames) == 1 and next(frames) == 2
        with pytest.raises(OSError, match="camera unplugged"):
            next(frames)
        with pytest.raises(StopIteration):
            next(frames)


def test_close_stops_a_reader_waiting_for_room() -> None:
    def endless():
        i = 0
        while True:
            yield i
            i += 1

    frames = FrameThread(endless(), latest=False)
    assert next(frames) == 0
    frames.close()
    assert not frames._thread.is_alive()
    with pytest.raises(StopIteration):
        next(frames)


def test_bad_queue_size() -> None:
    with pytest.raises(ValueError, match="ahead"):
        FrameThread([], latest=False, ahead=0)
