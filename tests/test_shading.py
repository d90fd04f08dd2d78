"""The light that follows, measured on the sender (``sender.shading``) and its field
(``models.shading``): known gains put on a real frame of lp_d0 are recovered, a hand-sized
patch does not move it, and the packets carry it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.models.infra.video import frame_range, read_frames
from facewire.models.modelfile import load_model
from facewire.models.shading import LOG_GAIN_MAX, LOG_GAIN_MIN, basis, log_gain
from facewire.protocol.packet import decode
from facewire.sender.capture import estimate_intrinsics
from facewire.sender.pipeline import SenderOutput, SenderPipeline
from facewire.sender.shading import (
    HYSTERESIS,
    MIN_POINTS,
    STEP,
    TAU_S,
    ShadingEstimator,
    skin_points,
)


@pytest.fixture(scope="module")
def posed(person_model: Path, shared_data: Path) -> tuple[SenderPipeline, list, list]:
    """The sender pipeline after lp_d0's frames 0..11, those frames and their outputs."""
    model = load_model(person_model)
    frames = list(read_frames(shared_data / "video" / "lp_d0.mp4", frame_range("0:12")))
    h, w = frames[0].image.shape[:2]
    pipeline = SenderPipeline(model, estimate_intrinsics(w, h))
    outputs = [pipeline.process(f.image, f.time) for f in frames]
    assert outputs[-1].rotation is not None
    return pipeline, frames, outputs


def _fit(estimator: ShadingEstimator, gray: np.ndarray, out: SenderOutput) -> np.ndarray:
    fit = estimator.fit(gray, out.rotation, out.translation, out.residuals)
    assert fit is not None
    return fit


def _image_gain(gray: np.ndarray, gain: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(gray * gain), 0, 255).astype(np.uint8)


def test_the_field_formula() -> None:
    points = np.array([[0.0, 0.0, 5.0], [100.0, 0.0, 0.0], [0.0, -50.0, 0.0], [300.0, 0, 0]])
    shade = np.array([0.25, 0.5, -0.25])
    np.testing.assert_allclose(basis(points)[:, 1:], [[0, 0], [1, 0], [0, -0.5], [3, 0]])
    np.testing.assert_allclose(log_gain(shade, points), [0.25, 0.75, 0.375, LOG_GAIN_MAX])
    assert log_gain(-shade, points)[3] == LOG_GAIN_MIN


def test_points_avoid_the_eyes_brows_and_mouth(person_model: Path) -> None:
    mesh = load_model(person_model).mesh
    triangles = skin_points(mesh)
    centroids = mesh.vertices[mesh.triangles[triangles]].mean(axis=1)
    assert 300 < len(triangles) < 900
    x, y = np.abs(centroids[:, 0]), centroids[:, 1]
    assert not ((x > 20) & (x < 45) & (np.abs(y) < 8)).any()  # the eyes
    assert not ((x < 25) & (y > -80) & (y < -55)).any()  # the mouth
    # both cheeks, the forehead and the chin
    assert min((centroids[:, 0] < -30).sum(), (centroids[:, 0] > 30).sum()) > 40
    assert (y > 40).sum() > 20 and (y < -90).sum() > 10


def test_known_gains_on_a_real_frame_are_recovered(posed: tuple) -> None:
    """lp_d0 frame 11: as it is (the model's own light: near 0), 0.7 times as bright, a ramp
    across the face, and its left half (on the image) darker."""
    pipeline, frames, outputs = posed
    estimator = ShadingEstimator(pipeline.model, pipeline.rig, pipeline.camera)
    out = outputs[-1]
    gray = cv2.cvtColor(frames[-1].image, cv2.COLOR_BGR2GRAY).astype(np.float64)
    own = _fit(estimator, gray.astype(np.uint8), out)
    assert np.abs(own).max() < 0.08
    darker = _fit(estimator, _image_gain(gray, 0.7), out)
    np.testing.assert_allclose(darker - own, [np.log(0.7), 0, 0], atol=0.03)
    # a ramp of -0.3 per 100 mm of the face toward the image's right (the model's +x on this
    # nearly frontal face), 0 at the face centre: the points' depth gives the pixels per mm
    centre = pipeline.camera.cx + pipeline.camera.fx * out.translation[0] / -out.translation[2]
    px_per_mm = pipeline.camera.fx / -out.translation[2]
    columns = np.arange(gray.shape[1])
    ramp = np.exp(-0.3 * (columns - centre) / (100 * px_per_mm))[None, :]
    sloped = _fit(estimator, _image_gain(gray, ramp), out)
    np.testing.assert_allclose(sloped - own, [0, -0.3, 0], atol=0.06)
    # the image's left half (the person's right, -x) at half the light: a step, fitted as a
    # slope of the right sign and a darker centre
    half = np.where(columns < centre, 0.5, 1.0)[None, :]
    stepped = _fit(estimator, _image_gain(gray, half), out) - own
    assert stepped[1] > 0.4 and -0.6 < stepped[0] < -0.15


