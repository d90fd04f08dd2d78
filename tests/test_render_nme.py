"""Tests for bench.render_nme: the project's tracker on a picture against the real frame.

Real frames of lp_d0.mp4 (the shortest shared clip) and the real dlib tracker; the
"pictures" are made from the real frame so that the expected NME is known.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.bench.render_nme import PARTS, FaceCounts, picture_nme, summary, track_fresh
from facewire.models.infra.video import read_frames
from facewire.models.landmarks import outer_eye_distance
from facewire.sender.tracker import LandmarkTracker


@pytest.fixture(scope="module")
def frames(shared_data: Path) -> list[np.ndarray]:
    """Three real frames of lp_d0.mp4 (512 x 512, one face), BGR."""
    return [f.image for f in read_frames(shared_data / "video" / "lp_d0.mp4", slice(40, 43))]


@pytest.fixture(scope="module")
def tracker() -> LandmarkTracker:
    return LandmarkTracker()


def _shifted(image: np.ndarray, dx: float) -> np.ndarray:
    """The image moved right by ``dx`` pixels (edges repeated)."""
    matrix = np.float32([[1, 0, dx], [0, 1, 0]])
    return cv2.warpAffine(image, matrix, (image.shape[1], image.shape[0]),
                          borderMode=cv2.BORDER_REPLICATE)


def test_the_real_frame_as_its_own_picture_scores_zero(frames: list[np.ndarray],
                                                       tracker: LandmarkTracker) -> None:
    for image in frames:
        real = track_fresh(tracker, image)
        assert real is not None and real.shape == (68, 2)
        again = track_fresh(tracker, image[..., ::-1][..., ::-1])  # a strided view of it
        assert again is not None
        np.testing.assert_array_equal(picture_nme(real, again), np.zeros(len(PARTS)))


def test_a_shifted_picture_scores_its_shift(frames: list[np.ndarray],
                                            tracker: LandmarkTracker) -> None:
    """A picture moved by k px has every point k px off: NME k / (outer-eye distance), in
    every part, growing with k (measured within 15 % for k >= 4)."""
    for image in frames:
        real = track_fresh(tracker, image)
        assert real is not None
        eyes = float(outer_eye_distance(real))
        previous = 0.0
        for k in (4, 8, 16):
            points = track_fresh(tracker, _shifted(image, k))
            assert points is not None
            np.testing.assert_allclose((points - real).mean(axis=0), [k, 0], atol=1.0)
            error = picture_nme(real, points)
            assert error[0] == pytest.approx(k / eyes, rel=0.2), (k, error)
            assert np.all(np.abs(error / (k / eyes) - 1) < 0.35), (k, error)
            assert error[0] > previous
            previous = error[0]


def test_a_black_frame_has_no_face(frames: list[np.ndarray], tracker: LandmarkTracker) -> None:
    assert track_fresh(tracker, np.zeros_like(frames[0])) is None
    nme = np.full((3, len(PARTS)), np.nan)
    real = track_fresh(tracker, frames[0])
    picture = track_fresh(tracker, frames[1])
    assert real is not None and picture is not None
    nme[1] = picture_nme(real, picture)
    s = summary("render", FaceCounts(nme, missing=2))
    assert s["render_nme_frames"] == 1
    assert s["render_nme_mean"] == pytest.approx(nme[1, 0] * 100, abs=1e-4)
    assert set(s) == {"render_nme_mean", "render_nme_mouth", "render_nme_eyes",
                      "render_nme_brows", "render_nme_frames"}
    empty = summary("h264_render", FaceCounts(np.full((3, len(PARTS)), np.nan), missing=3))
    assert empty["h264_render_nme_mean"] is None and empty["h264_render_nme_frames"] == 0


def test_each_image_is_tracked_on_its_own(frames: list[np.ndarray],
                                          tracker: LandmarkTracker) -> None:
    """A fresh detection per image: what was tracked before does not change the points.
    The live tracker, by contrast, follows the previous frame's box into the next image."""
    image, moved = frames[0], _shifted(frames[0], 12)
    alone = track_fresh(LandmarkTracker(), moved)
    track_fresh(tracker, image)
    after = track_fresh(tracker, moved)
    assert alone is not None and after is not None
    np.testing.assert_array_equal(after, alone)
    live = LandmarkTracker()
    live.track(image)
    followed = live.track(moved)
    assert followed.detected is False  # the live tracker carried its box over,
    assert followed.points is not None and not np.array_equal(followed.points, alone)  # and
    # that box moved its points (by 0.6 px on average here): a fresh detection does not
