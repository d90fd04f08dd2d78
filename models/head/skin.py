"""The generic head's skin: the zero set of a field f (negative inside, close to a distance in
mm near the surface), even in x (the functions take points with x >= 0, or fold x).

- a loft of horizontal sections ``|x / W|^n + |(z - z0) / D|^n = 1`` with W, D, z0, n
  tabulated against y (skull, face, jaw; monotone cubic interpolation, PCHIP, sampled every
  0.25 mm), D and n differing in front of and behind z0; the field is the section's radius
  minus one, times ``min(W, D)``; above the crown (y = 119) a flat cap;
- its front pushed forward (along z, fading in over z from 10 to 50 mm) by a relief height
  field ``D(|x|, y)``, a sum of smooth bumps: brow ridge, orbits, nose, cheeks, nasolabial
  folds, lips (between the mouth line and the vermilion borders), lip line, chin;
- cut under the jaw, and smoothly united (polynomial smooth minimum) with a neck, an eyelid
  shell around each eyeball (the margin ellipsoid, turned 30 deg about y so that its
  lateral end recedes, grown by a lid thickness: 0.3 mm at the margin) and an ear (a tilted
  plate with a rim, a bowl and a lobe); the neck ends in a flat cap at y = -152.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator

from facewire.models.head.anatomy import EYE_CENTRE, MOUTH_CORNER_X, mouth_line, vermilion
from facewire.models.head.primitives import bump, ellipsoid, rot_y, smax, smin, sstep

# Loft: at height y, the section is |x/W|^n + |(z - z0)/(F - z0)|^n <= 1 in front of z0
# (n = NF) and the same with B and NB behind it.
_Y_TOP = 119.0
_NECK_CUT = 152.0  # the neck ends in a flat cap at y = -_NECK_CUT
_LOFT_Y = [-125, -112, -100, -85, -70, -55, -40, -20, 0, 20, 40, 60, 80, 95, 105, 112, 116, 118,
           119]
_LOFT = {
    "W": [45, 49, 52, 57, 62, 66, 68, 69, 71, 74, 76, 74, 67, 57, 45, 32, 21, 12, 0.5],
    "F": [80, 88, 92, 91, 94, 96, 94, 88, 90, 94, 93, 89, 81, 68, 50, 32, 19, 9, -4],
    "B": [-62, -68, -76, -84, -92, -98, -102, -104, -104, -103, -99, -91, -78, -63, -47, -30,
          -21.5, -14.5, -6],
    "Z0": [-10, -10, -8, -6, -5, -5, -5, -5, -5, -5, -5, -5, -5, -5, -5, -5, -5, -5, -5],
    "NF": [2.0, 1.8, 1.85, 2.0, 2.3, 2.5, 2.5, 2.6, 2.6, 2.6, 2.5, 2.4, 2.3, 2.2, 2.1, 2.0,
           2.0, 2.0, 2.0],
    "NB": [2.2, 2.2, 2.2, 2.2, 2.3, 2.4, 2.5, 2.5, 2.5, 2.5, 2.5, 2.4, 2.3, 2.2, 2.1, 2.0,
           2.0, 2.0, 2.0],
}
_LOFT_STEP = 0.25
_LOFT_GRID = np.arange(_LOFT_Y[0], _Y_TOP + _LOFT_STEP, _LOFT_STEP)
_LOFT_TABLE = np.column_stack([PchipInterpolator(_LOFT_Y, _LOFT[k])(_LOFT_GRID)
                               for k in ("W", "F", "B", "Z0", "NF", "NB")])

# The eyelid shell: the margin ellipsoid, centred on the eyeball and turned about y so that
# its lateral end recedes.
_MARGIN_RADII = np.array([16.5, 12.8, 12.7])
_MARGIN_YAW_DEG = 30.0


def _loft(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    g = np.clip((y - _LOFT_Y[0]) / _LOFT_STEP, 0.0, len(_LOFT_GRID) - 1.000001)
    i = g.astype(np.int64)
    frac = (g - i)[:, None]
    w, f, b, z0, nf, nb = ((1.0 - frac) * _LOFT_TABLE[i] + frac * _LOFT_TABLE[i + 1]).T
    front = z >= z0
    depth = np.where(front, f - z0, z0 - b)
    n = np.where(front, nf, nb)
    r = ((np.abs(x) / w) ** n + (np.abs(z - z0) / depth) ** n) ** (1.0 / n)
    s = (r - 1.0) * np.minimum(w, depth)
    return np.where(y > _Y_TOP, np.maximum(s, y - _Y_TOP), s)


def _relief(ax: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Forward displacement (mm) of the face over the loft, at (|x|, y)."""
    d = np.zeros_like(ax)
    # Forehead, brow ridge, temples.
    d += 2.0 * bump(np.hypot((ax - 27.0) / 26.0, (y - 52.0) / 22.0))
    yb = 19.0 + 2.0 * np.exp(-(((ax - 30.0) / 16.0) ** 2)) - 0.002 * ax ** 2
    d += 4.0 * bump((y - yb) / 12.0) * bump(ax / 62.0)
    d -= 3.0 * bump(np.hypot((ax - 63.0) / 12.0, (y - 18.0) / 20.0))
    # Orbits, upper sulcus under the brow, groove between lower lid and cheek.
    d -= 10.0 * bump(np.hypot((ax - 31.0) / 22.0, (y + 1.0) / 17.0))
    d -= 1.5 * bump(np.hypot((ax - 30.0) / 14.0, (y - 10.5) / 5.0))
    d -= 1.2 * bump(np.hypot((ax - 33.0) / 13.0, (y + 9.5) / 3.0))
    # Nose: a ridge from the root (y = 8) to the tip (y = -28), the rounded tip, the wings.
    t = np.clip((8.0 - y) / 36.0, 0.0, 1.0)
    height = 2.5 + 16.0 * t ** 1.3
    width = 6.5 + 5.0 * t ** 1.5
    ridge = height * bump(ax / width) ** 0.55
    d += ridge * sstep(-43.0, -32.0, y) * sstep(14.0, 6.0, y)
    d += 4.5 * bump(np.hypot(ax / 9.5, (y + 27.0) / 8.5))
    d += 6.0 * bump(np.hypot((ax - 11.5) / 7.0, (y + 36.5) / 6.0))
    d -= 0.7 * bump((np.hypot((ax - 12.0) / 9.0, (y + 36.5) / 8.0) - 1.0) / 0.35)
    d -= 1.5 * bump(np.hypot((ax - 5.5) / 4.0, (y + 41.0) / 3.0))
    # Cheekbones, cheeks, nasolabial folds.
    d += 5.0 * bump(np.hypot((ax - 48.0) / 22.0, (y + 15.0) / 16.0))
    d += 2.5 * bump(np.hypot((ax - 34.0) / 16.0, (y + 32.0) / 14.0))
    fold = (ax - 16.0) * 0.83 + (y + 38.0) * 0.55  # distance across the fold line
    along = -(ax - 16.0) * 0.55 + (y + 38.0) * 0.83
    d -= 0.9 * bump(fold / 3.5) * bump((along + 14.0) / 15.0)
    # Mouth: a muzzle, the lips between the mouth line and their vermilion borders, the lip
    # line itself, the fold under the lower lip, the chin.
    d += 4.0 * bump(np.hypot(ax / 30.0, (y + 64.0) / 26.0))
    ym = mouth_line(ax)
    up, low = vermilion(ax)
    su = (y - ym) / np.maximum(up, 1.0)
    sl = (ym - y) / np.maximum(low, 1.0)
    fade = bump(ax / (MOUTH_CORNER_X + 3.0)) ** 0.5
    d += 2.6 * bump((su - 0.5) / 0.75) * fade
    d += 3.3 * bump((sl - 0.5) / 0.8) * fade
    d -= 2.5 * bump((y - ym) / 2.0) * bump(ax / (MOUTH_CORNER_X + 3.0))
    d -= 2.0 * bump((y + 84.0) / 6.0) * bump(ax / 22.0)
    d += 5.5 * bump(np.hypot(ax / 18.0, (y + 99.0) / 12.0))
    return d


