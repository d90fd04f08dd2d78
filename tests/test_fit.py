"""Tests for sender.enroll.fit: fitting the generic head to one person from tracked 68-point
frames."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.geometry import Intrinsics, Pose, intrinsics_guess, project
from facewire.models.head import generic_head
from facewire.models.infra.raster import orbit_pose
from facewire.models.mesh import Tag
from facewire.sender.enroll.fit import FitError, fit_person, flipped_triangles

W, H = 640, 480
CAMERA = Intrinsics(640.0, 640.0, 319.5, 239.5, W, H)
TARGET = (0.0, -30.0, 60.0)  # orbit centre, model mm
DISTANCE = 600.0
YAWS = np.arange(-30.0, 31.0, 5.0)  # camera orbit yaw, degrees; 0 is frontal (index 6)


def _person(generic: np.ndarray) -> np.ndarray:
    """A known non-rigid change of the generic landmarks; the outer eye corners keep their
    distance, so the scale convention (eye distance = generic) holds exactly."""
    t = generic.copy()
    t[0:17, 0] *= 1.08  # wider jaw
    t[27:36, 2] += 4.0  # nose further out
    t[30:36, 1] -= 3.0  # longer nose
    t[48:68, 0] *= 1.1  # wider mouth
    t[17:27, 1] += 2.0  # higher brows
    return t


def _frame(rng: np.random.Generator, shape: np.ndarray, yaw: float, pitch: float
           ) -> tuple[np.ndarray, Pose]:
    pose = orbit_pose(yaw, pitch, DISTANCE, TARGET)
    return project(shape, pose, CAMERA) + rng.normal(0.0, 0.5, (68, 2)), pose


def _similarity_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-point distance between b and a after the best similarity a -> b (Umeyama)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, s, vt = np.linalg.svd((b - cb).T @ (a - ca))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    r = u @ d @ vt
    scale = (s * np.diag(d)).sum() / ((a - ca) ** 2).sum()
    return np.linalg.norm(scale * (a - ca) @ r.T + cb - b, axis=1)


def _angle_deg(r1: np.ndarray, r2: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r1 @ r2.T) - 1) / 2, -1.0, 1.0))))


@pytest.fixture(scope="module")
def head():
    return generic_head()


@pytest.fixture(scope="module")
def synthetic(head):
    """A turning head (yaw -30..30) plus a frontal blink, a frontal open mouth, a no-face frame."""
    rng = np.random.default_rng(7)
    generic = head.vertices[head.landmarks].astype(np.float64)
    person = _person(generic)
    points, truth = [], []
    for yaw in YAWS:
        p, pose = _frame(rng, person, yaw, 3.0 * np.sin(yaw / 7.0))
        points.append(p)
        truth.append(pose)
    blink = person.copy()
    blink[[37, 38, 43, 44]] = person[[41, 40, 47, 46]]
    mouth = person.copy()
    mouth[[56, 57, 58, 65, 66, 67]] += [0.0, -15.0, -3.0]
    mouth[5:12, 1] -= 8.0
    for shape in (blink, mouth):
        p, pose = _frame(rng, shape, 0.0, 0.0)
        points.append(p)
        truth.append(pose)
    points.append(None)
    truth.append(None)
    fit = fit_person(points, CAMERA, head=head)
    return fit, person, truth, points


def test_synthetic_poses(synthetic):
    fit, _, truth, points = synthetic
    assert len(fit.poses) == len(points)
    assert fit.poses[-1] is None
    for pose, true in zip(fit.poses[:-1], truth[:-1]):
        assert pose is not None
        assert _angle_deg(pose.rotation, true.rotation) < 2.0
        # same scale (eye distance kept): the head's distance within 2 %
        assert abs(np.linalg.norm(pose.translation) / np.linalg.norm(true.translation) - 1) < 0.02
        assert pose.translation[2] < 0
    assert fit.yaw_range_deg[0] < -25 and fit.yaw_range_deg[1] > 25


def test_synthetic_shape_and_depth(synthetic, head):
    fit, person, _, _ = synthetic
    generic = head.vertices[head.landmarks].astype(np.float64)
    assert fit.depth == "structure-from-motion"
    assert fit.depth_change_mm > 0.5
    err = _similarity_error(fit.landmarks3d[:60], person[:60])
    before = _similarity_error(generic[:60], person[:60])
    assert err.mean() < 1.5 and err.max() < 4.0
    assert err.mean() < 0.6 * before.mean()
    # the nose came forward (SfM saw the 4 mm the generic head lacks)
    nose = fit.landmarks3d[30, 2] - fit.landmarks3d[[36, 45], 2].mean()
    nose_true = person[30, 2] - person[[36, 45], 2].mean()
    assert abs(nose - nose_true) < 2.0
    assert abs(np.linalg.norm(fit.landmarks3d[36] - fit.landmarks3d[45])
               - np.linalg.norm(generic[36] - generic[45])) < 0.5


def test_synthetic_neutral_and_views(synthetic):
    fit, _, truth, _ = synthetic
    frontal = int(np.flatnonzero(YAWS == 0)[0])
    assert fit.neutral == frontal  # not the blink (len(YAWS)) nor the open mouth (+1)
    assert fit.views[0] == frontal
    assert 3 <= len(fit.views) <= 5
    yaws = [fit.poses[v].yaw_deg for v in fit.views]
    assert min(yaws) < -20 and max(yaws) > 20
    for i in range(len(yaws)):
        for j in range(i):
            assert abs(yaws[i] - yaws[j]) >= 15


def test_fitted_mesh(synthetic, head):
    fit, _, _, _ = synthetic
    mesh = fit.mesh
    assert mesh.vertices.shape == head.vertices.shape
    assert np.array_equal(mesh.triangles, head.triangles)
    assert np.array_equal(mesh.landmarks, head.landmarks)
    assert np.array_equal(mesh.phantoms, head.phantoms)
    assert np.array_equal(mesh.uv, head.uv)
    on_mesh = mesh.vertices[mesh.landmarks].astype(np.float64)
    assert np.abs(on_mesh - fit.landmarks3d).max() < 0.5
    assert len(flipped_triangles(head, mesh, Tag.SKIN)) == 0
    assert len(flipped_triangles(head, mesh, None)) == 0
    # the face did change
    moved = np.linalg.norm(mesh.vertices - head.vertices, axis=1)
    assert moved[head.landmarks].max() > 3.0
    # the skull moves by one similarity: scalp and ear vertices 60 mm or more from every
    # landmark and phantom fit one to 0.5 mm
    v0 = head.vertices.astype(np.float64)
    skull = np.unique(head.triangles[np.isin(head.tags, [Tag.SCALP, Tag.EAR])])
    face = np.vstack([v0[head.landmarks], v0[head.phantoms]])
    gap = np.min(np.linalg.norm(v0[skull, None] - face[None], axis=2), axis=1)
    back = skull[gap >= 60]
    assert back.size > 500
    assert _similarity_error(v0[back], mesh.vertices[back].astype(np.float64)).max() < 0.5
    # eyeballs move rigidly (pairwise distances kept up to the global scale)
    eye = np.unique(head.triangles[head.tags == Tag.RIGHT_EYEBALL])
    assert _similarity_error(v0[eye], mesh.vertices[eye].astype(np.float64)).max() < 1e-3


def test_generic_depth_without_turning(head):
    rng = np.random.default_rng(3)
    person = _person(head.vertices[head.landmarks].astype(np.float64))
    points = [_frame(rng, person, yaw, 0.0)[0] for yaw in np.linspace(-3, 3, 12)]
    fit = fit_person(points, CAMERA, head=head)
    assert fit.depth == "generic"
    assert fit.depth_change_mm == 0.0
    assert fit.views == (fit.neutral,)
    assert all(p is not None for p in fit.poses)


def test_errors(head):
    with pytest.raises(FitError, match="no face"):
        fit_person([None] * 20, CAMERA, head=head)
    rng = np.random.default_rng(0)
    person = head.vertices[head.landmarks].astype(np.float64)
    few = [_frame(rng, person, 0.0, 0.0)[0] for _ in range(3)] + [None] * 20
    with pytest.raises(FitError, match="only 3 frames with a face; need at least 10"):
        fit_person(few, CAMERA, head=head)
    with pytest.raises(ValueError, match=r"points\[1\]"):
        fit_person([few[0], np.zeros((67, 2))], CAMERA, head=head)
    with pytest.raises(ValueError, match="camera: expected a models.geometry.Intrinsics"):
        fit_person(few, (640.0, 640.0, 319.5, 239.5), head=head)


def test_real_video(shared_data, head):
    from facewire.models.infra.video import read_frames, video_info
    from facewire.sender.tracker import LandmarkTracker

    path = shared_data / "video" / "openface_default.wmv"
    info = video_info(path)
    tracker = LandmarkTracker()
    points = [tracker.track(f.image).points for f in read_frames(path, slice(0, 90))]
    camera = intrinsics_guess(info.width, info.height)
    fit = fit_person(points, camera, head=head)
    faces = [i for i, p in enumerate(points) if p is not None]
    assert len(faces) >= 80
    assert sum(fit.poses[i] is not None for i in faces) >= 0.9 * len(faces)
    neutral = points[fit.neutral]
    error = np.linalg.norm(project(fit.landmarks3d, fit.poses[fit.neutral], camera) - neutral,
                           axis=1)
    assert np.median(error[:60]) < 3.0
    errors = [np.linalg.norm(project(fit.landmarks3d, fit.poses[i], camera)[17:48]
                             - points[i][17:48], axis=1).mean()
              for i in faces if fit.poses[i] is not None]
    assert np.median(errors) < 5.0
    assert len(flipped_triangles(head, fit.mesh, Tag.SKIN)) == 0
    assert fit.depth in ("structure-from-motion", "generic")
