"""Appearance enrollment (sender.enroll.layers): cues, the choice of states, layers and failures."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.models.modelfile import load_model
from facewire.models.regions import REGION_NAMES, ramp_mask, spec
from facewire.sender.cues import _iris_position, region_cues
from facewire.sender.enroll.layers import (
    EnrollError,
    _choose_states,
    _gaze_cost,
    enroll_regions,
    without_closed_eyes,
)
from facewire.sender.texels import SHADING_SIGMA


def test_states_span_the_cue_at_even_levels() -> None:
    rng = np.random.default_rng(3)
    cue = rng.uniform(0.0, 10.0, 400)
    yaw = np.zeros_like(cue)
    neutral = int(np.argmin(np.abs(cue - 0.4)))  # a neutral frame near the closed end
    picks, info = _choose_states(spec("mouth"), cue, yaw, neutral)  # 5th to 98th percentile
    levels = np.linspace(np.percentile(cue, 5), np.percentile(cue, 98), spec("mouth").layers)
    assert len(set(picks)) == len(picks) == spec("mouth").layers
    assert info["rest"] == 0 and picks[0] == neutral  # the neutral frame is the rest state
    np.testing.assert_allclose(cue[picks[1:]], levels[1:], atol=0.1)
    assert info["span"] == pytest.approx(levels[-1] - levels[0], abs=1e-3)
    assert not info["weak"] and info["cue"] == [round(float(cue[i]), 4) for i in picks]


def test_states_prefer_a_frontal_head_and_skip_undefined_cues() -> None:
    cue = np.array([0.0, 1.0, 1.0, np.nan, 2.0, 3.0, 3.0])
    yaw = np.array([0.0, 30.0, 2.0, 0.0, 0.0, 1.0, 40.0])
    picks, info = _choose_states(spec("mouth"), cue, yaw, neutral=4)
    assert picks[info["rest"]] == 4
    assert 3 not in picks and 1 not in picks and 6 not in picks
    assert picks == sorted(picks)  # the levels rise with the cue


def test_a_region_takes_nothing_from_a_frame_it_cannot_use() -> None:
    """Frames whose cue is undefined (occluded there, ``sender.enroll.usage``) give no state,
    not even the rest state when the neutral frame is one of them; with fewer usable frames
    than states, the usable ones serve twice; with none, no frame at all (the region then
    draws the base texture). On main (9691a01) the occluded neutral kept the rest state and
    the other states fell back to occluded frames."""
    cue = np.array([np.nan, 0.0, np.nan, 1.0, np.nan, 2.0, 3.0])
    picks, info = _choose_states(spec("mouth"), cue, np.zeros(7), neutral=0)
    assert 0 not in picks and not set(picks) & {2, 4}
    assert len(set(picks)) == len(picks) == 4 and picks == sorted(picks)
    few = np.array([np.nan, 0.0, np.nan, 1.0, np.nan, np.nan])
    picks, _ = _choose_states(spec("mouth"), few, np.zeros(6), neutral=1)
    assert len(picks) == 4 and set(picks) == {1, 3}
    assert _choose_states(spec("mouth"), np.full(5, np.nan), np.zeros(5), neutral=2)[0] == []


def test_an_eyelid_state_prefers_an_eye_looking_ahead() -> None:
    """Two frames have the same lid cue; the one whose eye looks aside (its eyeball's gaze
    cue far from the median) loses, so the lid's template does not carry a gaze."""
    frames = 40
    cues = np.full((frames, len(REGION_NAMES)), np.nan)
    lid, ball = REGION_NAMES.index("eyelid_left"), REGION_NAMES.index("eyeball_left")
    cues[:, lid] = np.linspace(-0.25, -0.05, frames)  # minus the eye aspect ratio
    cues[:, ball] = 0.5 + 0.05 * np.sin(np.arange(frames))
    cues[5:11, lid] = -0.35  # the widest-open lid, the 10th percentile, ...
    cues[5, ball] = 0.95  # ... and frame 5 looks far aside
    cost = _gaze_cost(spec("eyelid_left"), cues)
    assert cost[5] > 5 * cost[6:11].max()
    picks, _ = _choose_states(spec("eyelid_left"), cues[:, lid], cost, neutral=20)
    assert 5 not in picks and set(range(6, 11)) & set(picks)
    plain, _ = _choose_states(spec("eyelid_left"), cues[:, lid], np.zeros(frames), neutral=20)
    assert 5 in plain  # without the gaze cost, the first of the ties
    assert not _gaze_cost(spec("mouth"), cues).any()
    cues[:, ball] = np.nan  # no gaze cue (lids closed): no cost
    assert not _gaze_cost(spec("eyelid_left"), cues).any()


