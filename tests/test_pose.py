"""Tests for sender.pose: the weighted robust head pose and its One-Euro filter, on synthetic
projections of a morphed head with a known pose, and tangent frames of models.rig."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import EXPRESSION_UV, SYNTH_FX

from facewire.models.geometry import Intrinsics, Pose, project, rotation_matrix, rotation_vector
from facewire.models.landmarks import NONRIGID, RIGID
from facewire.models.rig import FRONTAL_POINTS, Rig
from facewire.sender.pose import POSE_WEIGHTS, PoseSolver

CAMERA = Intrinsics(SYNTH_FX, SYNTH_FX, 319.5, 239.5, 640, 480)  # the 640x480 intrinsics guess


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(rotation_vector(a.T @ b))))


def _scene(rig: Rig, rvec_deg: tuple[float, float, float], t: tuple[float, float, float],
           uv: np.ndarray, noise_px: float, seed: int = 0) -> tuple[Pose, np.ndarray]:
    """The true pose and the 68 image points of the morphed head (+ Gaussian noise)."""
    pose = Pose(rotation=rotation_matrix(np.radians(rvec_deg)), translation=np.array(t, float))
    points3d = rig.landmarks(rig.from_tangent(uv))
    image = project(points3d, pose, CAMERA)
    return pose, image + np.random.default_rng(seed).normal(0.0, noise_px, image.shape)


@pytest.mark.parametrize("rvec_deg, t", [((0.0, 0.0, 0.0), (0.0, 0.0, -450.0)),
                                         ((8.0, -20.0, 4.0), (30.0, -15.0, -450.0)),
                                         ((-5.0, 25.0, -3.0), (-30.0, 20.0, -500.0))])
def test_pose_recovered_with_expression_and_noise(rig: Rig, rvec_deg, t) -> None:
    """Fitted against the model's landmarks under the (here known) expression. Noise-free:
    exact; with 0.3 px noise (eyes 120-160 px apart): RMS over 10 draws within the issue's
    0.5 deg and 1 mm (single draws reach 0.7 deg and 1.9 mm: the noise floor)."""
    neutral = rig.mesh.vertices[rig.mesh.landmarks].astype(np.float64)
    solver = PoseSolver(neutral, CAMERA)
    shape = rig.landmarks(rig.from_tangent(EXPRESSION_UV))
    truth, image = _scene(rig, rvec_deg, t, EXPRESSION_UV, noise_px=0.0)
    pose = solver.solve(image, None, shape)  # acquisition (SQPnP, then Gauss-Newton)
    assert _angle_deg(pose.rotation, truth.rotation) < 0.01
    assert np.linalg.norm(pose.translation - truth.translation) < 0.05
    angles, shifts = [], []
    for seed in range(10):
        truth, image = _scene(rig, rvec_deg, t, EXPRESSION_UV, noise_px=0.3, seed=seed)
        pose = solver.solve(image, None, shape)
        assert pose is not None
        angles.append(_angle_deg(pose.rotation, truth.rotation))
        shifts.append(np.linalg.norm(pose.translation - truth.translation))
        again = solver.solve(image, pose, shape)  # tracking from the previous pose
        assert _angle_deg(again.rotation, pose.rotation) < 0.01
    assert np.sqrt(np.mean(np.square(angles))) < 0.5
    assert np.sqrt(np.mean(np.square(shifts))) < 1.0


def test_exact_without_noise_or_expression(rig: Rig) -> None:
    neutral = rig.mesh.vertices[rig.mesh.landmarks].astype(np.float64)
    truth, image = _scene(rig, (5.0, 12.0, -3.0), (10.0, 5.0, -560.0),
                          np.zeros((9, 2), np.float32), noise_px=0.0)
    start = Pose(rotation=rotation_matrix(np.radians([9.0, 4.0, 0.0])),
                 translation=np.array([0.0, 0.0, -600.0]))
    pose = PoseSolver(neutral, CAMERA).solve(image, start)
    assert _angle_deg(pose.rotation, truth.rotation) < 0.01
    assert np.linalg.norm(pose.translation - truth.translation) < 0.05


def test_rigid_points_outweigh_an_outlier(rig: Rig) -> None:
    """A wild brow point (weight 0.15, Huber) moves the pose far less than a rigid one."""
    neutral = rig.mesh.vertices[rig.mesh.landmarks].astype(np.float64)
    truth, image = _scene(rig, (0.0, 10.0, 0.0), (0.0, 0.0, -600.0),
                          np.zeros((9, 2), np.float32), noise_px=0.0)
    solver = PoseSolver(neutral, CAMERA)
    errors = {}
    for point in (19, 36):
        moved = image.copy()
        moved[point, 1] -= 40.0
        pose = solver.solve(moved, truth)
        errors[point] = _angle_deg(pose.rotation, truth.rotation)
    assert POSE_WEIGHTS[19] < POSE_WEIGHTS[36] == 1.0
    assert errors[19] < 0.3 < errors[36]
    assert errors[19] < errors[36] / 3


def test_rejects_impossible_input(rig: Rig) -> None:
    neutral = rig.mesh.vertices[rig.mesh.landmarks].astype(np.float64)
    solver = PoseSolver(neutral, CAMERA)
    scrambled = np.random.default_rng(1).uniform(0, 480, (68, 2))
    assert solver.solve(scrambled) is None
    with pytest.raises(ValueError, match="points"):
        solver.solve(np.zeros((60, 2)))
    with pytest.raises(ValueError, match="weights"):
        PoseSolver(neutral, CAMERA, np.zeros(68))
    with pytest.raises(ValueError, match="landmarks3d"):
        PoseSolver(neutral[:10], CAMERA)


def test_tangent_frames(rig: Rig) -> None:
    t = rig.tangents
    assert t.shape == (9, 2, 3) and t.dtype == np.float32 and not t.flags.writeable
    gram = np.einsum("kai,kbi->kab", t, t)
    assert np.allclose(gram, np.eye(2), atol=1e-6)
    normals = np.cross(t[:, 0], t[:, 1])
    vertex_normals = rig.mesh.vertex_normals()[rig.mesh.landmarks[NONRIGID]]
    for k, point in enumerate(NONRIGID):
        if int(point) in FRONTAL_POINTS:
            assert np.allclose(normals[k], [0, 0, 1], atol=1e-6)
        else:  # the vertex normal (no seam copies on these vertices of the generic head)
            assert np.allclose(normals[k], vertex_normals[k], atol=1e-5)
        assert t[k, 0, 0] > 0.8  # t1 follows the model x axis
        assert abs(np.dot(t[k, 1], [1.0, 0.0, 0.0])) < 1e-6  # t2 = n x t1 has no x
    rng = np.random.default_rng(3)
    uv = rng.uniform(-10, 10, (9, 2)).astype(np.float32)
    assert np.allclose(rig.to_tangent(rig.from_tangent(uv)), uv, atol=1e-5)
    d = rng.uniform(-10, 10, (9, 3)).astype(np.float32)
    projected = rig.from_tangent(rig.to_tangent(d))
    assert np.allclose(np.einsum("ki,ki->k", d - projected, d - projected),
                       np.einsum("ki,ki->k", d, normals) ** 2, atol=1e-3)  # only n is lost
    with pytest.raises(ValueError, match="uv: expected shape"):
        rig.from_tangent(np.zeros((9, 3), np.float32))
    with pytest.raises(ValueError, match="d: contains NaN"):
        rig.to_tangent(np.full((9, 3), np.nan, np.float32))


def test_rigid_points_are_fully_weighted() -> None:
    assert np.all(POSE_WEIGHTS[RIGID] == 1.0)
    assert np.all(POSE_WEIGHTS[:17] == 0.0)  # the jaw contour slides
    assert np.all(POSE_WEIGHTS[60:] == 0.0)  # the inner lips are the mesh's lip slit
