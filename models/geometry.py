"""The geometry both hosts share: camera intrinsics, rotations, the head pose, projection, normals.

Frames
------
- Model space: millimetres, right-handed, x toward the person's left, y up, z toward the
  camera (out of the face).
- GL camera frame (docs/DESIGN.md §2): x right, y up, the camera looking along -z. A pose (R, t)
  maps model to camera, ``X_cam = R X + t``; a head in front of the camera has depth
  ``d = -Z_cam > 0`` (``t_z < 0``).
- Image: pixels, origin top-left, rows down, pixel centres at integers (as dlib and OpenCV).
  A GL camera point projects to

      u = cx + fx X / d,        v = cy - fy Y / d,        d = -Z.

- OpenCV's camera frame (x right, y down, z forward), used only where an OpenCV solver
  runs: ``X_cv = S X_gl`` with ``S = diag(1, -1, -1)``, so a pose converts as
  ``R_gl = S R_cv``, ``t_gl = S t_cv`` (``Pose.from_opencv``, ``Pose.to_opencv``), and the
  intrinsic matrix ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` is OpenCV's.

Rotations
---------
A rotation vector r is axis times angle (radians). ``rotation_matrix`` is Rodrigues'
formula, ``R = I + sin(a) [k]_x + (1 - cos(a)) [k]_x^2`` with ``a = |r|``, ``k = r / a``;
``rotation_vector`` is its inverse with the angle in [0, pi]. Both are OpenCV's
``cv2.Rodrigues`` (the one implementation: the sender's packets were made with it, and its
results are bit-exact with those packets). ``rotation_matrices`` is the same formula for many
vectors at once in numpy (the enrollment's structure-from-motion evaluates it for every
frame at every solver step), written with the unnormalised ``[r]_x`` so that it is stable
near the identity: ``R = I + s [r]_x + c [r]_x^2``, ``s = sin(a) / a``,
``c = (1 - cos(a)) / a^2 = 2 sin^2(a / 2) / a^2`` (``s = 1``, ``c = 1/2`` at ``a = 0``); it
agrees with ``rotation_matrix`` within float round-off, not to the bit.

Intrinsics
----------
``Intrinsics`` holds a pinhole camera's fx, fy, cx, cy (pixels) and image size. Its bounds
are the wire's, one set defined in ``protocol.control`` beside the ``Camera`` a Hello carries
(``MAX_FOCAL_PX``, ``MAX_PRINCIPAL_PX``, ``MAX_IMAGE_SIDE``): fx, fy in (0, 1e6), cx, cy
finite with ``|c| < 1e5``, width and height integers in [1, 16384]. ``intrinsics_guess`` is
the guess for an unknown webcam; resizing an image by ``s = W' / W`` maps a pixel centre u
to ``s (u + 1/2) - 1/2`` (``Intrinsics.resized``).

Vertex normals
--------------
``vertex_normals`` of a triangle mesh: each vertex's unit normal is the normalised sum of its
triangles' ``(b - a) x (c - a)`` (counter-clockwise from outside), i.e. their normals
weighted by area; a vertex in no triangle gets zero. With ``groups``, the vertices of one
group (the copies of a vertex on a UV seam) share the normal of all their triangles. The
person model's mesh, the rasteriser (every frame) and the texture projection use it.

Head pose yaw and pitch are those of the face's forward axis ``f = R e_z`` in the camera:
``yaw = atan2(f_x, f_z)`` (positive: the nose turns toward the image's right),
``pitch = atan2(f_y, hypot(f_x, f_z))`` (positive: chin up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from facewire.protocol.control import MAX_FOCAL_PX, MAX_IMAGE_SIDE, MAX_PRINCIPAL_PX

OPENCV_FLIP = np.diag([1.0, -1.0, -1.0])  # S: GL camera frame <-> OpenCV camera frame
OPENCV_FLIP.setflags(write=False)


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera's intrinsics for a ``width`` x ``height`` image (module docstring).

    Attributes:
        fx, fy: focal lengths, px, in (0, 1e6).
        cx, cy: principal point, px (origin top-left, centres at integers), |c| < 1e5.
        width, height: image size, px, integers in [1, 16384].

    Raises:
        ValueError: a field of the wrong type or out of bounds; the message names it.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer,
                                                                 np.floating)):
                raise ValueError(f"{name}: expected a number, got {type(value).__name__}")
            value = float(value)
            if not math.isfinite(value):
                raise ValueError(f"{name}: must be finite, got {value}")
            if name in ("fx", "fy") and not 0 < value < MAX_FOCAL_PX:
                raise ValueError(f"{name}: must be in (0, {MAX_FOCAL_PX:g}), got {value}")
            if name in ("cx", "cy") and not abs(value) < MAX_PRINCIPAL_PX:
                raise ValueError(f"{name}: must be in (-{MAX_PRINCIPAL_PX:g}, "
                                 f"{MAX_PRINCIPAL_PX:g}), got {value}")
            object.__setattr__(self, name, value)
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"{name}: expected an integer, got {type(value).__name__}")
            if not 1 <= value <= MAX_IMAGE_SIDE:
                raise ValueError(f"{name}: must be in [1, {MAX_IMAGE_SIDE}], got {value}")
            object.__setattr__(self, name, int(value))

    def matrix(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix K (OpenCV's)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def resized(self, width: int, height: int) -> Intrinsics:
        """The intrinsics of the image resized to ``width`` x ``height`` (module docstring)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                          (self.cy + 0.5) * sy - 0.5, width, height)


