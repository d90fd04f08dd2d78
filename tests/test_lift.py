"""Tests for sender.lift: lifting 2D residuals onto the lift planes, on synthetic projections of
a morphed head with a known pose, then pose + lift together."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import EXPRESSION_UV, SYNTH_FX

from facewire.models.geometry import Intrinsics, Pose, project, rotation_matrix, rotation_vector
from facewire.models.rig import Rig
from facewire.sender.lift import GRAZING_COS, Lifter, pose_and_lift
from facewire.sender.pose import PoseSolver

CAMERA = Intrinsics(SYNTH_FX, SYNTH_FX, 319.5, 239.5, 640, 480)  # the 640x480 intrinsics guess


def _image(rig: Rig, pose: Pose, uv: np.ndarray) -> np.ndarray:
    return project(rig.landmarks(rig.from_tangent(uv)), pose, CAMERA)


def test_exact_pose_gives_exact_residuals(rig: Rig) -> None:
    pose = Pose(rotation=rotation_matrix(np.radians([6.0, -15.0, 2.0])),
                translation=np.array([12.0, -8.0, -580.0]))
    truth = rig.from_tangent(EXPRESSION_UV)
    lifted = Lifter(rig, CAMERA).lift(_image(rig, pose, EXPRESSION_UV), pose)
    assert lifted.valid.all() and not lifted.grazing.any()
    assert np.abs(lifted.residuals - truth).max() < 0.1  # the leak of the morph (module doc)
    assert lifted.residuals.dtype == np.float32
    # in the planes: the tangent coordinates carry them without loss
    assert np.allclose(rig.from_tangent(rig.to_tangent(lifted.residuals)), lifted.residuals,
                       atol=1e-4)
    neutral = Lifter(rig, CAMERA).lift(_image(rig, pose, np.zeros((9, 2), np.float32)), pose)
    assert np.abs(neutral.residuals).max() < 1e-3


@pytest.mark.parametrize("rvec_deg, t", [((0.0, 0.0, 0.0), (0.0, 0.0, -450.0)),
                                         ((8.0, -20.0, 4.0), (30.0, -15.0, -450.0)),
                                         ((-5.0, 25.0, -3.0), (-30.0, 20.0, -500.0))])
def test_pose_and_lift_recover_the_expression(rig: Rig, rvec_deg, t) -> None:
    """The issue's numbers: pose within 0.5 deg and 1 mm, residuals within 0.5 mm. Noise-free
    they hold on every point with a wide margin; with 0.3 px tracker noise (eyes 120-160 px
    apart) they hold as RMS over 10 draws (single draws reach 0.7 deg, 1.9 mm and 1.7 mm on
    the worst point: the noise floor of one camera at this face size)."""
    truth_pose = Pose(rotation=rotation_matrix(np.radians(rvec_deg)),
                      translation=np.array(t, float))
    truth = rig.from_tangent(EXPRESSION_UV)
    solver = PoseSolver(rig.mesh.vertices[rig.mesh.landmarks].astype(np.float64), CAMERA)
    lifter = Lifter(rig, CAMERA)
    clean = _image(rig, truth_pose, EXPRESSION_UV)
    pose, lifted = pose_and_lift(solver, lifter, rig, clean, None, None)
    assert _angle(pose, truth_pose) < 0.05
    assert np.linalg.norm(pose.translation - truth_pose.translation) < 0.3
    assert lifted.valid.all()
    assert np.linalg.norm(lifted.residuals - truth, axis=1).max() < 0.15
    rng = np.random.default_rng(4)
    angles, shifts, errors = [], [], []
    for _ in range(10):
        image = clean + rng.normal(0, 0.3, (68, 2))
        pose, lifted = pose_and_lift(solver, lifter, rig, image, None, None)
        angles.append(_angle(pose, truth_pose))
        shifts.append(np.linalg.norm(pose.translation - truth_pose.translation))
        errors.append(np.linalg.norm(lifted.residuals - truth, axis=1))
    assert np.sqrt(np.mean(np.square(angles))) < 0.5
    assert np.sqrt(np.mean(np.square(shifts))) < 1.0
    assert np.sqrt(np.mean(np.square(errors))) < 0.5


def _angle(a: Pose, b: Pose) -> float:
    return float(np.degrees(np.linalg.norm(rotation_vector(a.rotation.T @ b.rotation))))


def test_grazing_and_facing_away(rig: Rig) -> None:
    """Turned 80 deg, a brow's plane is seen edge-on (capped); turned 120 deg, the far side's
    points face away (invalid, zero)."""
    lifter = Lifter(rig, CAMERA)
    for yaw, check in ((80.0, "grazing"), (120.0, "away")):
        pose = Pose(rotation=rotation_matrix(np.radians([0.0, yaw, 0.0])),
                    translation=np.array([0.0, 0.0, -640.0]))
        image = _image(rig, pose, EXPRESSION_UV) + 2.0  # 2 px off everywhere
        lifted = lifter.lift(image, pose)
        if check == "grazing":
            assert lifted.grazing.any()
            # the cap: at most 1/GRAZING_COS times the image offset's size at that depth
            mm_per_px = 640.0 / 640.0
            limit = np.hypot(2.0, 2.0) * mm_per_px / GRAZING_COS * 2  # + the expression
            assert np.linalg.norm(lifted.residuals[lifted.grazing], axis=1).max() < limit + 10
        else:
            assert not lifted.valid.all()
            assert np.all(lifted.residuals[~lifted.valid] == 0)


def test_input_errors(rig: Rig) -> None:
    lifter = Lifter(rig, CAMERA)
    pose = Pose(rotation=np.eye(3), translation=np.array([0.0, 0.0, -600.0]))
    with pytest.raises(ValueError, match="points"):
        lifter.lift(np.zeros((9, 2)), pose)
    with pytest.raises(ValueError, match="points"):
        lifter.lift(np.full((68, 2), np.nan), pose)
    with pytest.raises(ValueError, match="rig"):
        Lifter("rig", CAMERA)  # type: ignore[arg-type]


def test_expression_alternation_removes_the_pose_bias(rig: Rig) -> None:
    """Fitting the neutral shape to an expressive face tilts the pose; the rounds undo it."""
    truth_pose = Pose(rotation=rotation_matrix(np.radians([8.0, -20.0, 4.0])),
                      translation=np.array([30.0, -15.0, -520.0]))
    image = _image(rig, truth_pose, EXPRESSION_UV)
    solver = PoseSolver(rig.mesh.vertices[rig.mesh.landmarks].astype(np.float64), CAMERA)
    lifter = Lifter(rig, CAMERA)
    errors = []
    for rounds in (1, 2, 4):
        pose, _ = pose_and_lift(solver, lifter, rig, image, None, None, rounds)
        errors.append(np.linalg.norm(pose.translation - truth_pose.translation))
    assert errors[0] > 2.0 and errors[1] < errors[0] / 2 and errors[2] < 0.3
    with pytest.raises(ValueError, match="rounds"):
        pose_and_lift(solver, lifter, rig, image, None, None, 0)
