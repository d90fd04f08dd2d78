"""Residual heuristics, each on its own, on synthetic tracks of the 9 non-rigid residuals."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.landmarks import NONRIGID
from facewire.protocol.packet import Flag
from facewire.sender.heuristics import PARTNER, ResidualFilter

DT = 1 / 30
ALL = np.ones(9, bool)


def _smile(mm: float = 6.0) -> np.ndarray:
    """A left-right symmetric expression: corners out and up, brows up, chin down."""
    r = np.zeros((9, 3), np.float32)
    r[4] = (-mm, mm / 2, 1.0)  # 48, right mouth corner: toward the person's right (-x)
    r[5] = (mm, mm / 2, 1.0)  # 54, left mouth corner
    r[0], r[3] = (-1.0, 3.0, 0.5), (1.0, 3.0, 0.5)  # brows 19, 24
    r[1], r[2] = (-0.5, 2.0, 0.0), (0.5, 2.0, 0.0)  # brows 21, 22
    r[8] = (0.0, -4.0, 0.0)  # chin 8
    return r


def test_partners_follow_the_landmark_scheme() -> None:
    names = NONRIGID.tolist()
    pairs = {(names[i], names[j]) for i, j in enumerate(PARTNER)}
    assert pairs == {(19, 24), (24, 19), (21, 22), (22, 21), (48, 54), (54, 48),
                     (51, 51), (57, 57), (8, 8)}


def test_missing_point_decays_at_the_stated_half_life() -> None:
    f = ResidualFilter(decay_half_life_s=0.5)
    start = _smile()
    f.step(start, ALL, DT)
    valid = ALL.copy()
    valid[8] = False  # the chin (no partner) goes missing for one second
    out = None
    for _ in range(30):
        out = f.step(start, valid, DT)
        assert out.held and not out.mirrored and out.counts.decayed == 1
    assert out is not None
    np.testing.assert_allclose(out.residuals[8], start[8] * 0.25, rtol=1e-4)  # two half-lives
    np.testing.assert_array_equal(np.delete(out.residuals, 8, 0), np.delete(start, 8, 0))
    # The rate is per second, not per frame: at 10 Hz, 5 frames are one half-life.
    g = ResidualFilter(decay_half_life_s=0.5)
    g.step(start, ALL, 0.1)
    for _ in range(5):
        out = g.step(start, valid, 0.1)
    np.testing.assert_allclose(out.residuals[8], start[8] * 0.5, rtol=1e-4)
    assert out.flags == Flag.FACE_PRESENT | Flag.HELD


def test_low_confidence_counts_as_missing() -> None:
    f = ResidualFilter(decay_half_life_s=0.5, min_confidence=0.6)
    f.step(_smile(), ALL, DT)
    conf = np.full(9, 0.9)
    conf[7] = 0.3  # lower lip 57
    out = f.step(_smile() + 1.0, conf, DT)
    assert out.counts.decayed == 1 and out.counts.measured == 8
    np.testing.assert_allclose(out.residuals[7], _smile()[7] * 2 ** (-DT / 0.5), rtol=1e-5)


def test_symmetric_completion_mirrors_the_partner() -> None:
    f = ResidualFilter()
    f.step(np.zeros((9, 3)), ALL, DT)
    r = _smile()
    r[4] = (-7.0, 2.5, 1.5)  # right corner moves
    measured = r.copy()
    measured[5] = np.nan  # left corner 54 missing (NaN allowed where not valid)
    measured[3] = np.nan  # left outer brow 24 missing
    valid = ALL.copy()
    valid[[5, 3]] = False
    out = f.step(measured, valid, DT)
    np.testing.assert_array_equal(out.residuals[5], [7.0, 2.5, 1.5])
    np.testing.assert_array_equal(out.residuals[3], [1.0, 3.0, 0.5])
    assert out.mirrored and not out.held
    assert out.counts.mirrored == 2 and out.flags == Flag.FACE_PRESENT | Flag.MIRRORED
    # Both partners missing: neither can be completed; both decay.
    valid[4] = False
    out = f.step(measured, valid, DT)
    assert out.counts.mirrored == 1 and out.counts.decayed == 2  # 24 still from 19
    np.testing.assert_allclose(out.residuals[5], np.float32([7.0, 2.5, 1.5]) * 2 ** (-DT / 0.5),
                               rtol=1e-5)


def test_single_frame_spike_is_held() -> None:
    f = ResidualFilter(jump_mm=15.0, release_frames=3)
    base = _smile()
    f.step(base, ALL, DT)
    spike = base.copy()
    spike[6] += (0.0, 20.0, 0.0)  # upper lip 51 jumps 20 mm for one frame
    out = f.step(spike, ALL, DT)
    np.testing.assert_array_equal(out.residuals, base)
    assert out.held and out.counts.held == 1
    out = f.step(base, ALL, DT)
    np.testing.assert_array_equal(out.residuals, base)
    assert not out.held
    # A change just under the threshold is taken at once.
    small = base.copy()
    small[6, 1] += 14.5
    np.testing.assert_array_equal(f.step(small, ALL, DT).residuals, small)


def test_sustained_jump_is_released_after_n_frames() -> None:
    f = ResidualFilter(jump_mm=15.0, release_frames=3)
    base = _smile()
    f.step(base, ALL, DT)
    moved = base.copy()
    moved[8, 1] -= 25.0  # the jaw drops 25 mm in one frame and stays
    outs = [f.step(moved + 0.1 * k, ALL, DT) for k in range(4)]
    assert [o.held for o in outs] == [True, True, False, False]
    np.testing.assert_array_equal(outs[1].residuals[8], base[8])
    np.testing.assert_allclose(outs[2].residuals[8], moved[8] + 0.2)


def test_disagreeing_jumps_are_held_then_count_as_missing() -> None:
    f = ResidualFilter(jump_mm=15.0, release_frames=3, decay_half_life_s=0.5)
    base = _smile()
    f.step(base, ALL, DT)
    outs = []
    for k in range(4):  # the chin flies about: every frame 20 mm from the last
        r = base.copy()
        r[8, 1] += 20.0 if k % 2 == 0 else -20.0
        outs.append(f.step(r, ALL, DT))
    assert [o.counts.held for o in outs] == [1, 1, 0, 0]
    assert [o.counts.decayed for o in outs] == [0, 0, 1, 1]
    np.testing.assert_allclose(outs[3].residuals[8], base[8] * 2 ** (-2 * DT / 0.5), rtol=1e-5)


def test_jump_threshold_scales_with_the_time_step() -> None:
    base = _smile()
    moved = base.copy()
    moved[0, 1] += 20.0
    fast = ResidualFilter(jump_mm=15.0)
    fast.step(base, ALL, DT)
    assert fast.step(moved, ALL, DT).held
    slow = ResidualFilter(jump_mm=15.0)
    slow.step(base, ALL, 0.1)  # 10 Hz: 45 mm per frame allowed
    assert not slow.step(moved, ALL, 0.1).held


def test_extreme_residual_is_not_sent() -> None:
    f = ResidualFilter(extreme_mm=40.0, jump_mm=1000.0)
    base = _smile()
    f.step(base, ALL, DT)
    r = base.copy()
    r[7] = (0.0, -45.0, 0.0)  # lower lip 57: 45 mm, beyond any face
    r[4] = (-41.0, 0.0, 0.0)  # right mouth corner: extreme, completed from the left one
    out = f.step(r, ALL, DT)
    assert out.counts.extreme == 2 and out.counts.mirrored == 1 and out.counts.decayed == 1
    assert np.linalg.norm(out.residuals, axis=1).max() < 40.0
    np.testing.assert_allclose(out.residuals[7], base[7] * 2 ** (-DT / 0.5), rtol=1e-5)
    np.testing.assert_array_equal(out.residuals[4], base[5] * (-1, 1, 1))
    r[7] = (0.0, -39.0, 0.0)  # just inside the range: taken
    np.testing.assert_array_equal(f.step(r, ALL, DT).residuals[7], r[7])


def test_face_loss_then_smooth_reacquisition() -> None:
    f = ResidualFilter(decay_half_life_s=0.5, reacquire_s=0.3)
    expr = _smile(12.0)
    expr[8] = (0.0, -30.0, 0.0)  # mouth wide open
    f.step(expr, ALL, DT)
    lost = [f.step(None, None, DT) for _ in range(30)]  # one second without a face
    assert all(o.tracking_lost and not o.face_present and o.held for o in lost)
    assert lost[0].flags == Flag.TRACKING_LOST | Flag.HELD
    np.testing.assert_allclose(lost[-1].residuals, expr * 0.25, rtol=1e-4, atol=1e-6)
    # The face comes back with the opposite expression: a 30 mm jump of the chin, not held.
    back = -expr
    outs = [f.step(back, ALL, DT) for _ in range(15)]
    assert outs[0].reacquired and outs[0].flags & Flag.REACQUIRED
    assert not any(o.reacquired for o in outs[1:])
    assert not any(o.tracking_lost or o.held for o in outs)
    track = np.stack([lost[-1].residuals] + [o.residuals for o in outs])
    steps = np.linalg.norm(np.diff(track, axis=0), axis=2).max(axis=1)
    gap = np.linalg.norm(back - lost[-1].residuals, axis=1).max()
    assert gap > 35.0  # it would have been one step of 37 mm without the blend
    assert steps.max() <= gap * DT / 0.3 + 1e-4  # 9 even steps of at most 4.2 mm
    np.testing.assert_allclose(outs[8].residuals, back, atol=1e-3)  # done after 0.3 s
    np.testing.assert_allclose(outs[-1].residuals, back, atol=1e-6)


def test_first_frame_is_taken_as_measured() -> None:
    f = ResidualFilter()
    r = _smile(20.0)
    out = f.step(r, ALL, DT)
    np.testing.assert_array_equal(out.residuals, r)
    assert out.flags == Flag.FACE_PRESENT and out.residuals.dtype == np.float32
    f.reset()
    valid = ALL.copy()
    valid[6] = False
    out = f.step(r, valid, DT)
    np.testing.assert_array_equal(out.residuals[6], [0, 0, 0])  # missing starts at neutral


@pytest.mark.parametrize("residuals, valid, dt, message", [
    (np.zeros((9, 2)), None, DT, r"residuals: expected a \(9, 3\) array"),
    (np.zeros((18, 3)), None, DT, r"residuals: expected a \(9, 3\) array"),
    (np.full((9, 3), np.nan), None, DT, "point 0 .landmark 19. is marked valid but is not finite"),
    (np.zeros((9, 3)), np.ones(8, bool), DT, r"valid: expected shape \(9,\)"),
    (np.zeros((9, 3)), np.full(9, 1.5), DT, "valid: expected bools or confidences"),
    (np.zeros((9, 3)), None, 0.0, "dt: expected a positive number"),
    (np.zeros((9, 3)), None, float("nan"), "dt: expected a positive number"),
    (np.array([["a"] * 3] * 9), None, DT, r"residuals: expected a \(9, 3\) array of numbers"),
])
def test_bad_inputs_raise(residuals: np.ndarray, valid: np.ndarray | None, dt: float,
                          message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ResidualFilter().step(residuals, valid, dt)


def test_bad_settings_raise() -> None:
    with pytest.raises(ValueError, match="decay_half_life_s"):
        ResidualFilter(decay_half_life_s=0)
    with pytest.raises(ValueError, match="release_frames"):
        ResidualFilter(release_frames=0)
    with pytest.raises(ValueError, match="reacquire_s"):
        ResidualFilter(reacquire_s=-1)
    with pytest.raises(ValueError, match="min_confidence"):
        ResidualFilter(min_confidence=2)


def test_stream_starting_without_a_face_reacquires_from_neutral() -> None:
    f = ResidualFilter(reacquire_s=0.3)
    out = f.step(None, None, DT)
    assert out.tracking_lost and not out.residuals.any()
    r = _smile(9.0)
    first = f.step(r, ALL, DT)
    assert first.reacquired
    np.testing.assert_allclose(first.residuals, r * (DT / 0.3), rtol=1e-4, atol=1e-6)


def test_restart_makes_the_next_face_frame_reacquired_and_blended() -> None:
    """Another face from one frame to the next: no lost frame, but the next face frame is
    REACQUIRED and blends from the last output as after a loss."""
    f = ResidualFilter(reacquire_s=0.3)
    before = _smile(9.0)
    for _ in range(3):
        f.step(before, ALL, DT)
    f.restart()
    after = _smile(-6.0)
    first = f.step(after, ALL, DT)
    assert first.reacquired and not first.tracking_lost
    np.testing.assert_allclose(first.residuals, before + (after - before) * (DT / 0.3),
                               rtol=1e-4, atol=1e-5)
    assert not f.step(after, ALL, DT).reacquired
    fresh = ResidualFilter()
    fresh.restart()  # before any face: nothing to restart from
    assert not fresh.step(after, ALL, DT).reacquired
