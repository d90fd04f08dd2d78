"""The generic head's designed features (mm; the left side x >= 0, the right is its mirror).

Eyes. The eyeball (centre ``EYE_CENTRE``, radius 12.2 mm, corneal bulge 0.8 mm, the iris
within 29.5 deg of the gaze axis) looks along +z. The eyelid margin, seen from the front, is
the fissure outline: the inner corner (endocanthion, iBUG 42) at x = 17 mm and the outer one
(exocanthion, 45) at x = 45.5 mm, the lids 5.2 mm above and 4.4 mm below the line between
them, shaped ``sin(pi t^a) ** 0.75`` along it with ``a = log(1/2) / log(peak)`` (peak at
t = 0.42 for the upper lid, 0.58 for the lower); ``LID_STEPS`` samples a lid, the ones at 1/3
and 2/3 being landmarks.

Mouth. The mouth line ``y = -64.5 - 0.004 x^2``; the inner lip lines at
``+- gap(x) / 2`` about it, ``gap = 2 sqrt(1 - (x / 22.5)^2)`` mm (the slit between the lips,
2 mm at the middle), ``LIP_STEPS`` samples from the midline to the corner; the vermilion
borders above and below the mouth line (``vermilion``).

Landmarks and phantoms. Brows, nose, nostrils and outer lips are designed by where they are
seen from the front, (x, y); eye (36-47) and inner-lip (60-67) points are samples of the
margin and the lip lines. The phantoms are designed points in 3D around the face (hairline,
forehead, temples, zygomatic arches, jaw angles, under the jaw and the chin, crown), left-side
and midline ones only, taken on the skin along their rays.
"""

from __future__ import annotations

import numpy as np

# Eyes. The eyeball looks along +z. The margin is the fissure outline (corners, lid heights)
# as seen from the front, on the eyelid shell of ``skin``.
EYE_CENTRE = np.array([31.5, 1.0, 73.0])
EYE_RADIUS = 12.2
CORNEA_BULGE = 0.8
IRIS_ANGLE_DEG = 29.5
_FISSURE_X = (17.0, 45.5)  # inner and outer eye corner (endocanthion, exocanthion)
_FISSURE_Y = (-0.6, 1.2)   # their heights
_LID_UP, _LID_DOWN = 5.2, 4.4  # margin height above / below the corner line
LID_STEPS = 24  # margin samples per lid (corner to corner); 1/3 and 2/3 are landmarks

# Mouth. Inner lip lines y = mouth_line(x) +- gap(x) / 2 for |x| <= corner.
MOUTH_Y = -64.5
MOUTH_CORNER_X = 22.5
_MOUTH_GAP = 2.0
LIP_STEPS = 18  # lip-line samples from the midline to the corner; step 7 is a landmark


def mouth_line(ax: np.ndarray) -> np.ndarray:
    """Height (mm) of the mouth line at |x| = ax (any shape)."""
    return MOUTH_Y - 0.004 * ax ** 2


def _mouth_gap(ax: np.ndarray) -> np.ndarray:
    return _MOUTH_GAP * np.clip(1.0 - (ax / MOUTH_CORNER_X) ** 2, 0.0, 1.0) ** 0.5


def _lid_bump(t: np.ndarray, peak: float) -> np.ndarray:
    a = np.log(0.5) / np.log(peak)
    return np.sin(np.pi * np.clip(t, 0.0, 1.0) ** a) ** 0.75


def eyelid_margin_xy() -> np.ndarray:
    """The left eyelid margin seen from the front, a closed loop (2 * LID_STEPS, 2),
    counter-clockwise: inner corner (42), lower lid (47 at 1/3, 46 at 2/3), outer corner
    (45), upper lid (44 at 2/3, 43 at 1/3)."""
    t = np.linspace(0.0, 1.0, LID_STEPS + 1)
    x = _FISSURE_X[0] + (_FISSURE_X[1] - _FISSURE_X[0]) * t
    base = _FISSURE_Y[0] + (_FISSURE_Y[1] - _FISSURE_Y[0]) * t
    upper = np.column_stack([x, base + _LID_UP * _lid_bump(t, 0.42)])
    lower = np.column_stack([x, base - _LID_DOWN * _lid_bump(t, 0.58)])
    return np.concatenate([lower[:-1], upper[::-1][:-1]])


MARGIN_LANDMARKS = {42: 0, 47: LID_STEPS // 3, 46: 2 * LID_STEPS // 3, 45: LID_STEPS,
                     44: LID_STEPS + LID_STEPS // 3, 43: LID_STEPS + 2 * LID_STEPS // 3}


def lip_lines() -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the upper inner lip line from the midline (62) to the corner (64), and of
    the lower one from the corner back to the midline (66), corner not repeated."""
    x = np.linspace(0.0, MOUTH_CORNER_X, LIP_STEPS + 1)
    ym, gap = mouth_line(x), _mouth_gap(x)
    upper = np.column_stack([x, ym + 0.5 * gap])
    lower = np.column_stack([x, ym - 0.5 * gap])[::-1][1:]
    return upper, lower


LIP_LANDMARK_STEP = 7  # 63 on the upper line, 65 on the lower


def vermilion(ax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heights (mm) of the upper and lower vermilion borders above / below the mouth line."""
    end = MOUTH_CORNER_X + 2.0
    s = np.clip((ax - 6.0) / (end - 6.0), 0.0, 1.0)
    upper = np.where(ax < 6.0, 6.0 + (ax / 6.0) ** 2, 7.0 * (1.0 - s * s) ** 0.8)
    lower = 9.5 * np.clip(1.0 - (ax / end) ** 2, 0.0, 1.0) ** 0.6
    return upper, lower


def outer_lip_xy() -> dict[int, tuple[float, float]]:
    """(x, y) seen from the front of the outer lip points 51-57 of the left side and midline:
    on the vermilion borders, the corner (54) on the mouth line 2 mm beyond the slit's end."""
    xs = {51: 0.0, 52: 6.0, 53: 14.0, 57: 0.0, 56: 8.0, 55: 16.0}
    out = {}
    for i, x in xs.items():
        up, low = vermilion(np.array(x))
        ym = float(mouth_line(np.array(x)))
        out[i] = (x, ym + float(up)) if i <= 53 else (x, ym - float(low))
    xc = MOUTH_CORNER_X + 2.0
    out[54] = (xc, float(mouth_line(np.array(xc))))
    return out


# (x, y) seen from the front: brows, nose and nostrils.
FRONT_LANDMARKS = {
    22: (7.4, 19.0), 23: (21.0, 23.6), 24: (36.8, 24.4), 25: (50.9, 19.9), 26: (61.2, 9.9),
    27: (0.0, 6.0), 28: (0.0, -5.0), 29: (0.0, -16.5), 30: (0.0, -28.0),
    33: (0.0, -43.0), 34: (6.5, -42.5), 35: (13.5, -40.5),
}

# Phantom points: designed points in 3D, taken on the skin along the ray from O.
PHANTOM_POINTS = {
    "forehead_top": (0.0, 75.0, 85.0), "forehead_left": (45.0, 62.0, 75.0),
    "temple_left": (66.0, 25.0, 30.0), "cheekbone_left": (67.0, -10.0, 15.0),
    "jaw_angle_left": (54.0, -80.0, 5.0), "jaw_left": (30.0, -114.0, 40.0),
    "under_chin": (0.0, -118.0, 55.0), "crown": (0.0, 119.0, -2.0),
}