def test_guided_states_come_from_their_prompts_frames() -> None:
    """Frames 0-9 neutral, 10-19 the region's prompt (half closed at most), 20-29 another
    prompt's (fully closed): the closed states come from 10-19, the levels from 0-19."""
    cue = np.concatenate([np.full(10, -0.3), np.linspace(-0.3, -0.15, 10), np.full(10, -0.05)])
    prompted = np.zeros(30, bool)
    prompted[10:20] = True
    calm = np.zeros(30, bool)
    calm[:10] = True
    picks, info = _choose_states(spec("eyelid_left"), cue, np.zeros(30), 4, prompted, calm)
    assert picks[info["rest"]] == 4 and info["prompted"]
    assert all(10 <= p < 20 for j, p in enumerate(picks) if j != info["rest"])
    assert info["span"] == pytest.approx(abs(np.percentile(cue[:20], 99)
                                             - np.percentile(cue[:20], 10)), abs=1e-3)
    unguided, _ = _choose_states(spec("eyelid_left"), cue, np.zeros(30), 4)
    assert unguided[-1] >= 20  # without the guide the closed state is another prompt's frame
    prompted[:] = False
    prompted[29] = True  # one prompted frame: the other states fall back to any frame
    picks, info = _choose_states(spec("eyelid_left"), cue, np.zeros(30), 4, prompted, calm)
    assert 29 in picks and info["prompted"] is False


def test_a_cue_the_video_barely_shows_is_weak() -> None:
    cue = np.full(50, 0.3) + np.linspace(0, 0.01, 50)
    _, info = _choose_states(spec("eyelid_left"), cue, np.zeros(50), neutral=0)
    assert info["weak"] and info["span"] < 0.08


def test_iris_position_follows_the_dark_columns() -> None:
    for column in (2, 7, 13):
        sample = np.full((16, 16), 200.0, np.float32)
        sample[3:13, column:column + 2] = 40.0
        assert _iris_position(sample) == pytest.approx((column + 1) / 16, abs=0.03)
    assert np.isnan(_iris_position(np.full((16, 16), 120.0, np.float32)))


def test_cues_of_one_frame() -> None:
    points = np.zeros((68, 2))
    points[36], points[45] = (100.0, 100.0), (190.0, 100.0)  # outer eye corners 90 px apart
    points[62], points[66] = (145.0, 180.0), (145.0, 198.0)  # an 18 px inner-lip gap
    for eye in (range(36, 42), range(42, 48)):
        x0 = points[36, 0] if eye.start == 36 else 160.0
        points[list(eye)] = [(x0, 100), (x0 + 10, 95), (x0 + 20, 95), (x0 + 30, 100),
                             (x0 + 20, 105), (x0 + 10, 105)]
    points[45] = (190.0, 100.0)
    residuals = np.zeros((9, 3), np.float32)
    residuals[:4, 1] = 2.0  # brows up 2 mm
    residuals[1, 0], residuals[2, 0] = 1.0, -1.0  # inner brows drawn together
    samples = np.full((len(REGION_NAMES), 16, 16), 200.0, np.float32)
    samples[REGION_NAMES.index("eyeball_left"), 3:13, 12:14] = 30.0
    cue = dict(zip(REGION_NAMES, region_cues(samples, points, residuals)))
    assert cue["forehead"] == pytest.approx(2.0)
    assert cue["brow_furrow"] == pytest.approx(2.0)
    assert cue["mouth"] == pytest.approx(18.0 / 90.0)
    assert cue["eyelid_left"] == pytest.approx(-10.0 / 30.0)
    assert cue["eyeball_left"] == pytest.approx(13 / 16, abs=0.03)
    assert np.isnan(cue["eyeball_right"])  # a flat sample has no iris


