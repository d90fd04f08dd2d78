"""What the viewer sees: the project's tracker on a picture of the face, against the real frame.

The user's card (``../shared/DESIGN.md``), "How we judge the result"; docs/DESIGN.md §8.
For frame f with real image ``I_f`` and a picture ``J_f`` of it (the receiver's rendering
from the sender's camera, or x264's decoding of the frame), the project's tracker
(``sender.tracker.LandmarkTracker``, dlib's HOG detector and 68-point shape predictor, the
sender's own) places its 68 points on both, ``q_f = track(I_f)`` and ``p_f = track(J_f)``
(pixels, x right, y down), and

    NME_f(S) = mean_{i in S} |p_f,i - q_f,i| / |q_f,36 - q_f,45|

is the error of the picture's points over the point set S, in units of the real frame's
outer-eye distance (``models.landmarks.nme``; reported in percent). The sets (``PARTS``):
``mean`` all 68, ``mouth`` 48-67 (outer and inner lips), ``eyes`` 36-47 (both eyes' six
points), ``brows`` 17-26. A picture that shows the right expression where the real face has
it scores low; one that shows the enrollment's mouth, a blur or a blocky face scores high.
The tracker is not truth on the real frame either: the measure is agreement, on the same
tracker, between what the camera saw and what the viewer is shown.

Each image is tracked independently (``track_fresh``): the tracker is reset before every
image (``LandmarkTracker.reset``), so ``track`` runs the full-frame detector (the frame
downscaled to at most 640 px wide, as the sender's acquisition) and places the points in
the largest face's box. No box, face patch or frame counter carries from one image to the
next, so a rendering is never tracked from the box the real frame (or the previous frame)
left behind, and one frame's result does not leak into another's.

Missing faces (``FaceCounts``). A frame whose real image has no face is left out of every
mean and counted apart (``real_face_missing``): there is nothing to compare with. A frame
whose real image has a face but whose picture has none counts as ``face_missing`` for that
picture and is left out of that picture's means, so each mean is over the frames on which
the tracker found the face in both images. A picture that loses the face on its worst
frames therefore leaves those frames out of its mean: read a mean only with its
``face_missing`` beside it (``bench quality`` reports both, and its judgement ours vs x264
requires both to be no worse).

Cost: one full-frame detection (about 20 ms at 640 x 480, ``sender.tracker``) and one
prediction (about 2 ms) per image; ``bench quality`` tracks two or three images per measured
frame (real, rendering, x264) and reports the time it spent (``render_nme_seconds``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from facewire.models.landmarks import N_LANDMARKS, nme
from facewire.sender.tracker import LandmarkTracker

PARTS: dict[str, np.ndarray] = {
    "mean": np.arange(N_LANDMARKS),
    "mouth": np.arange(48, 68),
    "eyes": np.arange(36, 48),
    "brows": np.arange(17, 27),
}


def track_fresh(tracker: LandmarkTracker, image: np.ndarray) -> np.ndarray | None:
    """The tracker's 68 points on one image on its own (module docstring): a fresh detection.

    Args:
        tracker: the project's tracker; it is reset before and after.
        image: (H, W, 3) uint8 BGR (any strides) or (H, W) uint8 grey.

    Returns:
        (68, 2) float64 pixel points of the largest face, or None when no face is found.
    """
    tracker.reset()
    result = tracker.track(np.ascontiguousarray(image))
    tracker.reset()
    return None if result.points is None else result.points.astype(np.float64)


def picture_nme(real: np.ndarray, picture: np.ndarray) -> np.ndarray:
    """NME of a picture's points against the real frame's, per part (module docstring).

    Args:
        real: (68, 2) the tracker's points on the real frame, pixels.
        picture: (68, 2) its points on the picture, pixels.

    Returns:
        (len(PARTS),) float64 fractions of the real outer-eye distance, in ``PARTS`` order.
    """
    return np.array([float(nme(picture, real, idx)) for idx in PARTS.values()])


class FaceCounts(NamedTuple):
    """Per-frame NME of one kind of picture and its missing faces.

    Attributes:
        nme: (F, len(PARTS)) fractions; NaN where not measured (no rendering, no face in the
            real frame, or no face in the picture).
        missing: frames whose real frame had a face and whose picture had none.
    """

    nme: np.ndarray
    missing: int


def summary(prefix: str, counts: FaceCounts) -> dict[str, Any]:
    """``{prefix}_nme_mean`` and ``_mouth``, ``_eyes``, ``_brows`` (percent, 4 decimals; None
    when no frame was measured) and ``{prefix}_nme_frames`` (frames measured)."""
    values = counts.nme
    measured = np.isfinite(values[:, 0])
    out: dict[str, Any] = {}
    for k, part in enumerate(PARTS):
        out[f"{prefix}_nme_{part}"] = round(float(values[measured, k].mean()) * 100, 4) \
            if measured.any() else None
    out[f"{prefix}_nme_frames"] = int(measured.sum())
    return out
