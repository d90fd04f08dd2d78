"""The light that follows: the face's shading relative to the model's texture, as a field.

A model's texture holds the light of its enrollment. The sender measures how the live face's
light differs from it and sends three numbers a frame (the packet's ``shade``, quantised to
1/64 in [-1, +0.984375]); the receiver multiplies the face's colour by the gain they
describe. The gain is a log-linear field over model space (docs/DESIGN.md §2, mm):

    g(x, y) = s0 + s1 x / SCALE_MM + s2 y / SCALE_MM,       SCALE_MM = 100 mm
    colour  = texture colour * exp(clip(g, LOG_GAIN_MIN, LOG_GAIN_MAX))

s0 is the natural-log gain at the model origin (the face's centre line at eye height), s1 its
change per 100 mm toward the model's +x (the person's left), s2 per 100 mm toward +y (up).
A light from one side makes s1 nonzero, a light from above or below s2, a brighter or darker
room s0. The field is clipped to a gain of e^-1 .. e^+1 (0.37 to 2.7 times the texture) at any
point, the range s0 alone can take, so that a steep field cannot blow out the back of the head
far from the face it was fitted on.

``basis`` gives the field's design matrix [1, x / SCALE_MM, y / SCALE_MM] (the sender fits s
by least squares on it, ``sender.shading``); ``log_gain`` evaluates it; the face's fragment
shader (``receiver/web/face.frag``, the Python renderer's and the page's) writes the same
formula with these constants as ``shade_gain(vec2 p)``, and a test holds the two together.
"""

from __future__ import annotations

import numpy as np

SCALE_MM = 100.0
LOG_GAIN_MIN = -1.0
LOG_GAIN_MAX = 1.0


def basis(points: np.ndarray) -> np.ndarray:
    """The field's design matrix.

    Args:
        points: (n, 2) or (n, 3) model-space points, mm (z is not used).

    Returns:
        (n, 3) float64 rows [1, x / SCALE_MM, y / SCALE_MM]: ``basis(p) @ s`` is g at p.
    """
    p = np.asarray(points, np.float64)
    return np.column_stack([np.ones(len(p)), p[:, 0] / SCALE_MM, p[:, 1] / SCALE_MM])


def log_gain(shade: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The clipped natural-log gain at model-space points.

    Args:
        shade: (3,) (s0, s1, s2).
        points: (n, 2) or (n, 3) model-space points, mm.

    Returns:
        (n,) float64 clip(g, LOG_GAIN_MIN, LOG_GAIN_MAX); the colour there is multiplied by
        its exponential.
    """
    s = np.asarray(shade, np.float64).reshape(3)
    return np.clip(basis(points) @ s, LOG_GAIN_MIN, LOG_GAIN_MAX)