def face_field(q: np.ndarray) -> np.ndarray:
    """The face and skull: relief-displaced loft cut under the jaw, with the eyelid shells."""
    ax, y, z = q[:, 0], q[:, 1], q[:, 2]
    shift = np.zeros_like(z)
    face = (z > 10.0) & (ax < 75.0) & (y > -125.0) & (y < 80.0)
    shift[face] = _relief(ax[face], y[face]) * sstep(10.0, 50.0, z[face])
    s = _loft(ax, y, z - shift)
    jaw = -114.0 + 34.0 * sstep(70.0, -5.0, z) + 0.004 * ax ** 2
    s = smax(s, jaw - y, 7.0)
    return smin(s, _lid_field(q), 4.0)


def _lid_field(q: np.ndarray) -> np.ndarray:
    """Eyelid shell: the margin ellipsoid grown by a lid thickness (0.3 mm at the margin)."""
    out = np.full(len(q), 30.0)
    near = np.abs(q - EYE_CENTRE).max(axis=1) < 30.0
    qn = q[near]
    local = (qn - EYE_CENTRE) @ rot_y(_MARGIN_YAW_DEG)
    e = np.hypot((qn[:, 0] - 31.25) / 14.5, (qn[:, 1] - 0.3) / 5.0)
    out[near] = ellipsoid(local, (0.0, 0.0, 0.0), _MARGIN_RADII) - 0.3 - 1.4 * sstep(0.95, 2.0, e)
    return out


