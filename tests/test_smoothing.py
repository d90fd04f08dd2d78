"""The One-Euro pose filter of ``sender.smoothing``: a still head is smoothed, a moving one is
followed with bounded lag (computed on synthetic poses, not timed)."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.geometry import Pose, rotation_matrix, rotation_vector
from facewire.sender.smoothing import OneEuro, PoseFilter, alpha

DT = 1 / 30


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(rotation_vector(a.T @ b))))


def test_filter_smooths_a_still_head_and_follows_a_turn() -> None:
    rng = np.random.default_rng(2)
    truth = rotation_matrix(np.radians([0.0, 10.0, 0.0]))
    f = PoseFilter()
    raw_steps, out_steps, prev_raw, prev_out = [], [], None, None
    for _ in range(90):  # 3 s still, 0.5 deg raw jitter
        raw = Pose(rotation=truth @ rotation_matrix(rng.normal(0, np.radians(0.5), 3)),
                   translation=np.array([0.0, 0.0, -600.0]) + rng.normal(0, 1.0, 3))
        out = f.step(raw, 1 / 30)
        if prev_raw is not None:
            raw_steps.append(_angle_deg(prev_raw.rotation, raw.rotation))
            out_steps.append(_angle_deg(prev_out.rotation, out.rotation))
        prev_raw, prev_out = raw, out
    assert np.median(out_steps) < np.median(raw_steps) / 3
    # a 60 deg/s turn for 1 s: the filter keeps up within a few degrees
    for k in range(30):
        raw = Pose(rotation=truth @ rotation_matrix(np.radians([0.0, 2.0 * (k + 1), 0.0])),
                   translation=np.array([0.0, 0.0, -600.0]))
        out = f.step(raw, 1 / 30)
    assert _angle_deg(out.rotation, raw.rotation) < 3.0
    f.reset()
    first = f.step(raw, 1 / 30)
    assert _angle_deg(first.rotation, raw.rotation) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("deg_a_frame", [1.0, 2.0, 4.0])
def test_a_steady_turn_is_followed_within_a_frame_and_a_half(deg_a_frame: float) -> None:
    """A head turning at 30-120 deg/s: once the filter has the speed, the filtered yaw
    trails the raw one by at most 1.5 frames of the turn (computed, not timed)."""
    f = PoseFilter()
    lag_frames = []
    for k in range(40):
        yaw = deg_a_frame * k
        raw = Pose(rotation=rotation_matrix(np.radians([0.0, yaw, 0.0])),
                   translation=np.array([0.0, 0.0, -600.0]))
        out = f.step(raw, DT)
        lag_frames.append(_angle_deg(out.rotation, raw.rotation) / deg_a_frame)
    assert max(lag_frames[15:]) <= 1.5
    assert lag_frames[-1] <= lag_frames[15] + 1e-6  # it settles, it does not drift away


def test_a_step_of_the_head_is_reached() -> None:
    f = PoseFilter()
    start = Pose(rotation=np.eye(3), translation=np.array([0.0, 0.0, -600.0]))
    f.step(start, DT)
    moved = Pose(rotation=rotation_matrix(np.radians([0.0, 10.0, 0.0])),
                 translation=np.array([20.0, 0.0, -600.0]))
    outs = [f.step(moved, DT) for _ in range(30)]
    assert _angle_deg(outs[4].rotation, moved.rotation) < 3.0  # 10 deg: within 3 in 5 frames
    assert _angle_deg(outs[-1].rotation, moved.rotation) < 0.5
    assert np.abs(outs[-1].translation - moved.translation).max() < 1.0


def test_alpha_and_bad_input() -> None:
    assert alpha(1 / (2 * np.pi * DT), DT) == pytest.approx(0.5)
    pose = Pose(rotation=np.eye(3), translation=np.array([0.0, 0.0, -600.0]))
    with pytest.raises(ValueError, match="dt"):
        PoseFilter().step(pose, 0.0)
    with pytest.raises(ValueError, match="translation"):
        PoseFilter(translation=OneEuro(f_min=0.0, beta=1.0))
    with pytest.raises(ValueError, match="rotation"):
        PoseFilter(rotation=OneEuro(f_min=1.0, beta=-1.0))
