"""``bench.jitter``: the render jitter ratio on still frames and the filter's lag, on
synthetic landmark tracks whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.bench.jitter import STILL, filter_lag, render_jitter

FACE = np.column_stack([np.linspace(100, 800, 68), np.linspace(200, 300, 68)])  # eyes 95 px apart


def _track(noise_px: float, frames: int, seed: int) -> dict[int, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {k: FACE + rng.normal(0, noise_px, FACE.shape) for k in range(frames)}


def test_the_ratio_compares_the_rendering_with_the_real_face_on_still_frames() -> None:
    real = _track(0.3, 60, 1)
    same = render_jitter(real, real, list(range(60)))
    assert same.ratio == pytest.approx(1.0) and same.still_frames > 40
    steadier = render_jitter(real, _track(0.05, 60, 2), list(range(60)))
    shakier = render_jitter(real, _track(0.8, 60, 3), list(range(60)))
    assert steadier.ratio is not None and shakier.ratio is not None
    assert steadier.ratio < 0.5 < 1.5 < shakier.ratio
    assert steadier.real_motion is not None and steadier.real_motion > STILL  # noise, unselected


def test_moving_frames_and_gaps_are_not_judged() -> None:
    moving = {k: FACE + [5.0 * k, 0.0] for k in range(30)}  # 5 px a frame: not still
    assert render_jitter(moving, moving, list(range(30))) == (None, 0, None, None)
    real = _track(0.3, 10, 4)
    apart = list(range(0, 20, 2))  # no two positions are consecutive video frames
    assert render_jitter(real, real, apart).still_frames == 0
    missing = dict(real)
    del missing[5]  # the rendering's face not found on one frame: two pairs fewer
    assert render_jitter(real, missing, list(range(10))).still_frames == \
        render_jitter(real, real, list(range(10))).still_frames - 2


@pytest.mark.parametrize("delay", [0, 1, 2])
def test_the_lag_is_the_delay_of_the_sent_points(delay: int) -> None:
    t = np.arange(120)
    shift = 30 * np.sin(2 * np.pi * t / 40)  # a head turning to and fro, up to 4.7 px a frame
    rng = np.random.default_rng(delay)
    tracked = [FACE + [s, 0.0] + rng.normal(0, 0.3, FACE.shape) for s in shift]
    sent: list[np.ndarray | None] = [FACE + [shift[max(k - delay, 0)], 0.0] for k in t]
    sent[50] = None  # a frame without a pose of its own is left out
    lag = filter_lag(tracked, sent)
    assert lag.frames == pytest.approx(delay, abs=0.2) and lag.moving_frames > 50
    with pytest.raises(ValueError, match="sent"):
        filter_lag(tracked, sent[:-1])
