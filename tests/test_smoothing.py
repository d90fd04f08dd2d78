"""The One-Euro filters of ``sender.smoothing``: a still signal is smoothed, a moving one is
followed with bounded lag (computed on synthetic signals, not timed)."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.geometry import Pose, rotation_matrix, rotation_vector
from facewire.sender.smoothing import OneEuro, PoseFilter, ResidualSmoother, alpha

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


def test_residuals_of_a_still_face_are_smoothed() -> None:
    rng = np.random.default_rng(5)
    rest = rng.uniform(-5, 5, (9, 3))
    smoother = ResidualSmoother()
    raw = rest + rng.normal(0, 0.5, (120, 9, 3))  # 4 s of a still face, 0.5 mm noise
    out = np.array([smoother.step(r, DT) for r in raw])
    raw_steps = np.linalg.norm(np.diff(raw[30:], axis=0), axis=2).mean()
    out_steps = np.linalg.norm(np.diff(out[30:], axis=0), axis=2).mean()
    assert out.dtype == np.float32 and out.shape == raw.shape
    assert out_steps < raw_steps / 3
    assert np.abs(out[30:] - rest).mean() < np.abs(raw[30:] - rest).mean() / 2


@pytest.mark.parametrize("mm_a_frame", [1.5, 3.0, 6.0])
def test_residuals_follow_a_ramp_within_a_frame(mm_a_frame: float) -> None:
    """A mouth opening at 45-180 mm/s: after the filter settles, the smoothed value trails
    the ramp by at most one frame's travel."""
    smoother = ResidualSmoother()
    direction = np.zeros((9, 3))
    direction[6, 1] = 1.0  # the upper lip, up
    lag_frames = []
    for k in range(30):
        x = direction * mm_a_frame * k
        y = smoother.step(x, DT)
        lag_frames.append((x[6, 1] - y[6, 1]) / mm_a_frame)
    assert max(lag_frames[10:]) <= 1.0
    assert np.allclose(y[[0, 1, 2, 3, 4, 5, 7, 8]], 0.0)  # the other points stay


def test_residuals_settle_after_a_step_and_restart_on_reset() -> None:
    smoother = ResidualSmoother()
    smoother.step(np.zeros((9, 3)), DT)
    step = np.full((9, 3), 10.0)
    outs = [smoother.step(step, DT) for _ in range(10)]
    assert np.abs(outs[2] - step).max() < 2.0  # 10 mm: within 2 mm after 3 frames
    assert np.abs(outs[-1] - step).max() < 0.5
    smoother.reset()
    assert np.array_equal(smoother.step(-step, DT), -step)


def test_alpha_and_bad_input() -> None:
    assert alpha(1 / (2 * np.pi * DT), DT) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="dt"):
        ResidualSmoother().step(np.zeros((9, 3)), 0.0)
    with pytest.raises(ValueError, match="residuals"):
        ResidualSmoother(OneEuro(f_min=0.0, beta=1.0))
    with pytest.raises(ValueError, match="rotation"):
        PoseFilter(rotation=OneEuro(f_min=1.0, beta=-1.0))
