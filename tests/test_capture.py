"""Frame sources: video file, image folder, camera errors, pacing, intrinsics, calibration."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.models.geometry import intrinsics_guess
from facewire.sender.capture import (
    CaptureError,
    Pacer,
    RateLimiter,
    estimate_intrinsics,
    open_source,
    read_calibration,
    scale_intrinsics,
)

REPO = Path(__file__).resolve().parents[1]


class FakeClock:
    """A clock that only moves when slept on (or told to)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


def _write_images(folder: Path, count: int, size: tuple[int, int] = (48, 32)) -> None:
    folder.mkdir(exist_ok=True)
    for i in range(count):
        image = np.full((size[1], size[0], 3), 10 * i, np.uint8)
        image[0, 0] = (i, 2 * i, 3 * i)
        assert cv2.imwrite(str(folder / f"img_{i}.png"), image)


def test_video_file_source(shared_data: Path) -> None:
    with open_source(str(shared_data / "video" / "lp_d0.mp4")) as source:
        assert (source.width, source.height) == (512, 512)
        assert source.rate_hz == pytest.approx(25.0)
        assert not source.pace and not source.live
        frames = list(source)
    assert len(frames) == 78 == source.frames
    assert [f.index for f in frames] == list(range(78))
    times = np.array([f.time for f in frames])
    assert np.all(np.diff(times) > 0)
    assert np.allclose(np.diff(times), 1 / 25, atol=1e-3)
    assert frames[0].image.shape == (512, 512, 3) and frames[0].image.dtype == np.uint8


def test_video_file_range(shared_data: Path) -> None:
    source = open_source(str(shared_data / "video" / "lp_d0.mp4"), frames=slice(10, 15))
    assert source.frames == 5
    assert [f.index for f in source] == [10, 11, 12, 13, 14]


