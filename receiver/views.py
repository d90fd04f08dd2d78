"""The receiver's two kinds of view: the sender's camera, and a free virtual camera.

Poses follow the GL camera of docs/DESIGN.md §2 (X_cam = R X + t; x right, y up, looking along
-z) and the packet's pose: ``rotation`` is a (3,) rotation vector (axis times angle, radians,
as ``protocol.packet.Frame`` carries it) or a (3, 3) rotation matrix, model to camera.

Sender view (``sender_view``): the sender's intrinsics from the Hello (the wire's
``protocol.control.Camera``, converted to ``models.geometry.Intrinsics`` here, the
receiver's one place), scaled to the output (``Intrinsics.resized``), with the received pose,
so that the render lines up with the sender's frame resized to the output. Pixel centres sit
at integers and an image of W pixels spans [-1/2, W - 1/2], so a scale s = W' / W maps u to
s (u + 1/2) - 1/2: fx' = s fx, cx' = s (cx + 1/2) - 1/2, and the same in y with H' / H (an
output of another aspect ratio stretches like a resized frame).

Virtual view (``virtual_view``): a square-pixel camera framing the head as the enrollment
preview does (``models.framing``: a field of ``FIELD_EYE_DISTANCES`` outer-eye distances
across the height of a ``FOV_DEG`` view, aimed at the head centre c, the landmarks' mean
raised by a tenth of the field), from the front (yaw 0) or from a three-quarter view
(``THREE_QUARTER_YAW_DEG`` toward the person's left, the model's +x). The head turns by the
received rotation about c and stays there (the translation is not followed): a model point X
is seen at R_v (R (X - c) + c) + t_v, with (R_v, t_v) the framing's orbit pose
(``models.framing.framing_pose``) around c, so c is always at the image centre.
"""

from __future__ import annotations

import numpy as np

from facewire.models.framing import FOV_DEG, THREE_QUARTER_YAW_DEG, framing_pose, head_field
from facewire.models.geometry import Intrinsics, Pose, rotation_matrix
from facewire.models.infra.raster import Camera, RenderError
from facewire.models.landmarks import N_LANDMARKS
from facewire.models.mesh import Mesh
from facewire.protocol import control

VIEW_KINDS = ("front", "three-quarter")


def _pose(rotation: np.ndarray, translation: np.ndarray) -> Pose:
    """The received pose: ``rotation`` a (3,) rotation vector (radians) or a (3, 3) matrix,
    ``translation`` (3,) mm; RenderError naming the field when either is malformed."""
    r = np.asarray(rotation, np.float64)
    try:
        matrix = r if r.shape == (3, 3) else rotation_matrix(r)
    except ValueError as e:
        raise RenderError(f"rotation: expected a (3,) rotation vector or a (3, 3) matrix "
                          f"({e})") from e
    try:
        return Pose(matrix, translation)
    except ValueError as e:
        raise RenderError(str(e)) from e


def sender_view(hello_camera: control.Camera, rotation: np.ndarray, translation: np.ndarray,
                width: int, height: int) -> Camera:
    """The sender's camera with the received pose, for a ``width`` x ``height`` output.

    Args:
        hello_camera: the sender's intrinsics from the Hello.
        rotation: (3,) rotation vector (radians) or (3, 3) matrix, model to camera.
        translation: (3,) mm, the model origin in the camera frame (z < 0 in front).
        width, height: output size in pixels.

    Returns:
        The camera (module docstring).

    Raises:
        RenderError: bad arguments (the message names the field).
    """
    if not isinstance(hello_camera, control.Camera):
        raise RenderError(f"hello_camera: expected a protocol.control.Camera, got "
                          f"{type(hello_camera).__name__}")
    _check_size(width, height)
    c = hello_camera
    try:
        intrinsics = Intrinsics(c.fx, c.fy, c.cx, c.cy, c.width, c.height).resized(width, height)
    except ValueError as e:
        raise RenderError(f"camera.{e}") from e
    return Camera(intrinsics, _pose(rotation, translation))


def head_centre(head: Mesh | np.ndarray) -> tuple[np.ndarray, float]:
    """The point a virtual view aims at, and the field it frames.

    Args:
        head: the model's neutral mesh, or its (68, 3) landmark positions, mm.

    Returns:
        (3,) float64 centre c (module docstring) and the field's height, mm.

    Raises:
        RenderError: not a Mesh or a finite (68, 3) array.
    """
    if isinstance(head, Mesh):
        landmarks = head.vertices[head.landmarks].astype(np.float64)
    else:
        landmarks = np.asarray(head, np.float64)
        if landmarks.shape != (N_LANDMARKS, 3) or not np.isfinite(landmarks).all():
            raise RenderError(f"head: expected a Mesh or finite ({N_LANDMARKS}, 3) landmarks, "
                              f"got shape {landmarks.shape}")
    centre, field = head_field(landmarks)
    if not field > 0:
        raise RenderError("head: the outer eye corners (36, 45) coincide")
    return centre, field


def virtual_view(kind: str, head: Mesh | np.ndarray, rotation: np.ndarray, width: int,
                 height: int) -> Camera:
    """A virtual camera framing the head, which turns by ``rotation`` about its centre.

    Args:
        kind: "front" or "three-quarter".
        head: the model's neutral mesh, or its (68, 3) landmark positions, mm.
        rotation: (3,) rotation vector (radians) or (3, 3) matrix: the received head rotation.
        width, height: output size in pixels.

    Returns:
        The camera (module docstring); the head centre projects to the image centre.

    Raises:
        RenderError: bad arguments (the message names the field).
    """
    if kind not in VIEW_KINDS:
        raise RenderError(f"kind: expected one of {', '.join(VIEW_KINDS)}, got {kind!r}")
    _check_size(width, height)
    turn = _pose(rotation, np.zeros(3)).rotation
    centre, field = head_centre(head)
    yaw = 0.0 if kind == "front" else THREE_QUARTER_YAW_DEG
    view = framing_pose(yaw, centre, field)
    pose = Pose(view.rotation @ turn,
                view.rotation @ (centre - turn @ centre) + view.translation)
    return Camera.virtual(width, height, pose, fov_y_deg=FOV_DEG)


def _check_size(width: int, height: int) -> None:
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise RenderError(f"width, height: expected positive ints, got {width!r}, {height!r}")
