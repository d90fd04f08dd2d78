"""Tests for models.infra.video: frame ranges, container info and frame-by-frame decoding."""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np
import pytest
from conftest import write_video

from facewire.models.infra.video import (
    VideoError,
    VideoFrame,
    frame_range,
    quarter_turns,
    read_frames,
    video_info,
)


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


# Rotation: a real clip (obama_speaking.mp4, 512x388: not square, so a quarter turn shows in
# the size) stored turned, with a display matrix saying how to stand it upright.

CLIP_FRAMES = slice(0, 8)


@pytest.fixture(scope="module")
def clip(shared_data: Path) -> list[np.ndarray]:
    return [f.image.copy() for f in read_frames(shared_data / "video" / "obama_speaking.mp4",
                                                CLIP_FRAMES)]


@pytest.mark.parametrize("rotation", [90, 180, 270, -90])
def test_a_rotated_file_reads_upright(clip: list[np.ndarray], tmp_path: Path,
                                      rotation: int) -> None:
    upright = write_video(tmp_path / "upright.mp4", clip)
    turned = write_video(tmp_path / "turned.mp4", clip, rotation=rotation)
    with av.open(str(turned)) as container:  # what is stored: the turned pixels, the matrix
        stream = container.streams.video[0]
        first = next(container.decode(stream))
        assert first.rotation % 360 == rotation % 360
        stored = first.to_ndarray(format="bgr24")
    quarter = rotation % 180 == 90
    assert stored.shape[:2] == ((512, 388) if quarter else (388, 512))
    info = video_info(turned)
    assert (info.width, info.height, info.frames) == (512, 388, len(clip))
    assert info.rotation == rotation % 360
    frames = list(read_frames(turned))
    assert [f.index for f in frames] == list(range(len(clip)))
    reference = list(read_frames(upright))
    for f, g, original in zip(frames, reference, clip, strict=True):
        assert f.image.shape == original.shape
        # equal to the upright original up to codec noise (both sides encoded once)
        assert np.abs(f.image.astype(int) - original).mean() < 3
        assert np.abs(f.image.astype(int) - g.image).mean() < 3
    if not quarter:  # the stored half-turned image is far from the upright one: not a no-op
        assert np.abs(stored.astype(int) - clip[0]).mean() > 20
    tail = list(read_frames(turned, slice(5, None)))  # a range not from 0 is turned too
    assert [f.index for f in tail] == [5, 6, 7] and tail[0].image.shape == (388, 512, 3)


def test_a_rotate_tag_reads_upright(clip: list[np.ndarray], tmp_path: Path) -> None:
    """Older files say ``rotate`` (degrees clockwise) in the stream's tags; Matroska keeps
    the tag (as ``ROTATE``)."""
    path = tmp_path / "tagged.mkv"
    stored = [np.ascontiguousarray(np.rot90(image, 1)) for image in clip]  # ccw on disk
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=25)
        stream.width, stream.height, stream.pix_fmt = 388, 512, "yuv420p"
        stream.metadata["rotate"] = "90"  # turn clockwise to show
        for image in stored:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    info = video_info(path)
    assert (info.width, info.height, info.rotation) == (512, 388, 270)
    frames = [f.image for f in read_frames(path)]
    assert len(frames) == len(clip)
    for image, original in zip(frames, clip, strict=True):
        assert np.abs(image.astype(int) - original).mean() < 3


def test_a_rotation_not_a_multiple_of_90_is_refused(clip: list[np.ndarray],
                                                    tmp_path: Path) -> None:
    path = write_video(tmp_path / "tilted.mp4", clip[:3], rotation=45)
    for read in (video_info, lambda p: list(read_frames(p)), lambda p: list(read_frames(
            p, slice(1, 2)))):
        with pytest.raises(VideoError) as err:
            read(path)
        message = str(err.value)
        assert "\n" not in message
        assert str(path) in message and "45 degrees" in message and "display matrix" in message
    # a rotate tag, in the words the file used
    assert quarter_turns("a.mkv", 0, "270") == 1 and quarter_turns("a.mkv", 0, "-90") == 1
    assert quarter_turns("a.mkv", -90, "30") == 3  # the display matrix wins
    for tag in ("30", "sideways", "nan", "inf"):
        with pytest.raises(VideoError, match=f"a.mkv: rotation '{tag}' \\(rotate tag\\) is not "
                                             "a multiple of 90 degrees"):
            quarter_turns("a.mkv", 0, tag)
