"""models.geometry: intrinsics bounds, rotation round trips, poses, projection."""

import math

import numpy as np
import pytest

from facewire.models.geometry import (
    OPENCV_FLIP,
    Intrinsics,
    Pose,
    intrinsics_guess,
    project,
    rotation_matrices,
    rotation_matrix,
    rotation_vector,
    vertex_normals,
)
from facewire.protocol.control import Camera, ControlError


def test_known_rotations():
    quarter_z = rotation_matrix(np.array([0.0, 0.0, math.pi / 2]))
    np.testing.assert_allclose(quarter_z @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    half_x = rotation_matrix(np.array([math.pi, 0.0, 0.0]))
    np.testing.assert_allclose(half_x, np.diag([1.0, -1.0, -1.0]), atol=1e-15)
    np.testing.assert_array_equal(rotation_matrix(np.zeros(3)), np.eye(3))
    np.testing.assert_allclose(rotation_vector(np.diag([-1.0, 1.0, -1.0])), [0.0, math.pi, 0.0],
                               atol=1e-12)


def test_rotation_round_trips():
    rng = np.random.default_rng(3)
    for _ in range(200):
        axis = rng.normal(size=3)
        rvec = axis / np.linalg.norm(axis) * rng.uniform(0.0, math.pi - 1e-3)
        r = rotation_matrix(rvec)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(r) == pytest.approx(1.0)
        np.testing.assert_allclose(rotation_vector(r), rvec, atol=1e-9)
        np.testing.assert_allclose(rotation_matrix(rotation_vector(r)), r, atol=1e-12)
    tiny = np.array([1e-10, -2e-10, 3e-10])  # R = I + [r]_x, exact to the angle squared
    cross = np.array([[0.0, -tiny[2], tiny[1]], [tiny[2], 0.0, -tiny[0]],
                      [-tiny[1], tiny[0], 0.0]])
    np.testing.assert_allclose(rotation_matrix(tiny), np.eye(3) + cross, rtol=0, atol=1e-18)


def test_rotation_matrices_are_rotation_matrix_batched():
    rng = np.random.default_rng(5)
    axes = rng.normal(size=(300, 3))
    angles = rng.uniform(0.0, math.pi, size=(300, 1))
    rvecs = np.concatenate([axes / np.linalg.norm(axes, axis=1, keepdims=True) * angles,
                            [[0.0, 0.0, 0.0], [1e-10, -2e-10, 3e-10], [1e-13, 0.0, 0.0],
                             [0.0, 0.0, math.pi], [2e-6, -1e-6, 4e-6]]])
    batched = rotation_matrices(rvecs)
    assert batched.shape == (len(rvecs), 3, 3) and batched.dtype == np.float64
    for rvec, r in zip(rvecs, batched, strict=True):
        np.testing.assert_allclose(r, rotation_matrix(rvec), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(rotation_matrices(np.zeros((2, 3))), np.stack([np.eye(3)] * 2))
    assert rotation_matrices(np.zeros((0, 3))).shape == (0, 3, 3)


def test_rotations_refuse_bad_input():
    with pytest.raises(ValueError, match="rvec"):
        rotation_matrix(np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="rvec"):
        rotation_matrix(np.zeros(4))
    with pytest.raises(ValueError, match="rotation"):
        rotation_vector(np.eye(4))


def test_intrinsics_bounds_name_the_field():
    good = dict(fx=600.0, fy=610.0, cx=319.5, cy=239.5, width=640, height=480)
    assert Intrinsics(**good).fx == 600.0
    for field, value in (("fx", 0.0), ("fy", -1.0), ("fx", 1e6), ("cx", 1e5), ("cy", -1e5),
                         ("cx", math.nan), ("fy", math.inf), ("width", 0), ("height", 16385),
                         ("width", 640.0), ("height", True), ("fx", "600")):
        with pytest.raises(ValueError, match=f"^{field}: "):
            Intrinsics(**{**good, field: value})
    cam = Intrinsics(1, 2, -3, 4, np.int64(5), np.int32(6))
    assert (type(cam.fx), type(cam.width)) == (float, int)


def test_intrinsics_bounds_are_the_wires():
    """Every Intrinsics at the edge of its bounds is a valid wire Camera, and just past an
    edge neither accepts it: the two types hold one set of bounds."""
    edges = [dict(fx=1e-9, fy=999999.0, cx=-99999.0, cy=99999.0, width=1, height=16384),
             dict(fx=999999.0, fy=1e-9, cx=99999.0, cy=-99999.0, width=16384, height=1)]
    for fields in edges:
        Intrinsics(**fields)
        Camera(**fields)
    for field, value in (("fx", 1e6), ("cx", 1e5), ("width", 16385), ("height", 0)):
        bad = {**edges[0], field: value}
        with pytest.raises(ValueError):
            Intrinsics(**bad)
        with pytest.raises(ControlError):
            Camera(**bad)


def test_intrinsics_guess_and_resize():
    guess = intrinsics_guess(640, 480)
    assert guess == Intrinsics(640.0, 640.0, 319.5, 239.5, 640, 480)
    with pytest.raises(ValueError, match="width"):
        intrinsics_guess(0, 480)
    half = guess.resized(320, 240)
    assert half == Intrinsics(320.0, 320.0, 159.5, 119.5, 320, 240)
    np.testing.assert_array_equal(guess.matrix(), [[640, 0, 319.5], [0, 640, 239.5], [0, 0, 1]])


def test_pose_validation_and_opencv_frame():
    with pytest.raises(ValueError, match="rotation: not a rotation"):
        Pose(2.0 * np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="rotation: not a rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError, match="translation"):
        Pose(np.eye(3), np.array([0.0, 0.0, np.inf]))
    with pytest.raises(ValueError, match="rotation"):
        Pose(np.eye(2), np.zeros(3))
    r_cv = rotation_matrix(np.array([0.1, -0.2, 0.05]))
    pose = Pose.from_opencv(r_cv, np.array([[5.0], [-3.0], [600.0]]))
    np.testing.assert_array_equal(pose.translation, [5.0, 3.0, -600.0])
    np.testing.assert_array_equal(pose.rotation, OPENCV_FLIP @ r_cv)
    back_r, back_t = pose.to_opencv()
    np.testing.assert_allclose(back_r, r_cv, atol=1e-15)
    np.testing.assert_array_equal(back_t, [5.0, -3.0, 600.0])


def test_yaw_and_pitch():
    # a face turned toward the image's right: its forward axis has +x in the camera
    turned = Pose(rotation_matrix(np.radians([0.0, 20.0, 0.0])), np.array([0.0, 0.0, -600.0]))
    assert turned.yaw_deg == pytest.approx(20.0) and turned.pitch_deg == pytest.approx(0.0)
    chin_up = Pose(rotation_matrix(np.radians([-15.0, 0.0, 0.0])), np.array([0.0, 0.0, -600.0]))
    assert chin_up.pitch_deg == pytest.approx(15.0) and chin_up.yaw_deg == pytest.approx(0.0)


def test_project_matches_opencv():
    import cv2

    rng = np.random.default_rng(5)
    camera = Intrinsics(700.0, 690.0, 330.2, 245.7, 640, 480)
    pose = Pose(rotation_matrix(np.radians([5.0, -25.0, 3.0])), np.array([12.0, -8.0, -550.0]))
    points = rng.uniform(-80.0, 80.0, (20, 3))
    got = project(points, pose, camera)
    r_cv, t_cv = pose.to_opencv()
    want = cv2.projectPoints(points, cv2.Rodrigues(r_cv)[0], t_cv, camera.matrix(), None)[0]
    np.testing.assert_allclose(got, want.reshape(-1, 2), atol=1e-9)
    centre = project(np.zeros((1, 3)), Pose(np.eye(3), np.array([0.0, 0.0, -500.0])), camera)
    np.testing.assert_allclose(centre, [[camera.cx, camera.cy]])


def test_vertex_normals_weigh_triangles_by_area():
    # Two triangles folded along the edge 0-1: the square in z = 0 (normal +z, area 1/2) and
    # a larger one standing in y = 0 (normal -y, area 1); vertex 4 is in no triangle.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 2], [5, 5, 5]], np.float64)
    t = np.array([[0, 1, 2], [0, 1, 3]], np.int32)
    n = vertex_normals(v, t)
    assert n.dtype == np.float32 and n.shape == (5, 3)
    np.testing.assert_allclose(n[0], np.array([0.0, -2.0, 1.0]) / math.sqrt(5), atol=1e-7)
    np.testing.assert_allclose(n[2], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(n[3], [0.0, -1.0, 0.0])
    np.testing.assert_array_equal(n[4], 0.0)
    # Vertices 2 and 3 in one group share the normal of both triangles (as vertex 0's).
    shared = vertex_normals(v, t, np.array([0, 1, 2, 2, 3]))
    np.testing.assert_allclose(shared[2], shared[3])
    np.testing.assert_allclose(shared[2], n[0], atol=1e-7)