def intrinsics_guess(width: int, height: int) -> Intrinsics:
    """Intrinsics for an unknown webcam: ``fx = fy = width``, principal point at the centre.

    ``fx = width`` is a 53 deg horizontal field of view, between a narrow laptop camera
    (~45 deg) and a wide desk webcam (~70 deg, ``fx = 0.71 width``). With the face far from the
    camera compared with its own depth, a wrong focal length mostly trades against the head's
    distance (which the enrollment's scale convention already leaves arbitrary), not against
    its shape.

    Args:
        width, height: image size in pixels, in [1, 16384].

    Returns:
        fx = fy = width, cx = (width - 1) / 2, cy = (height - 1) / 2.
    """
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{name}: expected an integer, got {type(value).__name__}")
        if not 1 <= value <= MAX_IMAGE_SIDE:
            raise ValueError(f"{name}: must be in [1, {MAX_IMAGE_SIDE}], got {value}")
    f = float(width)
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height))


def rotation_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula (module docstring).

    Args:
        rvec: (3,) finite rotation vector, radians.

    Returns:
        (3, 3) float64 rotation matrix.
    """
    r = np.asarray(rvec, np.float64)
    if r.size != 3 or not _finite(r):
        raise ValueError(f"rvec: expected a finite (3,) rotation vector, got shape {r.shape}")
    return cv2.Rodrigues(r.reshape(3, 1))[0]


def rotation_matrices(rvecs: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for many rotation vectors at once (module docstring).

    No checks: it serves inner loops (a solver's residuals), whose callers hold their
    vectors' shape.

    Args:
        rvecs: (F, 3) float rotation vectors, radians.

    Returns:
        (F, 3, 3) float64 rotation matrices, ``rotation_matrix`` of each row within round-off.
    """
    r = np.asarray(rvecs, np.float64)
    a = np.linalg.norm(r, axis=1)
    small = a < 1e-12
    safe = np.where(small, 1.0, a)
    s = np.where(small, 1.0, np.sin(a) / safe)[:, None, None]
    c = np.where(small, 0.5, 2.0 * np.sin(0.5 * a) ** 2 / safe ** 2)[:, None, None]
    x, y, z = r[:, 0], r[:, 1], r[:, 2]
    zero = np.zeros_like(x)
    cross = np.stack([np.stack([zero, -z, y], axis=1),
                      np.stack([z, zero, -x], axis=1),
                      np.stack([-y, x, zero], axis=1)], axis=1)  # [r]_x, (F, 3, 3)
    return np.eye(3) + s * cross + c * (cross @ cross)


def rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """The rotation vector of a rotation matrix, angle in [0, pi].

    Args:
        rotation: (3, 3) finite rotation matrix.

    Returns:
        (3,) float64 rotation vector, radians.
    """
    r = np.asarray(rotation, np.float64)
    if r.shape != (3, 3) or not _finite(r):
        raise ValueError(f"rotation: expected a finite (3, 3) matrix, got shape {r.shape}")
    return cv2.Rodrigues(r)[0].ravel()


