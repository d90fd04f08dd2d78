"""How a virtual camera frames a head: the enrollment preview's views and the receiver's.

A square-pixel camera whose vertical field of view ``FOV_DEG`` holds ``FIELD_EYE_DISTANCES``
outer-eye distances (landmarks 36 to 45, in x and y) across the image height, the field

    field = FIELD_EYE_DISTANCES * |l_36 - l_45|,

aimed at the head centre ``c``, the 68 landmarks' mean raised by ``FIELD_RAISE`` of the field
(model +y), from the distance that makes the field fill the height,

    d = field / (2 tan(FOV_DEG / 2)),

on the orbit of ``models.infra.raster.orbit_pose`` around ``c``: from the front (yaw 0) or
from a three-quarter view (``THREE_QUARTER_YAW_DEG`` toward the person's left, model +x).

The enrollment's preview (``sender.enroll.build.preview_cameras``, and its crop of the
neutral frame with the same field and raise in pixels) and the receiver's virtual views
(``receiver.views.virtual_view``) frame the same way, so the preview shows the heads the
receiver will; the receiver cannot import the sender, so the framing lives here.
"""

from __future__ import annotations

import numpy as np

from facewire.models.geometry import Pose
from facewire.models.infra.raster import orbit_pose
from facewire.models.landmarks import outer_eye_distance

FOV_DEG = 25.0  # vertical field of view, degrees
FIELD_EYE_DISTANCES = 3.6  # the field's height, in outer-eye distances
FIELD_RAISE = 0.1  # the centre above the landmarks' mean, in fields
THREE_QUARTER_YAW_DEG = 35.0  # the three-quarter view, toward the person's left


def head_field(landmarks: np.ndarray) -> tuple[np.ndarray, float]:
    """The point a framing aims at, and the field it frames (module docstring).

    Args:
        landmarks: (68, 3) finite landmark positions, mm.

    Returns:
        (3,) float64 centre ``c`` and the field's height, mm (0 when the outer eye corners
        coincide in x and y: the caller refuses such a head).
    """
    field = FIELD_EYE_DISTANCES * float(outer_eye_distance(landmarks[:, :2]))
    return landmarks.mean(axis=0) + [0.0, FIELD_RAISE * field, 0.0], field


def framing_pose(yaw_deg: float, centre: np.ndarray, field: float) -> Pose:
    """The camera pose that frames a ``field`` mm high around ``centre`` from ``yaw_deg``.

    Raises:
        models.infra.raster.RenderError: the field is not positive.
    """
    distance = field / (2 * np.tan(np.radians(FOV_DEG) / 2))
    return orbit_pose(yaw_deg, 0.0, distance, centre)
