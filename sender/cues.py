"""Each region's landmark cue on one frame: a number that grows along the region's axis.

The cues come from the tracked points, the sent residuals and the regions' samples; the
classifier never sees them (at run time only the templates decide Q), but they order a
region's appearance states: enrollment spaces its states along them
(``sender.enroll.layers``), and the sender's learning places a learned state among the
existing ones by them (``sender.learn``).

=============  ============================================================================
region         cue, growing along the region's axis
=============  ============================================================================
forehead       brow raise: mean y residual of the brow points 19, 21, 22, 24 (mm)
brow_furrow    brows drawn together: x residual of 21 minus that of 22 (mm)
eyelid_*       eye closure: minus the eye aspect ratio of that eye
eyeball_*      gaze: where the iris lies across the eyeball's sample, 0 .. 1 along the
               model's +x: the centroid of the darkness (below the median) of the columns of
               its middle 8 rows
mouth          opening: inner-lip gap |p66 - p62| over the outer-eye distance
=============  ============================================================================
"""

from __future__ import annotations

import numpy as np

from facewire.models.landmarks import eye_aspect_ratio, outer_eye_distance
from facewire.models.regions import REGION_NAMES, REGIONS

EYEBALL_LEFT = REGION_NAMES.index("eyeball_left")
EYEBALL_RIGHT = REGION_NAMES.index("eyeball_right")


def region_cues(samples: np.ndarray, points: np.ndarray, residuals: np.ndarray) -> np.ndarray:
    """The cue of every region of ``REGIONS`` on one frame (module docstring).

    Args:
        samples: (R, 16, 16) the regions' centre samples, ``REGIONS`` order.
        points: (68, 2) the tracked points, px.
        residuals: (9, 3) the sent residuals, mm.

    Returns:
        (R,) float64 cues, ``REGIONS`` order (NaN: not defined on this frame).
    """
    ear_right, ear_left = eye_aspect_ratio(points)
    mouth = float(np.linalg.norm(points[66] - points[62]) / max(
        float(outer_eye_distance(points)), 1e-6))
    values = {
        "forehead": float(residuals[:4, 1].mean()),
        "brow_furrow": float(residuals[1, 0] - residuals[2, 0]),
        "eyelid_left": -float(ear_left), "eyelid_right": -float(ear_right),
        "eyeball_left": _iris_position(samples[EYEBALL_LEFT]),
        "eyeball_right": _iris_position(samples[EYEBALL_RIGHT]),
        "mouth": mouth,
    }
    return np.array([values[r.name] for r in REGIONS])


def _iris_position(sample: np.ndarray) -> float:
    """Where the iris lies across an eyeball sample (16 x 16, columns along model +x),
    0 .. 1: the centroid of the middle rows' column darkness below their median."""
    middle = sample[4:12].mean(axis=0)
    darkness = np.maximum(np.median(middle) - middle, 0.0)
    if darkness.sum() <= 1e-6:
        return float("nan")
    columns = (np.arange(len(middle)) + 0.5) / len(middle)
    return float((darkness * columns).sum() / darkness.sum())
