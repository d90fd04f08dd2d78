"""Hands on the face found in the enrollment frames (``sender.enroll.occluders``), on real
hands (``bench.handover``: cut from mediapipe_selfie and latentsync_demo2) laid on a real
talking face (hdtf_edmarkey, a tuning clip), and kept out of the model built from them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

CLIP = "hdtf_edmarkey.mp4"


def _frames(shared_data: Path, clip: str, frames: slice) -> list:
    from facewire.models.infra.video import read_frames
    from facewire.sender.tracker import LandmarkTracker

    tracker = LandmarkTracker()
    return [(f, tracker.track(f.image).points)
            for f in read_frames(shared_data / "video" / clip, frames)]


def _scan(pairs: list) -> list:
    from facewire.sender.enroll.occluders import OccluderScan

    scan = OccluderScan()
    for image, points in pairs:
        scan.see(image, points)
    return scan.verdicts()


@pytest.mark.parametrize("hand", ["raised", "back"])
def test_a_real_hand_on_a_real_face_is_found(shared_data: Path, hand: str):
    """``raised`` is the woman's hand of mediapipe_selfie, ``back`` the man's of
    latentsync_demo2, each laid over the mouth and cheek of eight frames of a talking clip."""
    from facewire.bench.handover import cut_hand, lay_hand

    cut = cut_hand(shared_data / "video", hand)
    tracked = _frames(shared_data, CLIP, slice(100, 108))
    assert all(p is not None for _, p in tracked)
    laid = [(lay_hand(f.image, cut, p, f.time)[0], p) for f, p in tracked]
    verdicts = _scan(laid)
    assert all(v.occluded for v in verdicts), [v.face for v in verdicts]
    assert all("mouth" in v.parts for v in verdicts), [v.parts for v in verdicts]
    assert min(v.face for v in verdicts) > 0.2
    image, points = laid[0]
    mask = verdicts[0].mask(image.shape)
    mouth = np.rint(points[48:68].mean(axis=0)).astype(int)
    assert mask.shape == image.shape[:2] and mask[mouth[1], mouth[0]]
    assert mask.mean() < 0.5  # the hand, not the frame


@pytest.mark.parametrize("clip, frames", [(CLIP, slice(100, 108)),
                                          ("mediapipe_selfie.mp4", slice(0, 8))])
def test_clean_faces_are_not_occluded(shared_data: Path, clip: str, frames: slice):
    """The talking clip's own frames, and the selfie's woman whose real hands are in front of
    her chest (found by the hand model, but not on her face)."""
    tracked = _frames(shared_data, clip, frames)
    verdicts = _scan([(f.image, p) for f, p in tracked])
    assert not any(v.occluded for v in verdicts), [(v.face, v.parts) for v in verdicts]


def test_a_mask_covers_the_parts_under_it():
    from facewire.sender.enroll.occluders import Occlusion, spread, verdict

    points = np.zeros((68, 2))
    rng = np.random.default_rng(0)
    points[:] = rng.uniform(100, 300, (68, 2))
    points[48:68] = rng.uniform([170, 250], [230, 280], (20, 2))  # the mouth
    mask = np.zeros((400, 400), bool)
    mask[240:300, 150:260] = True
    found = verdict(mask, points)
    assert "mouth" in found.parts and found.occluded
    assert not verdict(np.zeros_like(mask), points).occluded
    filled = spread({0: Occlusion(), 4: found}, 6)
    assert [v.occluded for v in filled] == [False, True, True, True, True, True]


def test_a_bad_stride_is_refused():
    from facewire.sender.enroll.occluders import OccluderScan

    with pytest.raises(ValueError, match="stride"):
        OccluderScan(stride=0)


def test_the_build_keeps_a_hand_out_of_the_neutral_and_the_layers(
        shared_data: Path, tmp_path: Path):
    """A reproduction: the man's real hand over the mouth in the first 36 of 60 frames."""
    from facewire.bench.handover import hand_over
    from facewire.sender.enroll.build import build_model

    made = hand_over(shared_data / "video" / CLIP, tmp_path / "hand.mp4", slice(0, 60),
                     part=0.6)
    assert made.covered == tuple(range(36))
    built = build_model(made.path, tmp_path / "hand.fwm")
    summary = built.summary()
    occluded = set(summary["occluders"]["frames"])
    faces = {i for i, pose in zip(built.frames, built.fit.poses) if pose is not None}
    assert faces & set(made.covered) <= occluded
    assert not occluded - set(range(36))  # no clean frame called occluded
    assert summary["occluded_enrollment_frames"] == len(occluded)
    assert built.model.info.neutral_frame not in made.covered
    assert not set(built.model.info.frames_used) & set(made.covered)
    assert not set(built.appearance["mouth"]["frames"]) & set(made.covered)