def test_a_hand_over_the_face_does_not_move_the_light(posed: tuple) -> None:
    """A dark patch over a third of the face changes the fit little; smoothing moves the
    light by a fraction of a frame's fit (a = 1 - exp(-dt / TAU_S))."""
    pipeline, frames, outputs = posed
    estimator = ShadingEstimator(pipeline.model, pipeline.rig, pipeline.camera)
    out = outputs[-1]
    gray = cv2.cvtColor(frames[-1].image, cv2.COLOR_BGR2GRAY)
    points = np.array(out.points)
    x0, x1 = points[:, 0].min(), points[:, 0].max()
    y0, y1 = points[:, 1].min(), points[:, 1].max()
    hand = gray.copy()
    hand[int(y0):int(y1), int(x0):int(x0 + (x1 - x0) / 3)] = 40  # a dark hand on one cheek
    own = _fit(estimator, gray, out)
    covered = _fit(estimator, hand, out)
    assert np.abs(covered - own).max() < 0.06
    args = (out.rotation, out.translation, out.residuals)
    sent = estimator.estimate(gray, *args, dt=1 / 30)
    first = estimator.shade.copy()
    np.testing.assert_allclose(first, own, atol=1e-6)  # a stream's first fit is taken as it is
    np.testing.assert_allclose(sent, np.rint(own / STEP) * STEP, atol=1e-6)  # on the grid
    estimator.estimate(_image_gain(gray.astype(np.float64), 0.5), *args, dt=1 / 30)
    second = estimator.shade.copy()
    a = 1 - np.exp(-1 / 30 / TAU_S)
    assert second[0] - first[0] == pytest.approx(a * np.log(0.5), abs=0.02)
    # no face on the image: no fit, the light is held
    black = np.zeros_like(gray)
    assert estimator.fit(black, *args) is None
    held = estimator.sent.copy()
    np.testing.assert_array_equal(estimator.estimate(black, *args, dt=1 / 30), held)
    np.testing.assert_array_equal(estimator.shade, second)
    assert MIN_POINTS < len(estimator.triangles)


def test_the_sent_light_moves_a_code_only_past_the_hysteresis(posed: tuple) -> None:
    """A light held 0.62 of a step above the code sent keeps that code (rounding would flip
    it, and a value near the middle would flicker); 1.1 steps above moves it one code."""
    pipeline, frames, outputs = posed
    estimator = ShadingEstimator(pipeline.model, pipeline.rig, pipeline.camera)
    out = outputs[-1]
    gray = cv2.cvtColor(frames[-1].image, cv2.COLOR_BGR2GRAY).astype(np.float64)
    args = (out.rotation, out.translation, out.residuals)
    code = estimator.estimate(gray.astype(np.uint8), *args, dt=1 / 30)[0]
    own = estimator.shade[0]
    for above, expected in ((0.62, code), (1.1, code + STEP)):
        image = _image_gain(gray, np.exp(code + above * STEP - own))
        sent = [estimator.estimate(image, *args, dt=1 / 30)[0] for _ in range(40)]
        assert estimator.shade[0] - code == pytest.approx(above * STEP, abs=0.1 * STEP)
        assert sent[-1] == pytest.approx(expected, abs=1e-6)
        assert len(set(sent[-20:])) == 1  # settled, no flicker


def test_the_packets_carry_the_light(posed: tuple, shared_data: Path) -> None:
    """The pipeline's packets carry its estimate as sent; 0.7 times the light shows as
    ln 0.7 within a second."""
    pipeline, frames, _ = posed
    pipeline.reset()
    shades = []
    for k, f in enumerate(frames * 3):
        image = f.image if k < len(frames) else np.clip(
            np.rint(f.image * 0.7), 0, 255).astype(np.uint8)
        out = pipeline.process(image, k / 30)
        sent = decode(out.packet).shade
        np.testing.assert_allclose(sent, pipeline.shading.sent, atol=1e-6)
        np.testing.assert_allclose(sent, pipeline.shading.shade, atol=HYSTERESIS * STEP + 1e-6)
        shades.append(sent)
    before, after = shades[len(frames) - 1], shades[-1]
    assert abs(before[0]) < 0.08
    assert after[0] - before[0] == pytest.approx(np.log(0.7), abs=0.06)