def test_image_folder_natural_order_and_skipped_corrupt(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    _write_images(folder, 12)
    (folder / "img_5.png").write_bytes(b"not a png at all")
    (folder / "notes.txt").write_text("ignored")
    source = open_source(str(folder), rate_hz=10.0)
    assert (source.width, source.height, source.frames) == (48, 32, 12)
    frames = list(source)
    # img_10 and img_11 come after img_9 (natural order); img_5 is skipped, its index unused.
    assert [f.index for f in frames] == [0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 11]
    assert [int(f.image[0, 0, 0]) for f in frames] == [0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 11]
    assert [f.time for f in frames] == pytest.approx([i / 10 for i in (0, 1, 2, 3, 4, 6, 7, 8,
                                                                          9, 10, 11)])
    assert source.skipped == 1 and source.skipped_names == ["img_5.png"]


def test_image_folder_errors(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("no images here")
    with pytest.raises(CaptureError, match="empty: no images"):
        open_source(str(empty))
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "a.jpg").write_bytes(b"\xff\xd8 truncated")
    with pytest.raises(CaptureError, match="none of its 1 images can be read"):
        open_source(str(broken))
    mixed = tmp_path / "mixed"
    _write_images(mixed, 3)
    cv2.imwrite(str(mixed / "img_2.png"), np.zeros((20, 20, 3), np.uint8))
    with pytest.raises(CaptureError, match=r"img_2\.png: image is 20x20.*48x32"):
        list(open_source(str(mixed)))


def test_missing_and_unreadable_file(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="nothere.mp4: no such file or folder"):
        open_source(str(tmp_path / "nothere.mp4"))
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\x00" * 1000)
    with pytest.raises(CaptureError, match="junk.mp4: not a readable video"):
        open_source(str(junk))
    with pytest.raises(CaptureError, match="expected camera:N"):
        open_source("camera:front")
    with pytest.raises(ValueError, match="rate_hz"):
        open_source(str(junk), rate_hz=0)


def test_missing_camera_is_a_clear_error() -> None:
    # In a child process with a timeout, so a slow device probe cannot hang the suite.
    code = ("from sender.capture import open_source, CaptureError\n"
            "try:\n    open_source('camera:57')\nexcept CaptureError as e:\n    print(e)\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == ("camera:57: no camera could be opened (is one connected? "
                                   "try camera:58)")


def test_pacer_releases_frames_at_their_times() -> None:
    clock = FakeClock()
    pacer = Pacer(clock, clock.sleep)
    released = []
    for t in (5.0, 5.04, 5.08, 5.12):
        pacer.wait(t)
        released.append(clock.now - 100.0)
        clock.now += 0.01  # the consumer's work on the frame
    assert released == pytest.approx([0.0, 0.04, 0.08, 0.12])
    assert clock.sleeps == pytest.approx([0.03, 0.03, 0.03])


def test_pacer_does_not_rush_after_a_slow_frame() -> None:
    clock = FakeClock()
    pacer = Pacer(clock, clock.sleep)
    pacer.wait(0.0)
    clock.now += 0.2  # a slow frame: 0.2 s instead of 0.04
    pacer.wait(0.04)  # late: released at once
    assert clock.sleeps == []
    pacer.wait(0.08)  # the schedule moved with the delay: a full period after the late one
    assert clock.sleeps == pytest.approx([0.04])


def test_paced_folder_source_with_injected_clock(tmp_path: Path) -> None:
    _write_images(tmp_path / "f", 5)
    clock = FakeClock()
    source = open_source(str(tmp_path / "f"), rate_hz=20.0, pace=True, clock=clock,
                         sleep=clock.sleep)
    times = [clock.now - 100.0 for _ in source]
    assert times == pytest.approx([0.0, 0.05, 0.1, 0.15, 0.2])
    unpaced = FakeClock()
    list(open_source(str(tmp_path / "f"), rate_hz=20.0, clock=unpaced, sleep=unpaced.sleep))
    assert unpaced.sleeps == []


def test_paced_file_runs_in_real_time(shared_data: Path) -> None:
    source = open_source(str(shared_data / "video" / "lp_d0.mp4"), pace=True,
                         frames=slice(0, 6))
    start = time.monotonic()
    count = sum(1 for _ in source)
    elapsed = time.monotonic() - start
    assert count == 6
    assert 0.19 <= elapsed < 1.0  # 5 periods of 1/25 s, with room for a busy machine


def test_rate_limiter_keeps_one_frame_per_slot() -> None:
    rng = np.random.default_rng(0)
    same = RateLimiter(30.0)
    late = np.arange(60) / 30 + rng.uniform(-0.005, 0.02, 60)  # -0.15 .. +0.6 period
    late[0] = 0.0  # a camera's times count from its first frame
    assert all(same.keep(t) for t in late)
    double = RateLimiter(30.0)
    kept = [double.keep(t) for t in np.arange(60) / 60 + rng.uniform(-0.002, 0.002, 60)]
    assert kept == [True, False] * 30
    slow = RateLimiter(30.0)
    assert all(slow.keep(t) for t in np.arange(20) / 20)
    with pytest.raises(ValueError, match="rate_hz"):
        RateLimiter(0)


def test_estimate_intrinsics_matches_the_model_build() -> None:
    cam = estimate_intrinsics(640, 480)
    assert cam == intrinsics_guess(640, 480)
    assert (cam.width, cam.height) == (640, 480)
    assert (cam.cx, cam.cy) == (319.5, 239.5)
    focal = estimate_intrinsics(640, 480, focal=900.0)
    assert (focal.fx, focal.fy, focal.cx) == (900.0, 900.0, 319.5)
    with pytest.raises(ValueError, match="--focal"):
        estimate_intrinsics(640, 480, focal=-1.0)
    with pytest.raises(ValueError, match="width"):
        estimate_intrinsics(0, 480)


def test_calibration_round_trip_and_scaling(tmp_path: Path) -> None:
    doc = {"fx": 612.5, "fy": 611.0, "cx": 319.25, "cy": 241.5, "width": 640, "height": 480}
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(doc))
    cam = read_calibration(path)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == tuple(doc.values())
    assert scale_intrinsics(cam, 640, 480) == cam
    half = scale_intrinsics(cam, 320, 240)
    assert (half.fx, half.fy) == (306.25, 305.5)
    assert (half.cx, half.cy) == (159.375, 120.5)  # pixel centres: (c + 1/2) / 2 - 1/2
    with pytest.raises(CaptureError, match="640x480.*512x512.*aspect"):
        scale_intrinsics(cam, 512, 512, name=str(path))


@pytest.mark.parametrize("change, message", [
    ({"fx": -3.0}, "field fx: must be in"),
    ({"fy": "600"}, "field fy: expected a number"),
    ({"width": 640.5}, "field width: expected an integer"),
    ({"height": True}, "field height: expected an integer"),
    ({"height": 20000}, "field height: must be in"),
    ({"cx": 700.0}, "field cx: 700.0 lies outside the image"),
    ({"skew": 0.0}, "unknown field 'skew'"),
    ({"cy": None}, "field cy: expected a number"),
])
def test_calibration_bad_fields(tmp_path: Path, change: dict, message: str) -> None:
    doc = {"fx": 612.5, "fy": 611.0, "cx": 319.25, "cy": 241.5, "width": 640, "height": 480}
    doc.update(change)
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match="calib.json: " + message):
        read_calibration(path)


def test_calibration_file_errors(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="no such calibration file"):
        read_calibration(tmp_path / "none.json")
    path = tmp_path / "c.json"
    path.write_text("{not json")
    with pytest.raises(CaptureError, match="c.json: not a JSON calibration file"):
        read_calibration(path)
    path.write_text(json.dumps({"fx": 1.0}))
    with pytest.raises(CaptureError, match="c.json: field 'fy' is missing"):
        read_calibration(path)
    path.write_text("[1, 2]")
    with pytest.raises(CaptureError, match="expected a JSON object"):
        read_calibration(path)
