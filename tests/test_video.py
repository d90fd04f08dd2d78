"""Tests for models.infra.video: frame ranges, container info and frame-by-frame decoding."""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np
import pytest
from conftest import write_video

from facewire.models.infra.video import VideoError, VideoFrame, frame_range, read_frames, video_info


@pytest.fixture(scope="module")
def small_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 frames of 64x48 whose brightness encodes the frame index (index * 20)."""
    path = tmp_path_factory.mktemp("video") / "ramp.mp4"
    write_video(path, [np.full((48, 64, 3), 10 + 20 * k, np.uint8) for k in range(12)])
    return path


def test_frame_range() -> None:
    assert frame_range(None) == slice(0, None)
    assert frame_range("0:180") == slice(0, 180)
    assert frame_range("5:") == slice(5, None)
    assert frame_range(":7") == slice(0, 7)
    assert frame_range(":") == slice(0, None)
    for bad in ("5:2", "5:5", "x", "-1:", "3", "a:b", "1:2:3", ""):
        with pytest.raises(ValueError, match="--frames"):
            frame_range(bad)


def test_small_video_counts_order_and_values(small_video: Path) -> None:
    info = video_info(small_video)
    assert (info.width, info.height, info.frames) == (64, 48, 12)
    assert info.rate_hz == pytest.approx(25.0)
    frames = list(read_frames(small_video))
    assert [f.index for f in frames] == list(range(12))
    for f in frames:
        assert isinstance(f, VideoFrame)
        assert f.image.shape == (48, 64, 3) and f.image.dtype == np.uint8
        assert abs(float(f.image.mean()) - (10 + 20 * f.index)) < 4  # the right frame, in order
    times = np.array([f.time for f in frames])
    np.testing.assert_allclose(np.diff(times), 1 / 25, atol=1e-6)
    sliced = list(read_frames(small_video, frame_range("3:6")))
    assert [f.index for f in sliced] == [3, 4, 5]
    for f, g in zip(sliced, frames[3:6]):
        np.testing.assert_array_equal(f.image, g.image)
        assert f.time == g.time
    assert [f.index for f in read_frames(small_video, frame_range("10:"))] == [10, 11]
    assert list(read_frames(small_video, frame_range("20:30"))) == []


def test_real_video(shared_data: Path) -> None:
    path = shared_data / "video" / "lp_d0.mp4"
    info = video_info(path)
    assert info.width > 0 and info.height > 0 and info.rate_hz > 0
    frames = list(read_frames(path))
    assert len(frames) > 30
    if info.frames:
        assert len(frames) == info.frames
    assert [f.index for f in frames] == list(range(len(frames)))
    for f in frames[:5]:
        assert f.image.shape == (info.height, info.width, 3) and f.image.dtype == np.uint8
    times = np.array([f.time for f in frames])
    assert (np.diff(times) > 0).all()
    assert times[-1] - times[0] == pytest.approx((len(frames) - 1) / info.rate_hz, rel=0.05)
    part = list(read_frames(path, frame_range("10:20")))
    assert [f.index for f in part] == list(range(10, 20))
    np.testing.assert_array_equal(part[0].image, frames[10].image)


def test_container_without_frame_count(shared_data: Path) -> None:
    """AVI/WMV containers may not state a frame count: 0 means unknown, frames still come."""
    path = shared_data / "video" / "openface_default.wmv"
    info = video_info(path)
    assert (info.width, info.height) == (640, 480)
    first = list(read_frames(path, frame_range(":5")))
    assert [f.index for f in first] == list(range(5))
    assert first[0].image.shape == (480, 640, 3)


def test_missing_and_unreadable_files(tmp_path: Path) -> None:
    missing = tmp_path / "nothere.mp4"
    text = tmp_path / "notes.mp4"
    text.write_text("this is not a video\n")
    truncated = tmp_path / "cut.mp4"
    whole = tmp_path / "whole.mp4"
    write_video(whole, [np.full((48, 64, 3), 90, np.uint8)] * 5)
    truncated.write_bytes(whole.read_bytes()[:200])
    for path, why in ((missing, "no such video file"), (text, "not a readable video"),
                      (tmp_path, "no such video file"), (truncated, str(truncated))):
        with pytest.raises(VideoError, match=why) as err:
            video_info(path)
        assert str(path) in str(err.value)
        with pytest.raises(VideoError) as err:
            list(read_frames(path))
        assert str(path) in str(err.value)


def test_video_without_frames(tmp_path: Path) -> None:
    """A container whose video stream got no frame at all: a clear error naming the file."""
    path = tmp_path / "empty.mp4"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=25)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        container.start_encoding()
    with pytest.raises(VideoError) as err:
        video_info(path)
    assert str(path) in str(err.value)
    with pytest.raises(VideoError):
        list(read_frames(path))


def test_decoded_once_serves_later_passes_from_memory(small_video: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    import facewire.models.infra.video as video

    opened = []
    real_open = video._open
    monkeypatch.setattr(video, "_open", lambda path: opened.append(path) or real_open(path))
    plain = [f.image.copy() for f in read_frames(small_video, slice(2, 9))]
    with video.decoded_once(small_video):
        first = list(read_frames(small_video))  # decodes: the whole file, now known to end
        again = list(read_frames(small_video, slice(2, 9)))
        tail = list(read_frames(small_video, slice(10, 50)))
        assert len(opened) == 2  # the plain pass and the first pass inside
        assert not again[0].image.flags.writeable  # shared, so read-only
    assert [f.index for f in first] == list(range(12))
    assert [f.index for f in tail] == [10, 11]
    for a, b in zip(plain, again, strict=True):
        assert np.array_equal(a, b.image)
    list(read_frames(small_video, slice(2, 9)))
    assert len(opened) == 3  # outside the block, decoded again


def test_decoded_once_past_its_budget_decodes_again(small_video: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    import facewire.models.infra.video as video

    opened = []
    real_open = video._open
    monkeypatch.setattr(video, "_open", lambda path: opened.append(path) or real_open(path))
    monkeypatch.setattr(video, "CACHE_BYTES", 5 * 48 * 64 * 3)  # five frames
    with video.decoded_once(small_video):
        list(read_frames(small_video))
        held = [f.index for f in read_frames(small_video, slice(0, 5))]
        assert len(opened) == 1
        again = [f.index for f in read_frames(small_video, slice(3, 8))]
        assert len(opened) == 2
    assert held == list(range(5)) and again == list(range(3, 8))
