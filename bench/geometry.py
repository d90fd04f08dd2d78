"""Geometry fidelity: the 68 landmarks one packet describes, against the tracker's.

The user's card (``../shared/DESIGN.md``), "How we judge the result"; docs/DESIGN.md §8.
For frame f with decoded rotation vector ``w_f`` (radians), translation ``t_f`` (mm) and
tangent residuals ``r_f`` (9, 2):

    D_f   = rig.from_tangent(r_f)                      (9, 3) model-space displacements
    X_f   = rig.landmarks(D_f)                          (68, 3) morphed landmark vertices
    C_f   = X_f R(w_f)^T + t_f                          camera frame (GL: x right, y up,
                                                        z toward the viewer; d = -z > 0)
    p_f,i = (cx + fx C_x / d, cy - fy C_y / d)          pixels, with the Hello's camera

(``Rig`` is the model's RBF volume morph, ``models/rig.py``; R(w) is Rodrigues' formula,
``models.geometry.rotation_matrix``.)
The reconstruction is compared with the tracker's own 68 points ``q_f`` on that frame:

    NME_f = mean_{i in HELD_OUT} |p_f,i - q_f,i| / |q_f,36 - q_f,45|

over the 50 points the packet never carries (``models.landmarks.HELD_OUT``), normalised by
the tracked outer-eye-corner distance (``models.landmarks.nme``). The rigid-only NME is the
same with zero residuals (``X_f`` = the neutral landmark vertices): what the pose alone
explains. A frame is measured when its packet says ``FACE_PRESENT`` without
``TRACKING_LOST`` (with ``TRACKING_LOST`` the packet repeats the last good pose) and the
tracker gave points; other frames are NaN.

The unweighted NME is the same (pose and residuals) over ``UNWEIGHTED``, the 24 points that
carry no weight in the sender's pose fit (``sender.pose.POSE_WEIGHTS`` = 0) and are not
sent: the jaw contour 0-16 without the chin 8 (a non-rigid feature point, in the packet),
and the inner lips 60-67. The pose fit never sees them, so they show how well pose, lift
and morph carry the parts of the face the fit ignores. Issue 16 says 24 points: weight 0
falls on 25 (0-16 and 60-67), one of which, the chin, the packet carries.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from facewire.models.geometry import rotation_matrix
from facewire.models.landmarks import FEATURES, HELD_OUT, N_LANDMARKS, nme
from facewire.models.rig import N_RESIDUALS, Rig
from facewire.protocol.packet import FRAME_DTYPE, Flag, Frame
from facewire.sender.pose import POSE_WEIGHTS

UNWEIGHTED = np.setdiff1d(np.flatnonzero(POSE_WEIGHTS == 0), FEATURES)  # (24,) module docstring


class GeometryNME(NamedTuple):
    """Per-frame NME (fractions of the outer-eye distance; NaN where not measured).

    Attributes:
        heldout: (F,) float64, pose and residuals.
        rigid_only: (F,) float64, pose alone.
        unweighted: (F,) float64, pose and residuals, over ``UNWEIGHTED`` (24 points).
    """

    heldout: np.ndarray
    rigid_only: np.ndarray
    unweighted: np.ndarray


def _intrinsics(camera: Any) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from a camera object with those attributes or a 4-sequence."""
    if all(hasattr(camera, k) for k in ("fx", "fy", "cx", "cy")):
        values: tuple[Any, ...] = (camera.fx, camera.fy, camera.cx, camera.cy)
    else:
        values = tuple(np.asarray(camera, np.float64).reshape(-1))
    if len(values) != 4 or not np.isfinite(values).all() or min(values[:2]) <= 0:
        raise ValueError(f"camera: expected finite (fx, fy, cx, cy) with fx, fy > 0, "
                         f"got {camera!r}")
    fx, fy, cx, cy = (float(v) for v in values)
    return fx, fy, cx, cy