@dataclass(frozen=True, eq=False)
class Pose:
    """A head (or camera) pose in the GL camera frame: ``X_cam = rotation @ X + translation``.

    Attributes:
        rotation: (3, 3) float64, model to camera, a rotation (orthonormal within 1e-5,
            determinant +1).
        translation: (3,) float64, mm; a head in front of the camera has translation[2] < 0.

    Raises:
        ValueError: wrong shapes, non-finite values or not a rotation (naming the field).
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, np.float64)
        t = np.asarray(self.translation, np.float64)
        if r.shape != (3, 3) or not _finite(r):
            raise ValueError(f"rotation: expected a finite (3, 3) array, got shape {r.shape}")
        if not _is_rotation(r):
            raise ValueError("rotation: not a rotation matrix")
        if t.shape != (3,) or not _finite(t):
            raise ValueError(f"translation: expected a finite (3,) array, got shape {t.shape}")
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    @classmethod
    def from_opencv(cls, rotation: np.ndarray, translation: np.ndarray) -> Pose:
        """The GL pose of an OpenCV pose: ``(S R_cv, S t_cv)``.

        Args:
            rotation: (3, 3) rotation, model to OpenCV camera.
            translation: (3,) or (3, 1), mm.
        """
        return cls(OPENCV_FLIP @ rotation, OPENCV_FLIP @ np.ravel(translation))

    def to_opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """(3, 3) rotation and (3,) translation in OpenCV's camera frame: ``(S R, S t)``."""
        return OPENCV_FLIP @ self.rotation, OPENCV_FLIP @ self.translation

    @property
    def yaw_deg(self) -> float:
        """Yaw of the face's forward axis, degrees (module docstring)."""
        f = self.rotation[:, 2]
        return float(np.degrees(np.arctan2(f[0], f[2])))

    @property
    def pitch_deg(self) -> float:
        """Pitch of the face's forward axis, degrees, positive chin up."""
        f = self.rotation[:, 2]
        return float(np.degrees(np.arctan2(f[1], np.hypot(f[0], f[2]))))


def project(points: np.ndarray, pose: Pose, intrinsics: Intrinsics) -> np.ndarray:
    """Image points of model points seen under a pose (module docstring).

    Args:
        points: (K, 3) model points, mm, in front of the camera.
        pose: model to GL camera.
        intrinsics: the camera.

    Returns:
        (K, 2) float64 (u, v): column and row, pixels.
    """
    cam = np.asarray(points, np.float64) @ pose.rotation.T + pose.translation
    d = -cam[:, 2]
    return np.column_stack([intrinsics.cx + intrinsics.fx * cam[:, 0] / d,
                            intrinsics.cy - intrinsics.fy * cam[:, 1] / d])


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray,
                   groups: np.ndarray | None = None) -> np.ndarray:
    """Area-weighted unit vertex normals (module docstring).

    Args:
        vertices: (N, 3) float positions; the sums are taken in their dtype.
        triangles: (M, 3) int vertex indices, counter-clockwise from outside.
        groups: optional (N,) int group of each vertex, from 0; a group shares one normal.

    Returns:
        (N, 3) float32 unit normals (zero for a vertex, or group, in no triangle).
    """
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    if groups is None:
        corners, size = triangles.ravel(), len(vertices)
    else:
        corners, size = groups[triangles].ravel(), int(groups.max()) + 1
    normals = np.column_stack([np.bincount(corners, weights=np.repeat(face[:, k], 3),
                                           minlength=size) for k in range(3)])
    if groups is not None:
        normals = normals[groups]
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return (normals / np.maximum(length, 1e-12)).astype(np.float32)


def _finite(a: np.ndarray) -> bool:
    """All of a small array's values are finite (in Python: several times faster than
    ``np.isfinite(a).all()`` on 3 or 9 values, and poses are made many times a frame)."""
    return all(map(math.isfinite, a.ravel().tolist()))


def _is_rotation(r: np.ndarray) -> bool:
    """A finite (3, 3) matrix is a rotation: ``R R^T = I`` within 1e-5, determinant > 0."""
    (a, b, c), (d, e, f), (g, h, i) = r.tolist()
    gram = (a * a + b * b + c * c - 1.0, d * d + e * e + f * f - 1.0,
            g * g + h * h + i * i - 1.0, a * d + b * e + c * f, a * g + b * h + c * i,
            d * g + e * h + f * i)
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return max(map(abs, gram)) <= 1e-5 and det > 0
