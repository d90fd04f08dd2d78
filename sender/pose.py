"""Head pose from the tracked 68 points: weighted, robust Gauss-Newton.

Frames as docs/DESIGN.md §2: model space mm (x toward the person's left, y up, z out of the face);
GL camera frame (x right, y up, z toward the viewer, the camera looks along -z);
``X_cam = R X + t``, image point ``u = cx + fx X/d``, ``v = cy - fy Y/d``, ``d = -Z_cam``.

Fit
---
The model is the person's landmark vertices ``L`` (68, 3): the neutral ones
(``mesh.vertices[mesh.landmarks]``), or, passed as ``shape``, the landmarks under the
current expression estimate (``sender.lift.pose_and_lift`` alternates the two). The pose
minimises the weighted, robust reprojection error

    E(R, t) = sum_i w_i rho(|pi(R L_i + t) - p_i|),

with ``rho`` Huber's loss (quadratic up to ``HUBER`` = 0.05 x the image's outer-eye
distance, about 5 px on a face whose eyes are 100 px apart, 5 times the tracker's noise;
linear beyond; iteratively reweighted on the first ``REWEIGHT_ITERATIONS`` = 2 steps, then
frozen: reweighting every step converges only linearly, by 0.7 a step, when many points
lie beyond the knee) and ``w_i`` = ``POSE_WEIGHTS``: 1 for the 9 rigid feature
points (``models.landmarks.RIGID``), lower for the points that move with expression or slide,
0 for the jaw contour and the inner lips. The weights were measured (``GROUP_WEIGHTS``): on
6 shared clips (lp_d0, lp_d3, lp_d14, openface_default, openface_gaze, hdtf_katiehill; up to
600 frames each; generic head; pose from the 9 rigid points alone), the RMS over time of
each point's reprojection residual about its clip median, in outer-eye distances, averaged
per group: rigid 0.0130, nose (28, 29, 32, 34) 0.0138, eyelids 0.0205, brows 0.0316, outer
lip 0.0422, inner lip 0.0437, jaw contour 0.0600. Inverse variance relative to the rigid
points, ``w = (s_rigid / s_group)^2``, gives 0.89, 0.40, 0.17, 0.095, 0.089, 0.047; the
weights are those rounded down (nose 0.8, eyelids 0.4, brows 0.15, outer lip 0.05). The jaw
contour and the inner lips get 0: the contour is a silhouette that slides over the surface
as the head turns (a bias that follows yaw, not noise that averages out), and the inner lips
are the edges of the mesh's lip slit, not surface points.

Gauss-Newton on 6 parameters: ``R <- exp([w]_x) R``, ``t <- t + dt``, at most
``MAX_ITERATIONS`` steps, stopping when the step is below 1e-4 rad and 0.02 mm (a tenth of
the packet's quanta). No Levenberg-Marquardt damping: the problem is ill-conditioned (a
small turn about y trades against a shift in x under a near-orthographic view), and damping
of 1e-3 of the diagonal slowed the steps along that direction to a factor 0.5 each, never
converging in 10; the start is always close (previous frame, or SQPnP). It starts from the
previous frame's raw pose; on acquisition (no previous pose, or after a failure) from
``cv2.solvePnP`` (SQPnP) on the points with weight >= 0.5 (converted from OpenCV's frame by
``S = diag(1, -1, -1)``: ``models.geometry.Pose.from_opencv``). A pose is rejected (None)
when a step cannot be solved, a weighted point falls behind the camera, the result is not
finite, or the median reprojection error of the 9 rigid points exceeds ``MAX_POSE_ERROR``
(0.15) of the image eye distance (as ``sender.enroll.fit``).

Temporal filter
---------------
The raw pose is smoothed by ``sender.smoothing.PoseFilter`` (One-Euro; the pipeline applies
it). On each clip's stillest second of openface_gaze.avi, lp_d0.mp4 and lp_d3.mp4 the raw
pose turns 0.54-0.87 deg from frame to frame (median; the points are whole pixels).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.linalg.lapack import dgesv as _dgesv

from facewire.models.geometry import Intrinsics, Pose, rotation_matrix
from facewire.models.landmarks import N_LANDMARKS, RIGID

__all__ = ["POSE_WEIGHTS", "GROUP_WEIGHTS", "PoseSolver"]

# Measured weights per landmark group (module docstring); rigid feature points are 1.
GROUP_WEIGHTS: dict[str, tuple[tuple[int, ...], float]] = {
    "jaw_contour": (tuple(range(0, 17)), 0.0),
    "brows": (tuple(range(17, 27)), 0.15),
    "nose": ((28, 29, 32, 34), 0.8),
    "eyelids": ((37, 38, 40, 41, 43, 44, 46, 47), 0.4),
    "outer_lip": (tuple(range(48, 60)), 0.05),
    "inner_lip": (tuple(range(60, 68)), 0.0),
}


def _pose_weights() -> np.ndarray:
    w = np.zeros(N_LANDMARKS)
    for points, weight in GROUP_WEIGHTS.values():
        w[list(points)] = weight
    w[RIGID] = 1.0
    w.setflags(write=False)
    return w


POSE_WEIGHTS = _pose_weights()
HUBER = 0.05  # of the image outer-eye distance: Huber's knee
REWEIGHT_ITERATIONS = 2  # Huber weights are recomputed on the first iterations only
MAX_ITERATIONS = 10
STEP_RAD = 1e-4  # converged when a step turns less than this (0.006 deg) ...
STEP_MM = 0.02  # ... and moves less than this (mm); quanta: 0.1 deg, 0.25 mm
MAX_POSE_ERROR = 0.15
ACQUIRE_WEIGHT = 0.5


class PoseSolver:
    """The weighted robust fit of one model's neutral landmarks (module docstring).

    Args:
        landmarks3d: (68, 3) neutral landmark positions, model space, mm.
        camera: the sender camera's intrinsics.
        weights: (68,) non-negative weights; ``POSE_WEIGHTS`` by default.

    Raises:
        ValueError: wrong shapes, non-finite values, or fewer than 4 weighted points.
    """

    def __init__(self, landmarks3d: np.ndarray, camera: Intrinsics,
                 weights: np.ndarray = POSE_WEIGHTS) -> None:
        model = np.asarray(landmarks3d, np.float64)
        if model.shape != (N_LANDMARKS, 3) or not np.isfinite(model).all():
            raise ValueError(f"landmarks3d: expected finite (68, 3), got {model.shape}")
        weights = np.asarray(weights, np.float64)
        if weights.shape != (N_LANDMARKS,) or not (np.isfinite(weights).all()
                                                  and (weights >= 0).all()):
            raise ValueError("weights: expected (68,) finite non-negative values")
        if np.count_nonzero(weights) < 4:
            raise ValueError("weights: at least 4 points must have a positive weight")
        if not isinstance(camera, Intrinsics):
            raise ValueError(f"camera: expected a models.geometry.Intrinsics, got "
                             f"{type(camera).__name__}")
        self.camera = camera
        self._used = np.flatnonzero(weights > 0)
        self._model = model[self._used]
        self._weights = weights[self._used]
        self._rigid = np.searchsorted(self._used, RIGID)
        self._acquire = np.flatnonzero(weights >= ACQUIRE_WEIGHT)
        self._acquire_model = np.ascontiguousarray(model[self._acquire])
        self._k = camera.matrix()
        self._focal = np.array([[camera.fx], [-camera.fy]])  # u = cx + fx a, v = cy - fy b
        self._centre = np.array([[camera.cx], [camera.cy]])

    def solve(self, points: np.ndarray, start: Pose | None = None,
              shape: np.ndarray | None = None) -> Pose | None:
        """The pose of the model against one frame's points.

        Args:
            points: (68, 2) image points, pixels (origin top-left, y down), finite.
            start: where to start (the previous frame's raw pose); None to acquire.
            shape: (68, 3) landmark positions to fit instead of the neutral ones (the
                model's landmarks under the current expression, ``Rig.landmarks``), mm.

        Returns:
            The pose, or None when it is rejected (module docstring).
        """
        p = np.asarray(points, np.float64)
        if p.shape != (N_LANDMARKS, 2) or not np.isfinite(p).all():
            raise ValueError(f"points: expected finite (68, 2), got {p.shape}")
        model = self._model
        if shape is not None:
            shape = np.asarray(shape, np.float64)
            if shape.shape != (N_LANDMARKS, 3) or not np.isfinite(shape).all():
                raise ValueError(f"shape: expected finite (68, 3), got {shape.shape}")
            model = shape[self._used]
        if start is None:
            start = self._acquire_pose(p, None if shape is None else shape[self._acquire])
            if start is None:
                return None
        eye_px = float(np.hypot(*(p[36] - p[45])))
        if eye_px <= 0:
            return None
        # (3, K) model points and (2, K) observations: coordinates as rows, so that every
        # step below is one vectorised operation over all points
        model_t = np.ascontiguousarray(model.T)
        obs = np.ascontiguousarray(p[self._used].T)
        fitted = self._gauss_newton(model_t, obs, start, HUBER * eye_px)
        if fitted is None:
            return None
        return self._accept(*fitted, model_t, obs, eye_px)

    def _gauss_newton(self, model_t: np.ndarray, obs: np.ndarray, start: Pose,
                      knee: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The reweighted Gauss-Newton steps (module docstring) from ``start``.

        Args:
            model_t: (3, K) the used model points, mm.
            obs: (2, K) their observed image points, pixels.
            start: the starting pose.
            knee: Huber's knee, pixels.

        Returns:
            (3, 3) R and (3,) t, or None when a point falls at or behind the camera or a
            step cannot be solved.
        """
        r, t = start.rotation.copy(), start.translation.copy()
        k = obs.shape[1]
        # rows 0-5: the Jacobian d(u, v)/d(w, t), transposed (columns: u of every point,
        # then v); row 6: the residuals. One product gives the normal matrix and the gradient.
        system = np.zeros((7, 2 * k))
        jac = system[:6]
        rows = system.reshape(7, 2, k)  # [row, u or v, point]
        w2 = np.empty((2, k))
        focal, centre = self._focal, self._centre
        for iteration in range(MAX_ITERATIONS):
            rx = r @ model_t  # (3, K) rotated model points
            x = rx + t[:, None]
            if np.maximum.reduce(x[2]) >= 0:  # a point at or behind the camera (d = -Z <= 0)
                return None
            inv = -1.0 / x[2]  # 1 / d
            ab = x[:2] * inv  # (a, b) = (X, Y) / d
            np.multiply(focal, ab, out=rows[6])  # (fx a, -fy b)
            rows[6] += centre
            rows[6] -= obs  # (u, v) - observed
            if iteration < REWEIGHT_ITERATIONS:  # Huber weights, then frozen (quadratic steps)
                norm = np.sqrt(np.add.reduce(rows[6] * rows[6], axis=0))
                w2[:] = self._weights * np.minimum(1.0, knee / np.maximum(norm, 1e-12))
            # d(u, v)/d(w, t) with X = exp([w]) R L + t, dX = w x RL + dt:
            # du = su (dX + a dZ), dv = sv (dY + b dZ), (su, sv) = (fx, -fy) / d
            rxx, ry, rz = rx
            s_uv = focal * inv  # (su, sv)
            su, sv = s_uv
            sab = s_uv * ab  # (su a, sv b)
            np.multiply(sab, ry, out=rows[0])
            rows[0, 1] -= sv * rz
            np.multiply(sab, -rxx, out=rows[1])
            rows[1, 0] += su * rz
            np.multiply(su, -ry, out=rows[2, 0])
            np.multiply(sv, rxx, out=rows[2, 1])
            rows[3, 0] = su
            rows[4, 1] = sv
            rows[5] = sab
            normal_grad = (jac * w2.reshape(-1)) @ system.T  # (6, 7): [J^T W J | J^T W res]
            _, _, step, info = _dgesv(normal_grad[:, :6], normal_grad[:, 6])
            if info != 0 or not np.isfinite(step).all():  # singular or overflowing
                return None
            r = rotation_matrix(-step[:3]) @ r
            t = t - step[3:]
            wx, wy, wz, dx, dy, dz = step.tolist()
            if (iteration >= REWEIGHT_ITERATIONS - 1 and max(abs(wx), abs(wy), abs(wz)) < STEP_RAD
                    and max(abs(dx), abs(dy), abs(dz)) < STEP_MM):
                break
        return r, t

    def _accept(self, r: np.ndarray, t: np.ndarray, model_t: np.ndarray, obs: np.ndarray,
                eye_px: float) -> Pose | None:
        """The pose (r, t), or None when it is not finite, puts a point at or behind the
        camera, or leaves the rigid points' median reprojection error above
        ``MAX_POSE_ERROR`` image eye distances ``eye_px``."""
        if not (np.isfinite(r).all() and np.isfinite(t).all()):
            return None
        x = r @ model_t + t[:, None]
        if np.maximum.reduce(x[2]) >= 0:
            return None
        rigid = x[:, self._rigid]
        proj = self._focal * (rigid[:2] / -rigid[2]) + self._centre
        error = np.sqrt(np.add.reduce((proj - obs[:, self._rigid]) ** 2, axis=0))
        if np.sort(error)[len(error) // 2] > MAX_POSE_ERROR * eye_px:  # median (9 points)
            return None
        return Pose(rotation=r, translation=t)

    def _acquire_pose(self, p: np.ndarray, model: np.ndarray | None) -> Pose | None:
        """SQPnP on the strongly weighted points, in the GL frame; None on failure."""
        img = np.ascontiguousarray(p[self._acquire])
        obj = self._acquire_model if model is None else np.ascontiguousarray(model)
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, self._k, None,
                                          flags=cv2.SOLVEPNP_SQPNP)
        except cv2.error:
            return None
        if not ok or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
            return None
        return Pose.from_opencv(rotation_matrix(rvec.ravel()), tvec)