def _records(decoded: np.ndarray | Sequence[Frame]) -> np.ndarray:
    """(F,) ``FRAME_DTYPE`` from a decoded record array or a list of ``Frame``s."""
    if isinstance(decoded, np.ndarray):
        if decoded.dtype != FRAME_DTYPE or decoded.ndim != 1:
            raise ValueError(f"decoded: expected a 1-D FRAME_DTYPE array, got "
                             f"{decoded.shape} {decoded.dtype}")
        return decoded
    records = np.zeros(len(decoded), FRAME_DTYPE)
    for i, frame in enumerate(decoded):
        if not isinstance(frame, Frame):
            raise ValueError(f"decoded[{i}]: expected a protocol.packet.Frame, "
                             f"got {type(frame).__name__}")
        records[i] = frame.to_record()
    return records


def project_landmarks(rig: Rig, camera: Any, rotation: np.ndarray, translation: np.ndarray,
                      residuals: np.ndarray | None) -> np.ndarray:
    """The model's 68 landmarks as one packet describes them, in the sender's image.

    Args:
        rig: the person model's rig.
        camera: (fx, fy, cx, cy) pixels, or an object with those attributes (the Hello's).
        rotation: (3,) rotation vector, radians, model -> GL camera frame.
        translation: (3,) model origin in the camera frame, mm (z < 0).
        residuals: (9, 2) tangent-frame residuals, mm; None for the pose alone.

    Returns:
        (68, 2) float64 pixel positions (u right, v down), iBUG order.

    Raises:
        ValueError: a landmark is not in front of the camera, or bad shapes.
    """
    fx, fy, cx, cy = _intrinsics(camera)
    r = np.zeros((N_RESIDUALS, 3), np.float32) if residuals is None else \
        rig.from_tangent(np.asarray(residuals, np.float32))
    x = rig.landmarks(r).astype(np.float64)
    t = np.asarray(translation, np.float64).reshape(3)
    cam = x @ rotation_matrix(rotation).T + t
    depth = -cam[:, 2]
    if not (depth > 0).all():
        raise ValueError(f"translation {t.tolist()}: landmarks behind the camera (need z < 0)")
    return np.column_stack([cx + fx * cam[:, 0] / depth, cy - fy * cam[:, 1] / depth])


def geometry_nme(rig: Rig, camera: Any, decoded: np.ndarray | Sequence[Frame],
                 tracked: Sequence[np.ndarray | None]) -> GeometryNME:
    """Per-frame held-out NME of the packets' geometry against the tracker (module docstring).

    Args:
        rig: the person model's rig (``models.rig.Rig``).
        camera: the sender's intrinsics (fx, fy, cx, cy), pixels, or an object with them.
        decoded: F decoded frames: the (F,) ``FRAME_DTYPE`` array of ``decode_frames``, or a
            list of ``protocol.packet.Frame``.
        tracked: F tracker results: (68, 2) pixel points, or None where no face was found.

    Returns:
        ``GeometryNME``: (F,) held-out, rigid-only and unweighted NME as fractions; NaN
        where the packet has no ``FACE_PRESENT`` flag or has ``TRACKING_LOST`` (no pose of
        its own), or ``tracked`` is None.

    Raises:
        ValueError: lengths differ, bad shapes, or a face-present pose is behind the camera.
    """
    records = _records(decoded)
    if len(tracked) != len(records):
        raise ValueError(f"tracked: {len(tracked)} entries for {len(records)} decoded frames")
    heldout = np.full(len(records), np.nan)
    rigid = np.full(len(records), np.nan)
    unweighted = np.full(len(records), np.nan)
    for f, (rec, points) in enumerate(zip(records, tracked)):
        flags = Flag(int(rec["flags"]))
        if points is None or Flag.TRACKING_LOST in flags or Flag.FACE_PRESENT not in flags:
            continue
        truth = np.asarray(points, np.float64)
        if truth.shape != (N_LANDMARKS, 2):
            raise ValueError(f"tracked[{f}]: expected shape (68, 2), got {truth.shape}")
        full = project_landmarks(rig, camera, rec["rotation"], rec["translation"],
                                 rec["residuals"])
        pose = project_landmarks(rig, camera, rec["rotation"], rec["translation"], None)
        heldout[f] = nme(full, truth, HELD_OUT)
        rigid[f] = nme(pose, truth, HELD_OUT)
        unweighted[f] = nme(full, truth, UNWEIGHTED)
    return GeometryNME(heldout, rigid, unweighted)