def test_gaze_cues_are_blanked_on_closed_eyes() -> None:
    cues = np.ones((4, len(REGION_NAMES)))
    ratios = np.array([[0.3, 0.3], [0.1, 0.3], [0.3, 0.1], [0.3, 0.3]])
    out = without_closed_eyes(cues, ratios)
    left, right = REGION_NAMES.index("eyeball_left"), REGION_NAMES.index("eyeball_right")
    assert np.isnan(out[1, right]) and not np.isnan(out[1, left])
    assert np.isnan(out[2, left]) and not np.isnan(out[2, right])
    assert np.isfinite(np.delete(out, [left, right], axis=1)).all() and np.isfinite(cues).all()


def test_layers_match_the_neutral_texture_at_their_border(person_model: Path) -> None:
    """Exposure matching: each layer meets the neutral texture at its ramp without a step,
    while its interior carries the state (the closed eyelid differs from the open one)."""
    model = load_model(person_model)
    for region in model.regions:
        h, w = region.mask.shape
        u0, _, _, v1 = region.uv_rect
        r0 = round((1 - v1) * model.texture.shape[0])
        c0 = round(u0 * model.texture.shape[1])
        base = model.texture[r0:r0 + h, c0:c0 + w].astype(np.float64)
        border = ramp_mask((h, w)) < 1
        np.testing.assert_array_equal(region.mask, np.rint(255 * ramp_mask((h, w))))
        for layer in region.layers:
            step = np.abs(layer[border].astype(np.float64).mean(axis=0)
                          - base[border].mean(axis=0))
            assert step.max() < 6.0, region.name
    lid = next(r for r in model.regions if r.name == "eyelid_left")
    inside = ramp_mask(lid.mask.shape) == 1
    change = np.abs(lid.layers[-1].astype(float) - lid.layers[0].astype(float))[inside].mean()
    assert change > 8.0


def test_skin_layers_take_the_base_shading_and_keep_their_detail(person_model: Path) -> None:
    """The forehead's and brow furrow's layers, blurred at the shading field's scale, lie
    within a few grey levels of the blurred base texture (a frame's own light on the skin
    showed as a lighter box: 8-13 levels at the 90th percentile on lp_d14 before), while
    their detail still differs from it."""
    model = load_model(person_model)
    for region in (r for r in model.regions if r.name in ("forehead", "brow_furrow")):
        h, w = region.mask.shape
        u0, _, _, v1 = region.uv_rect
        r0 = round((1 - v1) * model.texture.shape[0])
        c0 = round(u0 * model.texture.shape[1])
        base = model.texture[r0:r0 + h, c0:c0 + w].astype(np.float32).mean(axis=2)
        inside = region.mask == 255
        sigma = SHADING_SIGMA * min(h, w)
        detail = []
        for layer in region.layers:
            grey = layer.astype(np.float32).mean(axis=2)
            broad = cv2.GaussianBlur(grey, (0, 0), sigma) - cv2.GaussianBlur(base, (0, 0), sigma)
            assert np.percentile(np.abs(broad[inside]), 90) < 5.0, region.name
            detail.append(np.abs(grey - base)[inside].mean())
        assert max(detail) > 1.0, region.name  # the states are not the base texture


def test_a_video_without_a_pose_cannot_enroll(generic_model: Path, grey_video) -> None:
    video = grey_video("empty_room.mp4", frames=4)
    with pytest.raises(EnrollError, match="empty_room.mp4: 0 frames with a head pose"):
        enroll_regions(load_model(generic_model), video)
