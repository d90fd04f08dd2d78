"""Tests for receiver.output: the H.264 and PNG writers, their thread, side_by_side."""

from __future__ import annotations

import math
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from facewire.models.infra.video import read_frames, video_info
from facewire.receiver.output import (
    FRAME_PATTERN,
    QUEUE_FRAMES,
    FrameFolderWriter,
    OutputError,
    VideoWriter,
    side_by_side,
)

W, H, RATE = 160, 120, 30


def pattern(i: int, width: int = W, height: int = H) -> np.ndarray:
    """A smooth RGB scene that moves with i: two drifting waves and a travelling disc."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    r = 128 + 90 * np.sin((x + 3 * i) / 14)
    g = 128 + 90 * np.cos((y - 2 * i) / 11)
    b = np.where((x - 20 - 4 * i) ** 2 + (y - height / 2) ** 2 < 18 ** 2, 230, 40)
    return np.dstack([r, g, b]).astype(np.uint8)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return math.inf if mse == 0 else 10 * math.log10(255 ** 2 / mse)


def test_mp4_round_trip_keeps_every_frame_in_order(tmp_path: Path) -> None:
    frames = [pattern(i) for i in range(30)]
    path = tmp_path / "out.mp4"
    with VideoWriter(path, W, H, RATE) as writer:
        for frame in frames:
            writer.write(frame)
    assert writer.frames == 30
    info = video_info(path)
    assert (info.width, info.height) == (W, H)
    assert info.rate_hz == pytest.approx(RATE)
    decoded = list(read_frames(path))
    assert len(decoded) == 30
    for i, (frame, got) in enumerate(zip(frames, decoded)):
        rgb = got.image[:, :, ::-1]
        assert got.time == pytest.approx(i / RATE, abs=1e-3)
        assert psnr(frame, rgb) > 30
        if i:  # the right frame, not a neighbour: the scene moves 3-4 px a frame
            assert psnr(frame, rgb) > psnr(frames[i - 1], rgb) + 3


def test_mp4_pads_odd_sizes(tmp_path: Path) -> None:
    frames = [pattern(i, 33, 25) for i in range(4)]
    path = tmp_path / "odd.mp4"
    with VideoWriter(path, 33, 25, 25.0) as writer:
        for frame in frames:
            writer.write(frame)
    decoded = [f.image[:, :, ::-1] for f in read_frames(path)]
    assert len(decoded) == 4 and decoded[0].shape == (26, 34, 3)
    # a 33x25 picture with a sharp coloured disc loses more to 4:2:0 than a large one
    assert psnr(frames[3], decoded[3][:25, :33]) > 24
    edge = decoded[3].astype(int)
    assert np.abs(edge[:, 33] - edge[:, 32]).mean() < 4  # the pad repeats the last column
    assert np.abs(edge[25] - edge[24]).mean() < 4


def test_a_hold_is_not_encoded_and_keeps_the_timeline(tmp_path: Path) -> None:
    """Frames written and held: the file has only the written frames, each at its own index
    over the rate, lasting until the next; one that ends on holds lasts to its end."""
    plan = "wwhhwhwwhh"  # write or hold, slot by slot
    path = tmp_path / "held.mp4"
    with VideoWriter(path, W, H, RATE) as writer:
        writer.hold()  # nothing to hold yet: no effect
        for k, step in enumerate(plan):
            writer.write(pattern(k)) if step == "w" else writer.hold()
    assert writer.frames == len(plan) and writer.backlog == 0  # all encoded at close
    decoded = list(read_frames(path))
    written = [k for k, step in enumerate(plan) if step == "w"]
    assert [round(f.time * RATE) for f in decoded] == written + [len(plan) - 1]
    for k, got in zip(written, decoded):
        assert psnr(pattern(k), got.image[:, :, ::-1]) > 30
    assert psnr(pattern(written[-1]), decoded[-1].image[:, :, ::-1]) > 30  # the last again
    with av.open(str(path)) as container:  # the last frame lasts its slot
        assert container.duration / av.time_base == pytest.approx(len(plan) / RATE, abs=1e-3)


def test_a_held_png_frame_is_the_frame_before_under_its_own_number(tmp_path: Path) -> None:
    with FrameFolderWriter(tmp_path) as writer:
        writer.write(pattern(0))
        writer.hold()
        writer.write(pattern(2))
    images = [cv2.imread(str(tmp_path / FRAME_PATTERN.format(k)))[:, :, ::-1] for k in range(3)]
    assert np.array_equal(images[1], pattern(0)) and np.array_equal(images[2], pattern(2))


def test_png_folder_round_trip_is_exact(tmp_path: Path) -> None:
    folder = tmp_path / "new" / "frames"  # created with its parent
    frames = [pattern(i) for i in range(12)]
    with FrameFolderWriter(folder) as writer:
        for frame in frames:
            writer.write(frame)
    names = sorted(p.name for p in folder.iterdir())
    assert names == [FRAME_PATTERN.format(i) for i in range(12)]
    assert names[0] == "frame_000000.png"
    for name, frame in zip(names, frames):
        back = cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(back[:, :, ::-1], frame)


def test_folder_writer_refuses_files_and_used_folders(tmp_path: Path) -> None:
    a_file = tmp_path / "taken"
    a_file.write_bytes(b"x")
    with pytest.raises(OutputError, match="taken: exists and is not a folder"):
        FrameFolderWriter(a_file)
    used = tmp_path / "used"
    with FrameFolderWriter(used) as writer:
        writer.write(pattern(0))
    with pytest.raises(OutputError, match="used: already holds frame_"):
        FrameFolderWriter(used)


def test_frame_size_and_type_are_checked(tmp_path: Path) -> None:
    with VideoWriter(tmp_path / "v.mp4", W, H, RATE) as writer:
        writer.write(pattern(0))
        for bad in (pattern(0, W + 2, H), pattern(0).astype(np.float32), pattern(0)[:, :, 0]):
            with pytest.raises(ValueError, match="v.mp4: frame"):
                writer.write(bad)
    with FrameFolderWriter(tmp_path / "f") as writer:
        writer.write(pattern(0))
        with pytest.raises(ValueError, match="expected 160x120, got 80x60"):
            writer.write(pattern(0, 80, 60))


def test_write_after_close_and_bad_paths(tmp_path: Path) -> None:
    for writer in (VideoWriter(tmp_path / "c.mp4", W, H, RATE),
                   FrameFolderWriter(tmp_path / "c")):
        writer.write(pattern(0))
        writer.close()
        writer.close()  # closing twice is harmless
        with pytest.raises(ValueError, match="write after close"):
            writer.write(pattern(1))
    with pytest.raises(OutputError, match="no-such-folder/x.mp4: cannot create"):
        VideoWriter(tmp_path / "no-such-folder" / "x.mp4", W, H, RATE)
    with pytest.raises(OutputError, match="is a folder"):
        VideoWriter(tmp_path, W, H, RATE)
    with pytest.raises(ValueError, match="rate_hz"):
        VideoWriter(tmp_path / "r.mp4", W, H, 0)
    with pytest.raises(ValueError, match="preset 'nonsense'"):
        VideoWriter(tmp_path / "p.mp4", W, H, RATE, preset="nonsense")


def test_no_frames_leaves_no_video(tmp_path: Path) -> None:
    path = tmp_path / "empty.mp4"
    writer = VideoWriter(path, W, H, RATE)
    with pytest.raises(OutputError, match="empty.mp4: no frames were written"):
        writer.close()
    assert not path.exists()


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_video_thread_error_surfaces_at_close() -> None:
    # /dev/full accepts the open and fails every write with ENOSPC; x264 holds the first
    # frames in its lookahead, so nothing reaches the file before close flushes it.
    writer = VideoWriter("/dev/full", 64, 48, RATE)
    for i in range(3):
        writer.write(pattern(i, 64, 48))
    with pytest.raises(OutputError, match="/dev/full: .*No space left") as error:
        writer.close()
    assert isinstance(error.value.__cause__, OSError)


def test_folder_thread_error_surfaces_at_close_and_at_write(tmp_path: Path) -> None:
    folder = tmp_path / "gone"
    writer = FrameFolderWriter(folder)
    folder.rmdir()  # the thread's first PNG cannot be written
    writer.write(pattern(0))
    with pytest.raises(OutputError, match="gone/frame_000000.png: cannot write PNG"):
        writer.close()

    folder.mkdir()
    writer = FrameFolderWriter(folder)
    folder.rmdir()
    with pytest.raises(OutputError, match="gone/frame_000000.png"):
        # the thread fails on frame 0, then drains the queue: write never hangs, and once
        # the queue has been full the failure is known
        for i in range(QUEUE_FRAMES + 3):
            writer.write(pattern(i))
    with pytest.raises(OutputError):
        writer.close()


def test_context_manager_lets_the_callers_error_through(tmp_path: Path) -> None:
    path = tmp_path / "partial.mp4"
    with pytest.raises(RuntimeError, match="render failed"), \
            VideoWriter(path, W, H, RATE) as writer:
        for i in range(5):
            writer.write(pattern(i))
        raise RuntimeError("render failed")
    assert len(list(read_frames(path))) == 5  # what was written is a complete file


def test_side_by_side_shapes_and_content() -> None:
    left = pattern(0, 80, 100)
    right = pattern(5, 60, 50)
    both = side_by_side(left, right)
    assert both.shape == (100, 80 + 120, 3) and both.dtype == np.uint8
    np.testing.assert_array_equal(both[:, :80], left)
    scaled = both[:, 80:]
    np.testing.assert_allclose(scaled.mean(axis=(0, 1)), right.mean(axis=(0, 1)), atol=3)
    assert side_by_side(left, right, height=50).shape == (50, 40 + 60, 3)
    np.testing.assert_array_equal(side_by_side(left, right, height=50)[:, 40:], right)
    same = side_by_side(left, left)
    np.testing.assert_array_equal(same, np.concatenate([left, left], axis=1))
    assert side_by_side(pattern(0, 3, 7), pattern(0, 5, 5)).shape == (7, 3 + 7, 3)
    for bad in (left[:, :, 0], left.astype(np.float32), left[:0]):
        with pytest.raises(ValueError, match="left"):
            side_by_side(bad, right)
    with pytest.raises(ValueError, match="height"):
        side_by_side(left, right, height=0)