# The ear: a plate standing out from the side of the head (its back edge 16 mm out), with a
# thick rim, a bowl (concha) and a lobe. Local frame at the attachment point: u runs back
# along the plate, v up along it, w out of it (lateral and a little forward).
_EAR_BASE = np.array([69.0, -7.0, -12.0])
_EAR_FRAME = np.column_stack([  # columns u, v, w
    rot_y(-25.0) @ np.array([0.0, 0.0, -1.0]) * np.cos(np.radians(12.0))
    - np.array([0.0, 1.0, 0.0]) * np.sin(np.radians(12.0)),
    np.array([0.0, 1.0, 0.0]) * np.cos(np.radians(12.0))
    + rot_y(-25.0) @ np.array([0.0, 0.0, -1.0]) * np.sin(np.radians(12.0)),
    rot_y(-25.0) @ np.array([1.0, 0.0, 0.0])])


def ear_field(q: np.ndarray) -> np.ndarray:
    """The left ear at points q (N, 3) with x >= 0 (40 far from it)."""
    out = np.full(len(q), 40.0)
    near = (q[:, 0] > 45.0) & (np.abs(q[:, 1] + 8.0) < 50.0) & (np.abs(q[:, 2] + 20.0) < 40.0)
    u, v, w = ((q[near] - _EAR_BASE) @ _EAR_FRAME).T
    r = np.hypot((u - 13.0) / 16.0, (v - 3.0) / 29.0)
    thickness = 2.2 + 2.3 * sstep(0.55, 0.9, r)
    plate = smax(np.abs(w - 5.0) - thickness, (r - 1.0) * 14.0, 2.0)
    lobe = ellipsoid(np.column_stack([u, v, w]), (9.0, -23.0, 4.0), (7.0, 8.0, 3.5))
    ear = smin(plate, lobe, 3.0)
    bowl = ellipsoid(np.column_stack([u, v, w]), (8.0, -4.0, 9.5), (8.0, 11.0, 5.5))
    out[near] = smax(ear, -bowl, 1.5)
    return out


def skin_field(p: np.ndarray) -> np.ndarray:
    """The skin field f at points (N, 3) (negative inside)."""
    q = np.column_stack([np.abs(p[:, 0]), p[:, 1], p[:, 2]])
    ax, y, z = q[:, 0], q[:, 1], q[:, 2]
    s = face_field(q)
    neck = (np.hypot(ax / 51.0, (z + 0.15 * (y + 100.0) + 12.0) / 50.0) - 1.0) * 50.0
    s = smin(s, smax(neck, y + 50.0, 10.0), 18.0)
    s = smin(s, ear_field(q), 4.0)
    return smax(s, -(y + _NECK_CUT), 20.0)
