"""The generic head: a procedural, closed, mirror-symmetric triangle mesh of an adult head.

Everything is built from the formulas in this file; no scanned or third-party mesh is used.

Frame (as ``models/mesh.py``): mm, x toward the person's left, y up, z out of the face. The
origin is on the midsagittal plane (x = 0) at the height of the eye corners (y = 0), about
halfway between the forehead and the back of the head (z = 0). Average adult dimensions: outer
eye corners 91 mm apart, inner 34 mm, pupils 63 mm; head breadth 152 mm, chin to vertex
232 mm, nose tip to the back of the head 217 mm; mouth 49 mm wide; nose tip 26 mm in front of
the inner eye corners (35 mm in front of the outer ones). About 11 200 vertices and 22 100
triangles.

Shape
-----
The skin is the zero set of a field ``f`` (negative inside, close to a distance in mm near the
surface), even in x:

- a loft of horizontal sections ``|x / W|^n + |(z - z0) / D|^n = 1`` with W, D, z0, n
  tabulated against y (skull, face, jaw), D and n differing in front of and behind z0;
- its front pushed forward (along z) by a relief height field ``D(|x|, y)``: brow ridge,
  orbits, nose, cheeks, nasolabial folds, lips (between the mouth line and the vermilion
  borders), lip line, chin;
- cut under the jaw, and smoothly united (polynomial smooth minimum) with a neck, an eyelid
  shell around each eyeball (an ellipsoid grown by a lid thickness, 0.3 mm at the margin) and
  an ear (a tilted plate with a rim, a bowl and a lobe).

Parameterisation and sampling
-----------------------------
Each unit direction ``d`` meets the skin once on the ray ``o(d) + t d``, t > 0, with ``o(d)``
on the vertical axis x = 0, z = -5: at y = -40 for directions above -40 deg of elevation and
lower (down to y = -120) for steeper ones, so that rays meet the neck at a good angle; the
height of ``o`` never decreases with the elevation, so rays never cross. The skin point
``p(d)`` is the outermost root of ``f`` on the ray (marched inward, then bisected). The half
sphere x >= 0 of directions is sampled

- exactly along the eyelid margins and the inner lip lines (the openings), along two rows
  parallel to each, on the midline, at the landmarks and at the phantoms;
- elsewhere by Poisson-disk thinning of random candidates, aiming at an edge length of 1.6 mm
  at the eyelids, 1.7 mm at the lips, 2.6 mm on the nose, 4.4 mm on the rest of the face,
  3.6 mm on the ears and 10 mm elsewhere, turned into angles with the local metric
  ``|dp / dd|``; then three Lloyd (centroidal Voronoi) relaxation steps.

The spherical Delaunay triangulation of the samples is the convex hull of the unit directions.
No free sample lies in the circle on any margin or lip-line segment (Gabriel condition; an
edge still missing at a sharp corner is recovered by one flip), so these segments are mesh
edges and the openings are cut out exactly by dropping the triangles inside them. The half is
mirrored (x -> -x, windings reversed) and welded along the midline.

Closing
-------
The slit between the lips (2 mm at the middle) leads into a mouth cavity: the lip line again
(its own copy: a texture seam), six rings shrinking 45 mm back into the head, and a fan. Each
eye opening leads into a socket cup: a narrow roll that rounds the lid edge, then rings on a
sphere 0.35 mm outside the eyeball that turn back to a cap behind it. Skin, sockets and cavity
are one closed genus-0 surface once the texture-seam copies are welded by position. Each
eyeball is a separate closed sphere (radius 12.2 mm, corneal bulge 0.8 mm) looking along +z.

Texture layout (u to the right, v up; 1024 x 512 in the paper)
---------------------------------------------------------------
- Skin, ``u in [0, 0.8]``: a warped cylindrical map of the ray direction,
  ``u = 0.4 +- 0.4 F(az)``, ``v = G(el)``, ``az = atan2(|d_x|, d_z)``, ``el = asin(d_y)``,
  ``+`` for x >= 0 (the image right of a frontal face). F and G are normalised integrals of a
  density that is 1 over the face (az < 70 deg, el from -45 to 52 deg) and 0.12 (u) or 0.15 (v)
  elsewhere: the face, between the ears and from hairline to chin, takes about half of the
  texture (62 % of the skin's share). The only seam runs down the back of the head (u = 0
  and u = 0.8 are the same points); the map's pole turns over a few scalp triangles at the
  very top. Socket cups map into the eye openings of this map, which no skin triangle covers.
- Eyeballs: discs of radius ``EYE_UV_RADIUS`` in u (twice that in v: round in texels) centred
  at ``EYE_UV[side]``; the angle theta from the gaze axis goes to the radius
  ``(theta / 90 deg) ** 0.75`` of the disc. The cornea apex is the centre, the iris
  (theta < 29.5 deg) the inner 44 %. The back halves, never seen, have small discs of their
  own at ``EYE_BACK_UV`` (a seam at the 90-degree ring), so no texel holds two surface points.
- Mouth cavity: a disc at ``MOUTH_UV`` with the inner lip line on its rim (the person's left
  half on the right, the midline at top and bottom) and the back of the cavity at its centre.

Tags: SKIN (face, neck, sockets), SCALP (above a hairline that comes down in front of the ears
and behind them to the nape), EAR, MOUTH_INTERIOR, RIGHT_EYEBALL, LEFT_EYEBALL.

Landmarks and phantoms
----------------------
``Mesh.landmarks[i]`` is the vertex of iBUG point i (0-based). Eye (36-47) and inner-lip
(60-67) points are vertices of the eyelid margins and lip lines; brows, nose, nostrils and outer
lips are the skin points seen straight from the front at designed (x, y); the jaw line (0-16)
lies on the frontal silhouette of the face without neck and ears (in front of z = 10), evenly
spaced from the chin (8) up to eye height. ``Mesh.phantoms`` follow
``models.landmarks.PHANTOM_NAMES``: skin points on the rays toward designed points around the
face (hairline, forehead, temples, zygomatic arches, jaw angles, under the jaw and the chin,
crown).

``mirror_map()`` gives, for each vertex, the vertex at its mirror image: an involution with
exactly mirrored positions; midline vertices map to themselves and the two copies of a seam
vertex on the back of the head to each other.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.spatial import ConvexHull, cKDTree

from facewire.models.landmarks import MIRROR, N_LANDMARKS, PHANTOM_NAMES
from facewire.models.mesh import Mesh, Tag

# ----------------------------------------------------------------------------------------
# Small field tools (all work on float64 arrays; `q` holds points (N, 3) with x >= 0).


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum of two fields with blend width k (mm)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    return -_smin(-a, -b, k)


def _sstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """Smoothstep from 0 at e0 to 1 at e1 (e1 < e0 gives a falling step)."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _bump(u: np.ndarray) -> np.ndarray:
    """(1 - u^2)^3 for |u| < 1, else 0: a smooth bump of height 1 and half-width 1."""
    t = np.clip(1.0 - u * u, 0.0, 1.0)
    return t * t * t


def _ellipsoid(q: np.ndarray, centre, radii) -> np.ndarray:
    """Approximate signed distance to an axis-aligned ellipsoid (exact on its surface)."""
    r = np.asarray(radii, dtype=np.float64)
    d = (q - np.asarray(centre, dtype=np.float64)) / r
    k0 = np.linalg.norm(d, axis=-1)
    k1 = np.linalg.norm(d / r, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def _rot_y(angle_deg: float) -> np.ndarray:
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


# ----------------------------------------------------------------------------------------
# Design (mm). Left side (x > 0); the right side is its mirror image.

# Rays start on the vertical axis x = 0, z = -5: at y = -40 for directions above 40 degrees
# below the horizon, lower (down to y = -120) for steeper ones, so that they meet the neck
# at a good angle. The origin height never decreases with the elevation, so no two rays
# cross and each skin point belongs to exactly one direction.
_RAY_AXIS_Z = -5.0
_RAY_Y = (-40.0, -120.0)
_RAY_EL = (np.radians(-40.0), np.radians(-90.0))
# An ellipsoid around the whole skin: rays are marched inward from it.
_BOUND_CENTRE = np.array([0.0, -23.0, -5.0])
_BOUND_RADII = np.array([100.0, 150.0, 135.0])

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

# Eyes. The eyeball looks along +z. The lids are a shell on the margin ellipsoid (centred on
# the eyeball, turned about y so that its lateral end recedes); the margin is the fissure
# outline (corners, lid heights) on that shell, as seen from the front.
EYE_CENTRE = np.array([31.5, 1.0, 73.0])
EYE_RADIUS = 12.2
CORNEA_BULGE = 0.8
IRIS_ANGLE_DEG = 29.5
_MARGIN_RADII = np.array([16.5, 12.8, 12.7])
_MARGIN_YAW_DEG = 30.0
_FISSURE_X = (17.0, 45.5)  # inner and outer eye corner (endocanthion, exocanthion)
_FISSURE_Y = (-0.6, 1.2)   # their heights
_LID_UP, _LID_DOWN = 5.2, 4.4  # margin height above / below the corner line
_LID_STEPS = 24  # margin samples per lid (corner to corner); 1/3 and 2/3 are landmarks
_SOCKET_GAP = 0.35  # socket cup radius minus eyeball radius

# Mouth. Inner lip lines y = mouth_line(x) +- gap(x) / 2 for |x| <= corner.
_MOUTH_Y = -64.5
_MOUTH_CORNER_X = 22.5
_MOUTH_GAP = 2.0
_LIP_STEPS = 18  # lip-line samples from the midline to the corner; step 7 is a landmark


def _mouth_line(ax: np.ndarray) -> np.ndarray:
    return _MOUTH_Y - 0.004 * ax ** 2


def _mouth_gap(ax: np.ndarray) -> np.ndarray:
    return _MOUTH_GAP * np.clip(1.0 - (ax / _MOUTH_CORNER_X) ** 2, 0.0, 1.0) ** 0.5


# ----------------------------------------------------------------------------------------
# The skin field.


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
    d += 2.0 * _bump(np.hypot((ax - 27.0) / 26.0, (y - 52.0) / 22.0))
    yb = 19.0 + 2.0 * np.exp(-(((ax - 30.0) / 16.0) ** 2)) - 0.002 * ax ** 2
    d += 4.0 * _bump((y - yb) / 12.0) * _bump(ax / 62.0)
    d -= 3.0 * _bump(np.hypot((ax - 63.0) / 12.0, (y - 18.0) / 20.0))
    # Orbits, upper sulcus under the brow, groove between lower lid and cheek.
    d -= 10.0 * _bump(np.hypot((ax - 31.0) / 22.0, (y + 1.0) / 17.0))
    d -= 1.5 * _bump(np.hypot((ax - 30.0) / 14.0, (y - 10.5) / 5.0))
    d -= 1.2 * _bump(np.hypot((ax - 33.0) / 13.0, (y + 9.5) / 3.0))
    # Nose: a ridge from the root (y = 8) to the tip (y = -28), the rounded tip, the wings.
    t = np.clip((8.0 - y) / 36.0, 0.0, 1.0)
    height = 2.5 + 16.0 * t ** 1.3
    width = 6.5 + 5.0 * t ** 1.5
    ridge = height * _bump(ax / width) ** 0.55
    d += ridge * _sstep(-43.0, -32.0, y) * _sstep(14.0, 6.0, y)
    d += 4.5 * _bump(np.hypot(ax / 9.5, (y + 27.0) / 8.5))
    d += 6.0 * _bump(np.hypot((ax - 11.5) / 7.0, (y + 36.5) / 6.0))
    d -= 0.7 * _bump((np.hypot((ax - 12.0) / 9.0, (y + 36.5) / 8.0) - 1.0) / 0.35)
    d -= 1.5 * _bump(np.hypot((ax - 5.5) / 4.0, (y + 41.0) / 3.0))
    # Cheekbones, cheeks, nasolabial folds.
    d += 5.0 * _bump(np.hypot((ax - 48.0) / 22.0, (y + 15.0) / 16.0))
    d += 2.5 * _bump(np.hypot((ax - 34.0) / 16.0, (y + 32.0) / 14.0))
    fold = (ax - 16.0) * 0.83 + (y + 38.0) * 0.55  # distance across the fold line
    along = -(ax - 16.0) * 0.55 + (y + 38.0) * 0.83
    d -= 0.9 * _bump(fold / 3.5) * _bump((along + 14.0) / 15.0)
    # Mouth: a muzzle, the lips between the mouth line and their vermilion borders, the lip
    # line itself, the fold under the lower lip, the chin.
    d += 4.0 * _bump(np.hypot(ax / 30.0, (y + 64.0) / 26.0))
    ym = _mouth_line(ax)
    up, low = _vermilion(ax)
    su = (y - ym) / np.maximum(up, 1.0)
    sl = (ym - y) / np.maximum(low, 1.0)
    fade = _bump(ax / (_MOUTH_CORNER_X + 3.0)) ** 0.5
    d += 2.6 * _bump((su - 0.5) / 0.75) * fade
    d += 3.3 * _bump((sl - 0.5) / 0.8) * fade
    d -= 2.5 * _bump((y - ym) / 2.0) * _bump(ax / (_MOUTH_CORNER_X + 3.0))
    d -= 2.0 * _bump((y + 84.0) / 6.0) * _bump(ax / 22.0)
    d += 5.5 * _bump(np.hypot(ax / 18.0, (y + 99.0) / 12.0))
    return d


def _face_field(q: np.ndarray) -> np.ndarray:
    """The face and skull: relief-displaced loft cut under the jaw, with the eyelid shells."""
    ax, y, z = q[:, 0], q[:, 1], q[:, 2]
    shift = np.zeros_like(z)
    face = (z > 10.0) & (ax < 75.0) & (y > -125.0) & (y < 80.0)
    shift[face] = _relief(ax[face], y[face]) * _sstep(10.0, 50.0, z[face])
    s = _loft(ax, y, z - shift)
    jaw = -114.0 + 34.0 * _sstep(70.0, -5.0, z) + 0.004 * ax ** 2
    s = _smax(s, jaw - y, 7.0)
    return _smin(s, _lid_field(q), 4.0)


def _lid_field(q: np.ndarray) -> np.ndarray:
    """Eyelid shell: the margin ellipsoid grown by a lid thickness (0.3 mm at the margin)."""
    out = np.full(len(q), 30.0)
    near = np.abs(q - EYE_CENTRE).max(axis=1) < 30.0
    qn = q[near]
    local = (qn - EYE_CENTRE) @ _rot_y(_MARGIN_YAW_DEG)
    e = np.hypot((qn[:, 0] - 31.25) / 14.5, (qn[:, 1] - 0.3) / 5.0)
    out[near] = _ellipsoid(local, (0.0, 0.0, 0.0), _MARGIN_RADII) - 0.3 - 1.4 * _sstep(0.95, 2.0, e)
    return out


# The ear: a plate standing out from the side of the head (its back edge 16 mm out), with a
# thick rim, a bowl (concha) and a lobe. Local frame at the attachment point: u runs back
# along the plate, v up along it, w out of it (lateral and a little forward).
_EAR_BASE = np.array([69.0, -7.0, -12.0])
_EAR_FRAME = np.column_stack([  # columns u, v, w
    _rot_y(-25.0) @ np.array([0.0, 0.0, -1.0]) * np.cos(np.radians(12.0))
    - np.array([0.0, 1.0, 0.0]) * np.sin(np.radians(12.0)),
    np.array([0.0, 1.0, 0.0]) * np.cos(np.radians(12.0))
    + _rot_y(-25.0) @ np.array([0.0, 0.0, -1.0]) * np.sin(np.radians(12.0)),
    _rot_y(-25.0) @ np.array([1.0, 0.0, 0.0])])


def _ear_field(q: np.ndarray) -> np.ndarray:
    """The left ear at points q (N, 3) with x >= 0 (40 far from it)."""
    out = np.full(len(q), 40.0)
    near = (q[:, 0] > 45.0) & (np.abs(q[:, 1] + 8.0) < 50.0) & (np.abs(q[:, 2] + 20.0) < 40.0)
    u, v, w = ((q[near] - _EAR_BASE) @ _EAR_FRAME).T
    r = np.hypot((u - 13.0) / 16.0, (v - 3.0) / 29.0)
    thickness = 2.2 + 2.3 * _sstep(0.55, 0.9, r)
    plate = _smax(np.abs(w - 5.0) - thickness, (r - 1.0) * 14.0, 2.0)
    lobe = _ellipsoid(np.column_stack([u, v, w]), (9.0, -23.0, 4.0), (7.0, 8.0, 3.5))
    ear = _smin(plate, lobe, 3.0)
    bowl = _ellipsoid(np.column_stack([u, v, w]), (8.0, -4.0, 9.5), (8.0, 11.0, 5.5))
    out[near] = _smax(ear, -bowl, 1.5)
    return out


def _skin_field(p: np.ndarray) -> np.ndarray:
    """The skin field f at points (N, 3) (negative inside)."""
    q = np.column_stack([np.abs(p[:, 0]), p[:, 1], p[:, 2]])
    ax, y, z = q[:, 0], q[:, 1], q[:, 2]
    s = _face_field(q)
    neck = (np.hypot(ax / 51.0, (z + 0.15 * (y + 100.0) + 12.0) / 50.0) - 1.0) * 50.0
    s = _smin(s, _smax(neck, y + 50.0, 10.0), 18.0)
    s = _smin(s, _ear_field(q), 4.0)
    return _smax(s, -(y + _NECK_CUT), 20.0)


# ----------------------------------------------------------------------------------------
# Rays.


def _raycast(dirs: np.ndarray, origins: np.ndarray | None = None,
             start: np.ndarray | None = None, field=_skin_field, step: float = 1.5) -> np.ndarray:
    """The outermost root of ``field`` on each ray o + t d, t > 0 (d unit, (N, 3); o the ray
    origins (N, 3), by default those of the skin parameterisation): marched inward from
    ``start`` (N,) where the field is positive there, else from the bounding ellipsoid, then
    bisected. Returns the points (N, 3)."""
    o = _origins(dirs) if origins is None else np.broadcast_to(origins, dirs.shape)
    oo = (o - _BOUND_CENTRE) / _BOUND_RADII
    dd = dirs / _BOUND_RADII
    a = (dd * dd).sum(1)
    b = 2.0 * (dd * oo).sum(1)
    c = (oo * oo).sum(1) - 1.0
    t = (-b + np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    if start is not None:
        t_start = np.minimum(start, t)
        outside = field(o + dirs * t_start[:, None]) > 0.0
        t = np.where(outside, t_start, t)
    todo = np.arange(len(dirs))
    while todo.size:
        inside = field(o[todo] + dirs[todo] * t[todo, None]) < 0.0
        todo = todo[~inside]
        t[todo] -= step
        if np.any(t[todo] < 1.0):
            raise RuntimeError("head: a ray misses the skin")
    lo, hi = t, t + step
    for _ in range(15):
        mid = 0.5 * (lo + hi)
        inside = field(o + dirs * mid[:, None]) < 0.0
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return o + dirs * (0.5 * (lo + hi))[:, None]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _origin_height(el: np.ndarray) -> np.ndarray:
    return _RAY_Y[0] + (_RAY_Y[1] - _RAY_Y[0]) * _sstep(_RAY_EL[0], _RAY_EL[1], el)


def _origins(dirs: np.ndarray) -> np.ndarray:
    """The ray origins (N, 3) of unit directions (N, 3)."""
    el = np.arcsin(np.clip(dirs[:, 1], -1.0, 1.0))
    n = len(dirs)
    return np.column_stack([np.zeros(n), _origin_height(el), np.full(n, _RAY_AXIS_Z)])


def _directions_to(points: np.ndarray) -> np.ndarray:
    """The ray directions (N, 3) whose rays pass through the points (N, 3): the azimuth is
    that of the point about the axis; the elevation solves tan(el) = (y - y_o(el)) / r by
    bisection (the left side rises with el, the right side does not)."""
    rel = points - np.array([0.0, 0.0, _RAY_AXIS_Z])
    r = np.hypot(rel[:, 0], rel[:, 2])
    lo, hi = np.full(len(points), -np.pi / 2), np.full(len(points), np.pi / 2)
    for _ in range(40):
        el = 0.5 * (lo + hi)
        above = np.arctan2(points[:, 1] - _origin_height(el), r) > el
        lo, hi = np.where(above, el, lo), np.where(above, hi, el)
    el = 0.5 * (lo + hi)
    h = np.cos(el)[:, None] * _unit(np.column_stack([rel[:, 0], np.zeros(len(points)), rel[:, 2]]))
    d = np.column_stack([h[:, 0], np.sin(el), h[:, 2]])
    d[points[:, 0] == 0.0, 0] = 0.0
    return d


def _front_directions(xy: np.ndarray) -> np.ndarray:
    """Ray directions of the skin points seen straight from the front at (x, y) (N, 2)."""
    origins = np.column_stack([xy, np.full(len(xy), -150.0)])
    dirs = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    return _directions_to(_raycast(dirs, origins, np.full(len(xy), 275.0)))


def _seen_from_front(xy: np.ndarray, field, z_min: float) -> np.ndarray:
    """Whether a line along z through each (x, y) meets field < 0 at some z >= z_min
    (sampled every 1.5 mm): the frontal silhouette test."""
    z = np.arange(z_min, 130.0, 1.5)
    p = np.column_stack([np.repeat(xy, len(z), axis=0), np.tile(z, len(xy))])
    return (field(p) < 0.0).reshape(len(xy), len(z)).any(axis=1)


# ----------------------------------------------------------------------------------------
# Feature curves and landmarks (left side and midline).


def _lid_bump(t: np.ndarray, peak: float) -> np.ndarray:
    a = np.log(0.5) / np.log(peak)
    return np.sin(np.pi * np.clip(t, 0.0, 1.0) ** a) ** 0.75


def _margin_xy() -> np.ndarray:
    """The left eyelid margin seen from the front, a closed loop (2 * _LID_STEPS, 2),
    counter-clockwise: inner corner (42), lower lid (47 at 1/3, 46 at 2/3), outer corner
    (45), upper lid (44 at 2/3, 43 at 1/3)."""
    t = np.linspace(0.0, 1.0, _LID_STEPS + 1)
    x = _FISSURE_X[0] + (_FISSURE_X[1] - _FISSURE_X[0]) * t
    base = _FISSURE_Y[0] + (_FISSURE_Y[1] - _FISSURE_Y[0]) * t
    upper = np.column_stack([x, base + _LID_UP * _lid_bump(t, 0.42)])
    lower = np.column_stack([x, base - _LID_DOWN * _lid_bump(t, 0.58)])
    return np.concatenate([lower[:-1], upper[::-1][:-1]])


def _offset_rows(xy: np.ndarray, closed: bool, left_normal: bool,
                 distances: tuple[float, ...]) -> np.ndarray:
    """Copies of a 2D polyline (N, 2) moved by each distance along its normal (the left-hand
    one if ``left_normal``); rows of regular samples along the eye and lip openings."""
    nxt = np.roll(xy, -1, axis=0) if closed else np.concatenate([xy[1:], xy[-1:]])
    prv = np.roll(xy, 1, axis=0) if closed else np.concatenate([xy[:1], xy[:-1]])
    t = _unit(nxt - prv)
    n = np.column_stack([-t[:, 1], t[:, 0]]) * (1.0 if left_normal else -1.0)
    return np.concatenate([xy + d * n for d in distances])


_MARGIN_LANDMARKS = {42: 0, 47: _LID_STEPS // 3, 46: 2 * _LID_STEPS // 3, 45: _LID_STEPS,
                     44: _LID_STEPS + _LID_STEPS // 3, 43: _LID_STEPS + 2 * _LID_STEPS // 3}


def _lip_lines() -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the upper inner lip line from the midline (62) to the corner (64), and of
    the lower one from the corner back to the midline (66), corner not repeated."""
    x = np.linspace(0.0, _MOUTH_CORNER_X, _LIP_STEPS + 1)
    ym, gap = _mouth_line(x), _mouth_gap(x)
    upper = np.column_stack([x, ym + 0.5 * gap])
    lower = np.column_stack([x, ym - 0.5 * gap])[::-1][1:]
    return upper, lower


_LIP_LANDMARK_STEP = 7  # 63 on the upper line, 65 on the lower


def _vermilion(ax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heights (mm) of the upper and lower vermilion borders above / below the mouth line."""
    end = _MOUTH_CORNER_X + 2.0
    s = np.clip((ax - 6.0) / (end - 6.0), 0.0, 1.0)
    upper = np.where(ax < 6.0, 6.0 + (ax / 6.0) ** 2, 7.0 * (1.0 - s * s) ** 0.8)
    lower = 9.5 * np.clip(1.0 - (ax / end) ** 2, 0.0, 1.0) ** 0.6
    return upper, lower


def _outer_lip_xy() -> dict[int, tuple[float, float]]:
    xs = {51: 0.0, 52: 6.0, 53: 14.0, 57: 0.0, 56: 8.0, 55: 16.0}
    out = {}
    for i, x in xs.items():
        up, low = _vermilion(np.array(x))
        ym = float(_mouth_line(np.array(x)))
        out[i] = (x, ym + float(up)) if i <= 53 else (x, ym - float(low))
    xc = _MOUTH_CORNER_X + 2.0
    out[54] = (xc, float(_mouth_line(np.array(xc))))
    return out


# (x, y) seen from the front: brows, nose and nostrils.
_FRONT_LANDMARKS = {
    22: (7.4, 19.0), 23: (21.0, 23.6), 24: (36.8, 24.4), 25: (50.9, 19.9), 26: (61.2, 9.9),
    27: (0.0, 6.0), 28: (0.0, -5.0), 29: (0.0, -16.5), 30: (0.0, -28.0),
    33: (0.0, -43.0), 34: (6.5, -42.5), 35: (13.5, -40.5),
}

# Phantom points: designed points in 3D, taken on the skin along the ray from O.
_PHANTOM_POINTS = {
    "forehead_top": (0.0, 75.0, 85.0), "forehead_left": (45.0, 62.0, 75.0),
    "temple_left": (66.0, 25.0, 30.0), "cheekbone_left": (67.0, -10.0, 15.0),
    "jaw_angle_left": (54.0, -80.0, 5.0), "jaw_left": (30.0, -114.0, 40.0),
    "under_chin": (0.0, -118.0, 55.0), "crown": (0.0, 119.0, -2.0),
}
_JAW_CENTRE = np.array([0.0, -45.0])
_JAW_TOP_Y = -2.0  # height of jaw points 0 and 16


def _jaw_contour() -> np.ndarray:
    """(x, y) of jaw points 8..16: the frontal silhouette of the face (no neck, no ears, in
    front of z = 10), from the chin (x = 0) up to eye height, evenly spaced along it."""

    def face(p: np.ndarray) -> np.ndarray:
        return _face_field(np.column_stack([np.abs(p[:, 0]), p[:, 1], p[:, 2]]))

    angles = np.radians(np.linspace(-90.0, 40.0, 27))
    u = np.column_stack([np.cos(angles), np.sin(angles)])
    lo, hi = np.full(len(u), 20.0), np.full(len(u), 140.0)
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        hit = _seen_from_front(_JAW_CENTRE + u * mid[:, None], face, 10.0)
        lo, hi = np.where(hit, mid, lo), np.where(hit, hi, mid)
    pts = _JAW_CENTRE + u * lo[:, None]
    k = int(np.argmax(pts[:, 1] > _JAW_TOP_Y))
    f = (_JAW_TOP_Y - pts[k - 1, 1]) / (pts[k, 1] - pts[k - 1, 1])
    pts = np.concatenate([pts[:k], [pts[k - 1] + f * (pts[k] - pts[k - 1])]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s = np.linspace(0.0, arc[-1], 9)
    out = np.column_stack([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])])
    out[0, 0] = 0.0
    # Half a millimetre inside the silhouette, so the skin point seen from the front is the
    # face at its edge and not the neck behind it.
    inward = _unit(_JAW_CENTRE - out)
    return out + 0.5 * inward


# ----------------------------------------------------------------------------------------
# Sampling the half sphere of directions and triangulating it.

_EDGE_PER_RADIUS = 1.8  # mean Delaunay edge length of our Poisson-disk sets, in disk radii
_CANDIDATES_PER_DISK = 5.0


def _spacing(p: np.ndarray) -> np.ndarray:
    """Target edge length (mm) on the skin near the points p (N, 3)."""
    ax, y, z = np.abs(p[:, 0]), p[:, 1], p[:, 2]
    face = _sstep(0.0, 35.0, z) * _sstep(90.0, 75.0, y) * _sstep(-125.0, -112.0, y)
    h = 10.0 - 5.6 * face
    ear = np.hypot(np.hypot((ax - 78.0) / 16.0, (y + 5.0) / 36.0), (z + 24.0) / 26.0)
    h = np.minimum(h, 3.6 + 6.4 * _sstep(1.0, 1.5, ear))
    front = z > 45.0  # the feature terms below are for the face only
    eye = np.hypot((ax - 31.25) / 14.25, (y - 0.3) / 4.5)
    h = np.where(front, np.minimum(h, 1.6 + 1.3 * np.maximum(eye - 1.3, 0.0)), h)
    lips = np.hypot(ax / 26.0, (y - _MOUTH_Y + 1.5) / 10.0)
    h = np.where(front, np.minimum(h, 1.7 + 2.5 * np.maximum(lips - 0.85, 0.0)), h)
    nose = np.hypot(ax / 18.0, (y + 20.0) / 28.0)
    return np.where(front, np.minimum(h, 2.6 + 2.2 * np.maximum(nose - 0.8, 0.0)), h)


def _az_el(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth from the front about the vertical (|x| side, [0, pi]) and elevation."""
    return np.arctan2(np.abs(d[:, 0]), d[:, 2]), np.arcsin(np.clip(d[:, 1], -1.0, 1.0))


def _from_az_el(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    return np.column_stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])


class _RayLengths:
    """The skin on a coarse (az, el) grid of the half sphere: ray lengths, and the metric
    m(d) = max(|dp/d el|, |dp/d az| / cos el) in mm per radian (how far a small turn of
    the ray moves its skin point), from differences on the grid, clamped to [t / 2, 4 t]."""

    STEP = np.radians(3.0)

    def __init__(self) -> None:
        self.az = np.linspace(0.0, np.pi, int(round(np.pi / self.STEP)) + 1)
        self.el = np.linspace(-np.pi / 2 + self.STEP / 2, np.pi / 2 - self.STEP / 2,
                              int(round(np.pi / self.STEP)))
        A, E = np.meshgrid(self.az, self.el, indexing="ij")
        d = _from_az_el(A.ravel(), E.ravel())
        p = _raycast(d).reshape(A.shape + (3,))
        t = np.linalg.norm(p.reshape(-1, 3) - _origins(d), axis=1).reshape(A.shape)
        d_az = np.linalg.norm(np.gradient(p, self.az, axis=0), axis=2) / np.cos(E)
        d_el = np.linalg.norm(np.gradient(p, self.el, axis=1), axis=2)
        self.length = t
        self.metric = np.clip(np.maximum(d_az, d_el), 0.5 * t, 4.0 * t)

    def _cell(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Grid cell (ia, ie) of each direction and its position in the cell (wa, we)."""
        az, el = _az_el(d)
        fa = np.clip(az / (self.az[1] - self.az[0]), 0, len(self.az) - 1.000001)
        fe = np.clip((el - self.el[0]) / (self.el[1] - self.el[0]), 0, len(self.el) - 1.000001)
        ia, ie = fa.astype(int), fe.astype(int)
        return ia, ie, fa - ia, fe - ie

    def _lookup(self, table: np.ndarray, d: np.ndarray) -> np.ndarray:
        ia, ie, wa, we = self._cell(d)
        return ((1 - wa) * (1 - we) * table[ia, ie] + wa * (1 - we) * table[ia + 1, ie]
                + (1 - wa) * we * table[ia, ie + 1] + wa * we * table[ia + 1, ie + 1])

    def start(self, d: np.ndarray) -> np.ndarray:
        """A ray length just beyond the skin: the largest of the four nearest table values
        plus 6 mm (``_raycast`` checks it)."""
        ia, ie, _, _ = self._cell(d)
        t = self.length
        return np.maximum.reduce([t[ia, ie], t[ia + 1, ie], t[ia, ie + 1], t[ia + 1, ie + 1]]) + 6.0

    def disk_radius(self, d: np.ndarray) -> np.ndarray:
        """Poisson-disk radius (radians) for directions d: target spacing over the metric."""
        t = self._lookup(self.length, d)
        h = _spacing(_origins(d) + d * t[:, None])
        return h / (_EDGE_PER_RADIUS * self._lookup(self.metric, d))


def _uniform_cap(rng: np.random.Generator, n: int, axis: np.ndarray, cos_max: float) -> np.ndarray:
    """n uniform unit vectors within the cap {d : d . axis >= cos_max}, with x >= 0."""
    w = rng.uniform(cos_max, 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    e1 = _unit(np.cross(axis, [0.0, 1.0, 0.0]))
    e2 = np.cross(axis, e1)
    r = np.sqrt(1.0 - w * w)
    d = w[:, None] * axis + r[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    d[:, 0] = np.abs(d[:, 0])
    return d


def _gnomonic(d: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Tangent-plane coordinates (N, 2) of directions d around the unit vector centre."""
    e1 = _unit(np.cross([0.0, 1.0, 0.0], centre))
    e2 = np.cross(centre, e1)
    w = d @ centre
    return np.column_stack([d @ e1 / w, d @ e2 / w])


def _inside_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Crossing-number test of 2D points (N, 2) against a closed polygon (M, 2)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    x, y = pts[:, :1], pts[:, 1:]
    straddle = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (straddle & (x < xc)).sum(axis=1) % 2 == 1


def _in_hole(d: np.ndarray, holes: list[np.ndarray]) -> np.ndarray:
    """Whether directions d (N, 3) fall inside any hole (closed loops of unit directions)."""
    out = np.zeros(len(d), dtype=bool)
    for loop in holes:
        centre = _unit(loop.mean(axis=0))
        out |= (d @ centre > 0.9) & _inside_polygon(_gnomonic(d, centre), _gnomonic(loop, centre))
    return out


def _gabriel_conflicts(d: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Whether directions d (N, 3) lie in the diametral circle of any segment (S, 2, 3)."""
    mid = _unit(segments[:, 0] + segments[:, 1])
    radius = 0.5 * np.linalg.norm(segments[:, 0] - segments[:, 1], axis=1) * 1.05
    bad = np.zeros(len(d), dtype=bool)
    tree = cKDTree(d)
    for m, r in zip(mid, radius):
        bad[tree.query_ball_point(m, r)] = True
    return bad


def _spherical_delaunay(dirs: np.ndarray) -> np.ndarray:
    """Triangles (M, 3) of the convex hull of unit vectors, counter-clockwise from outside."""
    hull = ConvexHull(dirs)
    if len(hull.vertices) != len(dirs):
        raise RuntimeError("head: a direction sample is not a hull vertex")
    tri = hull.simplices.astype(np.int64)
    a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) < 0.0
    tri[flip] = tri[flip][:, ::-1]
    return tri


_RELAXATIONS = 3


def _relax(base: np.ndarray, free: np.ndarray, lengths: _RayLengths, holes: list[np.ndarray],
           segments: np.ndarray) -> np.ndarray:
    """One Lloyd step for the free samples: each moves to the density-weighted mean of the
    centroids of its Delaunay triangles (a centroidal Voronoi relaxation with density
    1 / rho^2). A move that would leave the open half sphere, enter an opening or break the
    Gabriel condition of a margin or lip segment is not made."""
    dirs = np.concatenate([base, free])
    tri = _spherical_delaunay(dirs)
    tri = tri[~(dirs[tri, 0] == 0.0).all(axis=1)]
    a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
    centroid = _unit(a + b + c)
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    weight = area / lengths.disk_radius(centroid) ** 2
    acc = np.zeros_like(dirs)
    total = np.zeros(len(dirs))
    for k in range(3):
        np.add.at(acc, tri[:, k], weight[:, None] * centroid)
        np.add.at(total, tri[:, k], weight)
    moved = _unit(acc[len(base):])
    ok = (moved[:, 0] > 0.4 * lengths.disk_radius(moved)) & ~_in_hole(moved, holes)
    ok &= ~_gabriel_conflicts(moved, segments)
    return np.where(ok[:, None], moved, free)


def _recover_edges(tri: np.ndarray, wanted: list[tuple[int, int]]) -> np.ndarray:
    """Make each wanted edge (i, j) a triangulation edge by flipping the one edge that
    crosses it, where the two triangles on that edge have i and j as apexes (the case that
    a Gabriel-conforming sampling leaves at sharp corners). Windings are kept."""
    tri = tri.copy()
    for i, j in wanted:
        has_i = np.flatnonzero((tri == i).any(axis=1))
        if any(j in tri[t] for t in has_i):
            continue
        for t in has_i:
            k = int(np.flatnonzero(tri[t] == i)[0])
            b, c = tri[t][(k + 1) % 3], tri[t][(k + 2) % 3]  # triangle (i, b, c)
            has = (tri == c).any(axis=1) & (tri == b).any(axis=1) & (tri == j).any(axis=1)
            other = np.flatnonzero(has)
            if other.size:
                tri[t] = (i, b, j)
                tri[other[0]] = (j, c, i)
                break
        else:
            raise RuntimeError(f"head: cannot recover the edge {i}-{j}")
    return tri


@dataclass(frozen=True)
class _HalfSkin:
    """The skin over the half sphere x >= 0 (directions, points, triangles) and its features."""

    dirs: np.ndarray        # (N, 3) unit ray directions
    points: np.ndarray      # (N, 3) skin points, mm
    triangles: np.ndarray   # (M, 3) counter-clockwise from outside
    midline: np.ndarray     # (N,) bool, x == 0
    margin: np.ndarray      # (2 * _LID_STEPS,) vertex loop of the left eye opening
    lip_upper: np.ndarray   # (_LIP_STEPS + 1,) vertices from 62 to the corner 64
    lip_lower: np.ndarray   # (_LIP_STEPS,) vertices after the corner, down to 66
    named: dict[int | str, int]  # landmark index or phantom name -> vertex


@dataclass(frozen=True)
class _Fixed:
    """The samples placed by design: margin and lip lines (the openings' boundaries), the
    rows beside them, landmarks and phantoms."""

    dirs: np.ndarray             # (K, 3) unit directions: margin, lip lines, named, rows
    margin: np.ndarray           # indices of the margin loop (counter-clockwise from front)
    lip: np.ndarray              # indices of the half lip loop, 62 .. corner 64 .. 66
    named: dict[int | str, int]  # landmark index or phantom name -> index

    def segments(self) -> np.ndarray:
        """(S, 2, 3): the margin and lip-line segments that must be mesh edges."""
        m, lip = self.dirs[self.margin], self.dirs[self.lip]
        return np.concatenate([np.stack([m, np.roll(m, -1, axis=0)], axis=1),
                               np.stack([lip[:-1], lip[1:]], axis=1)])

    def holes(self) -> list[np.ndarray]:
        """The eye opening and the lip slit (closed through the midline from 66 to 62)."""
        return [self.dirs[self.margin], self.dirs[self.lip]]


def _fixed_samples() -> _Fixed:
    margin_xy = _margin_xy()
    upper_xy, lower_xy = _lip_lines()
    lip_xy = np.concatenate([upper_xy, lower_xy])
    lip_rows = _offset_rows(lip_xy, False, True, (1.5, 3.2)).reshape(2, len(lip_xy), 2)
    lip_rows[:, [0, -1], 0] = 0.0  # the rows start and end on the midline
    rows_xy = np.concatenate([_offset_rows(margin_xy, True, False, (1.4, 3.0)),
                              lip_rows.reshape(-1, 2)])
    front = dict(_FRONT_LANDMARKS)
    front.update(_outer_lip_xy())
    front.update(zip(range(8, 17), map(tuple, _jaw_contour())))
    front_xy = np.array(list(front.values()))
    all_xy = np.concatenate([margin_xy, lip_xy, front_xy, rows_xy])
    seen = _front_directions(all_xy)
    seen[all_xy[:, 0] == 0.0, 0] = 0.0
    n_margin, n_lip, n_front = len(margin_xy), len(lip_xy), len(front_xy)
    phantoms = _directions_to(np.array(list(_PHANTOM_POINTS.values())))
    cut = n_margin + n_lip + n_front
    dirs = np.concatenate([seen[:cut], phantoms, seen[cut:]])

    margin = np.arange(n_margin)
    lip = n_margin + np.arange(n_lip)
    keys = list(front) + list(_PHANTOM_POINTS)
    named: dict[int | str, int] = {k: n_margin + n_lip + i for i, k in enumerate(keys)}
    named.update({lm: int(margin[step]) for lm, step in _MARGIN_LANDMARKS.items()})
    upper, lower = lip[:_LIP_STEPS + 1], lip[_LIP_STEPS + 1:]
    named.update({62: int(upper[0]), 63: int(upper[_LIP_LANDMARK_STEP]), 64: int(upper[-1]),
                  65: int(lower[-1 - _LIP_LANDMARK_STEP]), 66: int(lower[-1])})
    return _Fixed(dirs, margin, lip, named)


def _midline_samples(lengths: _RayLengths, fixed: _Fixed) -> np.ndarray:
    """Directions on the midline x = 0, evenly spaced in units of the local spacing, away from
    the fixed midline samples, outside the lip slit and clear of the Gabriel circles."""
    psi = np.linspace(-np.pi, np.pi, 7201)[:-1] + np.pi / 7200  # angle from +z toward +y
    line = np.column_stack([np.zeros_like(psi), np.sin(psi), np.cos(psi)])
    step = lengths.disk_radius(line) * _EDGE_PER_RADIUS
    arc = np.concatenate([[0.0], np.cumsum(0.5 * (1 / step[1:] + 1 / step[:-1]) * np.diff(psi))])
    n = int(round(arc[-1]))
    at = np.interp(np.arange(n) * arc[-1] / n, arc, psi)
    dirs = np.column_stack([np.zeros(n), np.sin(at), np.cos(at)])
    on_mid = fixed.dirs[fixed.dirs[:, 0] == 0.0]
    gap = np.angle(np.exp(1j * (at[:, None] - np.arctan2(on_mid[:, 1], on_mid[:, 2])[None])))
    lip = fixed.dirs[fixed.lip]
    slit = (np.arctan2(lip[-1, 1], lip[-1, 2]), np.arctan2(lip[0, 1], lip[0, 2]))
    keep = np.abs(gap).min(axis=1) > 0.6 * np.interp(at, psi, step)
    keep &= ~((at > slit[0]) & (at < slit[1]))
    keep &= ~_gabriel_conflicts(dirs, fixed.segments())
    return dirs[keep]


def _poisson_samples(lengths: _RayLengths, fixed: _Fixed, base: np.ndarray,
                     rng: np.random.Generator) -> np.ndarray:
    """Free directions on the open half sphere: Poisson-disk thinning of random candidates
    (about ``_CANDIDATES_PER_DISK`` per disk, by rejection sampling from a uniform cover of
    the half sphere plus a denser one of the middle of the face), keeping away from the
    ``base`` samples, the midline, the openings and the Gabriel circles."""
    centre_axis = _directions_to(np.array([[0.0, -20.0, 100.0]]))[0]
    cos_cap = np.cos(np.radians(42.0))
    A, E = np.meshgrid(lengths.az, lengths.el, indexing="ij")
    grid = _from_az_el(A.ravel(), E.ravel())
    wanted = _CANDIDATES_PER_DISK / (np.pi * lengths.disk_radius(grid) ** 2)
    in_cap = grid @ centre_axis >= cos_cap
    n_coarse = int(1.3 * wanted[~in_cap].max() * 2.0 * np.pi)
    cap_area = np.pi * (1.0 - cos_cap)
    n_fine = int(1.3 * max(wanted[in_cap].max() - n_coarse / (2.0 * np.pi), 0.0) * cap_area)
    cand = np.concatenate([_uniform_cap(rng, n_coarse, np.array([1.0, 0.0, 0.0]), 0.0),
                           _uniform_cap(rng, n_fine, centre_axis, cos_cap)])
    offered = n_coarse / (2.0 * np.pi) + (cand @ centre_axis >= cos_cap) * n_fine / cap_area
    rho = lengths.disk_radius(cand)
    keep = rng.random(len(cand)) * offered < _CANDIDATES_PER_DISK / (np.pi * rho ** 2)
    keep &= cand[:, 0] > 0.4 * rho
    cand, rho = cand[keep], rho[keep]
    ok = ~_in_hole(cand, fixed.holes()) & ~_gabriel_conflicts(cand, fixed.segments())
    cand, rho = cand[ok], rho[ok]

    alive = np.ones(len(cand), dtype=bool)
    tree = cKDTree(cand)
    for d, r in zip(base, 0.8 * lengths.disk_radius(base)):
        alive[tree.query_ball_point(d, r)] = False
    chosen = []
    for i in rng.permutation(len(cand)):
        if alive[i]:
            chosen.append(i)
            alive[tree.query_ball_point(cand[i], rho[i])] = False
    return cand[np.sort(chosen)]


def _half_skin() -> _HalfSkin:
    lengths = _RayLengths()
    fixed = _fixed_samples()
    base = np.concatenate([fixed.dirs, _midline_samples(lengths, fixed)])
    free = _poisson_samples(lengths, fixed, base, np.random.default_rng(20240611))
    holes, segments = fixed.holes(), fixed.segments()
    for _ in range(_RELAXATIONS):
        free = _relax(base, free, lengths, holes, segments)
    dirs = np.concatenate([base, free])
    midline = dirs[:, 0] == 0.0
    if np.any(dirs[:, 0] < 0.0) or np.any(dirs[~midline, 0] < 1e-4):
        raise RuntimeError("head: a direction sample is on the wrong side of the midline")

    tri = _spherical_delaunay(dirs)
    tri = tri[~midline[tri].all(axis=1)]  # the flat lid of the half sphere's hull
    loop_edges = (list(zip(fixed.margin, np.roll(fixed.margin, -1)))
                  + list(zip(fixed.lip[:-1], fixed.lip[1:])))
    tri = _recover_edges(tri, loop_edges)
    tri = tri[~_in_hole(_unit(dirs[tri].sum(axis=1)), holes)]
    edges = {tuple(e) for t in tri for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    for i, j in loop_edges:
        if (i, j) not in edges and (j, i) not in edges:
            raise RuntimeError(f"head: the margin or lip-line segment {i}-{j} is not a mesh edge")
    points = _raycast(dirs, start=lengths.start(dirs))
    return _HalfSkin(dirs, points, tri, midline, fixed.margin, fixed.lip[:_LIP_STEPS + 1],
                     fixed.lip[_LIP_STEPS + 1:], fixed.named)


# ----------------------------------------------------------------------------------------
# Texture layout.

SKIN_U_MAX = 0.8
EYE_UV = {"left": (0.95, 0.9), "right": (0.85, 0.9)}
EYE_UV_RADIUS = 0.047  # in u; the v radius is twice as large (square texels on a 2:1 image)
EYE_BACK_UV = {"left": (0.95, 0.2), "right": (0.85, 0.2)}  # the hidden back halves
EYE_BACK_UV_RADIUS = 0.03
MOUTH_UV = (0.9, 0.55)
MOUTH_UV_RADIUS = 0.09


def _warp(values: np.ndarray, lo: float, hi: float, inner: float, outer: float,
          rest: float) -> np.ndarray:
    """Normalised integral over [lo, hi] of a density that is 1 inside [inner, outer] and
    falls smoothly (over 15 degrees) to ``rest`` outside, evaluated at ``values``."""
    grid = np.linspace(lo, hi, 2001)
    ramp = np.radians(15.0)
    inside = _sstep(inner - ramp, inner, grid) * _sstep(outer + ramp, outer, grid)
    dens = rest + (1.0 - rest) * inside
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    return np.interp(values, grid, cum / cum[-1])


def _skin_uv(dirs: np.ndarray) -> np.ndarray:
    """Texture coordinates of skin directions (N, 3) with x >= 0 (module docstring)."""
    az, el = _az_el(dirs)
    u = 0.5 * SKIN_U_MAX * (1.0 + _warp(az, 0.0, np.pi, -1.0, np.radians(70.0), 0.12))
    v = _warp(el, -np.pi / 2, np.pi / 2, np.radians(-45.0), np.radians(52.0), 0.15)
    return np.column_stack([u, v])


# ----------------------------------------------------------------------------------------
# Closing the openings, and the eyeballs (left side; the right side is mirrored).


def _slerp(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """Spherical interpolation between unit vectors a (N, 3) and b (3,)."""
    angle = np.arccos(np.clip(a @ b, -1.0, 1.0))[:, None]
    return (np.sin((1.0 - t) * angle) * a + np.sin(t * angle) * b) / np.sin(angle)


def _socket(margin_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The socket cup behind the eyelid margin loop (L, 3): a narrow roll just inside the
    margin (so the lid edge is rounded), then rings on a sphere just outside the eyeball,
    turning back to a cap behind it.

    Returns the new points (5 L + 1, 3), their ring weights for the UV (0 at the margin,
    1 at the cap), and triangles with the margin as indices 0..L-1 and the new points after."""
    back = np.array([0.0, 0.0, -1.0])
    offset = margin_points - EYE_CENTRE
    omega = _unit(offset)
    edge = np.linalg.norm(offset, axis=1)
    roll = 0.75 * edge + 0.25 * (EYE_RADIUS + _SOCKET_GAP)
    steps = [(0.012, roll), (0.1, EYE_RADIUS + 0.5), (0.3, EYE_RADIUS + _SOCKET_GAP),
             (0.55, EYE_RADIUS + _SOCKET_GAP), (0.8, EYE_RADIUS + _SOCKET_GAP)]
    rings = [EYE_CENTRE + np.reshape(r, (-1, 1)) * _slerp(omega, back, t) for t, r in steps]
    cap = EYE_CENTRE + (EYE_RADIUS + _SOCKET_GAP) * back
    n = len(margin_points)
    tri = []
    for k in range(len(steps)):
        a = np.arange(n) + k * n
        b = np.arange(n) + (k + 1) * n
        a1, b1 = np.roll(a, -1), np.roll(b, -1)
        tri += [np.column_stack([a, a1, b1]), np.column_stack([a, b1, b])]
    last = np.arange(n) + len(steps) * n
    tri.append(np.column_stack([last, np.roll(last, -1), np.full(n, (len(steps) + 1) * n)]))
    weights = np.concatenate([np.repeat([0.1, 0.3, 0.5, 0.7, 0.85], n), [1.0]])
    return np.concatenate(rings + [cap[None]]), weights, np.concatenate(tri)


def _cavity(lip_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half of the mouth cavity behind the inner lip line (L, 3), from 62 round the corner
    to 66 (both on the midline).

    Returns points (ring 0 = the lip line again, then 6 rings, then the cap centre on the
    midline), their polar texture parameters (radius in [0, 1], angle from +90 to -90 deg),
    and triangles, counter-clockwise seen from the air in the mouth (outward of the skin)."""
    n = len(lip_points)
    seg = np.linalg.norm(np.diff(lip_points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)]) / seg.sum()
    alpha = np.pi / 2 - np.pi * s
    z0 = float(lip_points[:, 2].mean())
    yc = _MOUTH_Y - 2.0
    design = [(-1.2, 21.0, 3.0), (-7.0, 23.0, 8.0), (-15.0, 24.0, 13.0), (-25.0, 22.0, 15.0),
              (-35.0, 17.0, 12.0), (-42.0, 9.0, 7.0)]
    rings = [lip_points]
    for k, (dz, half_w, half_h) in enumerate(design):
        ring = np.column_stack([half_w * np.cos(alpha), yc + half_h * np.sin(alpha),
                                np.full(n, z0 + dz)])
        if k == 0:
            ring = 0.8 * lip_points + 0.2 * ring
        ring[[0, -1], 0] = 0.0
        rings.append(ring)
    cap = np.array([[0.0, yc, z0 - 45.0]])
    points = np.concatenate(rings + [cap])
    radius = np.concatenate([np.repeat(1.0 - np.arange(len(rings)) / len(rings), n), [0.0]])
    angle = np.concatenate([np.tile(alpha, len(rings)), [0.0]])
    tri = []
    for k in range(len(rings) - 1):
        a = np.arange(n - 1) + k * n
        b = a + n
        tri += [np.column_stack([a, b + 1, a + 1]), np.column_stack([a, b, b + 1])]
    last = np.arange(n - 1) + (len(rings) - 1) * n
    tri.append(np.column_stack([last, np.full(n - 1, len(points) - 1), last + 1]))
    return points, np.column_stack([radius, angle]), np.concatenate(tri)


_EYE_THETA_DEG = [4.5, 9.0, 15.0, 22.0, IRIS_ANGLE_DEG, 37.0, 45.0, 55.0, 66.0, 78.0, 90.0,
                  105.0, 120.0, 135.0, 150.0, 165.0]
_EYE_LONGITUDES = 24


def _eyeball() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The left eyeball: points (N, 3), UV (N, 2) and triangles (outward).

    Two caps that share the 90-degree ring's positions but not its vertices (a UV seam): the
    front maps onto the disc at ``EYE_UV``, the back (never seen) onto the small disc at
    ``EYE_BACK_UV``, so no texel belongs to two surface points.
    """
    theta = np.radians(np.array(_EYE_THETA_DEG))
    equator = int(np.argmin(np.abs(theta - np.pi / 2)))
    front = _eye_cap(np.concatenate([[0.0], theta[:equator + 1]]), EYE_UV["left"],
                     EYE_UV_RADIUS)
    back = _eye_cap(np.concatenate([[np.pi], theta[equator:][::-1]]), EYE_BACK_UV["left"],
                    EYE_BACK_UV_RADIUS)
    points, uv = (np.concatenate([f, b]) for f, b in zip(front[:2], back[:2]))
    return points, uv, np.concatenate([front[2], back[2][:, ::-1] + len(front[0])])


def _eye_cap(theta: np.ndarray, centre: tuple[float, float], radius: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A cap of the eyeball from its pole ``theta[0]`` through rings ``theta[1:]`` (radians
    from the gaze axis, ending at 90 degrees): points, UV on a disc (the pole at the centre,
    the 90-degree ring at ``0.98 radius``), triangles outward for a front cap."""
    n = _EYE_LONGITUDES
    phi = 2.0 * np.pi * np.arange(n) / n
    T, P = np.meshgrid(theta[1:], phi, indexing="ij")
    T, P = np.concatenate([theta[:1], T.ravel()]), np.concatenate([[0.0], P.ravel()])
    lim = np.radians(IRIS_ANGLE_DEG + 6.0)
    r = EYE_RADIUS + CORNEA_BULGE * np.clip(1.0 - (T / lim) ** 2, 0.0, 1.0) ** 2
    points = EYE_CENTRE + r[:, None] * np.column_stack(
        [np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)])
    rho = 0.98 * (np.abs(T - theta[0]) / (np.pi / 2)) ** 0.75
    uv = np.column_stack([centre[0] + radius * rho * np.cos(P),
                          centre[1] + 2.0 * radius * rho * np.sin(P)])

    def ring(k: int) -> np.ndarray:
        return 1 + k * n + np.arange(n)

    tri = [np.column_stack([np.zeros(n, int), ring(0), np.roll(ring(0), -1)])]
    for k in range(len(theta) - 2):
        a, b = ring(k), ring(k + 1)
        tri += [np.column_stack([a, b, np.roll(b, -1)]),
                np.column_stack([a, np.roll(b, -1), np.roll(a, -1)])]
    return points, uv, np.concatenate(tri)


# ----------------------------------------------------------------------------------------
# Tags.

# Hairline: height (mm) against the azimuth about the vertical axis x = 0, z = -5 (0 at the
# front): the forehead, the temples, the sideburns in front of the ears, down behind them.
_HAIRLINE_AZ = np.radians([0.0, 30.0, 50.0, 65.0, 78.0, 90.0, 100.0, 180.0])
_HAIRLINE_Y = np.array([72.0, 68.0, 55.0, 35.0, 8.0, 5.0, -55.0, -55.0])


def _skin_tags(centroids: np.ndarray) -> np.ndarray:
    """SKIN, SCALP (above the hairline) or EAR for skin triangles with centroids (M, 3)."""
    q = np.column_stack([np.abs(centroids[:, 0]), centroids[:, 1], centroids[:, 2]])
    az = np.arctan2(q[:, 0], q[:, 2] - _RAY_AXIS_Z)
    tags = np.full(len(q), Tag.SKIN, dtype=np.uint8)
    tags[q[:, 1] > np.interp(az, _HAIRLINE_AZ, _HAIRLINE_Y)] = Tag.SCALP
    tags[_ear_field(q) < 2.0] = Tag.EAR
    return tags


# ----------------------------------------------------------------------------------------
# Assembly.


@dataclass(frozen=True)
class _Built:
    mesh: Mesh
    mirror: np.ndarray


def _assemble() -> _Built:
    half = _half_skin()
    seam = half.midline & (half.dirs[:, 2] < 0.0)

    pts: list[np.ndarray] = []
    uvs: list[np.ndarray] = []
    axis: list[np.ndarray] = []
    shared: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    tags: list[np.ndarray] = []

    def add(p, uv, a, sh):
        start = sum(len(x) for x in pts)
        pts.append(p)
        uvs.append(uv)
        axis.append(np.full(len(p), a))
        shared.append(sh)
        return start

    def add_tri(t, tag):
        tris.append(t)
        tags.append(np.broadcast_to(np.asarray(tag, dtype=np.uint8), (len(t),)))

    skin_uv = _skin_uv(half.dirs)
    skin_uv[half.midline & ~seam, 0] = 0.5 * SKIN_U_MAX
    add(half.points, skin_uv, 0.5 * SKIN_U_MAX, half.midline & ~seam)
    add_tri(half.triangles, _skin_tags(half.points[half.triangles].mean(axis=1)))

    # Socket: rings map into the eye opening's own (empty) area of the skin texture.
    margin = half.margin
    sock_p, sock_w, sock_t = _socket(half.points[margin])
    hole_uv = skin_uv[margin].mean(axis=0)
    ring_uv = np.concatenate([np.tile(skin_uv[margin], (5, 1)), [hole_uv]])
    sock_uv = (1.0 - sock_w[:, None]) * ring_uv + sock_w[:, None] * hole_uv
    start = add(sock_p, sock_uv, 0.5 * SKIN_U_MAX, np.zeros(len(sock_p), bool))
    local = np.concatenate([margin, start + np.arange(len(sock_p))])
    add_tri(local[sock_t], Tag.SKIN)

    # Mouth cavity: its own copy of the lip line (a texture seam), its own texture disc.
    lip = np.concatenate([half.lip_upper, half.lip_lower])
    cav_p, cav_polar, cav_t = _cavity(half.points[lip])
    cu, cv = MOUTH_UV
    cav_uv = np.column_stack([cu + MOUTH_UV_RADIUS * cav_polar[:, 0] * np.cos(cav_polar[:, 1]),
                              cv + 2 * MOUTH_UV_RADIUS * cav_polar[:, 0] * np.sin(cav_polar[:, 1])])
    on_mid = cav_p[:, 0] == 0.0
    cav_uv[on_mid, 0] = cu
    start = add(cav_p, cav_uv, cu, on_mid)
    add_tri(start + cav_t, Tag.MOUTH_INTERIOR)

    eye_p, eye_uv, eye_t = _eyeball()
    start = add(eye_p, eye_uv, 0.5 * (EYE_UV["left"][0] + EYE_UV["right"][0]),
                np.zeros(len(eye_p), bool))
    add_tri(start + eye_t, Tag.LEFT_EYEBALL)

    P, UV, A, S = (np.concatenate(x) for x in (pts, uvs, axis, shared))
    T, G = np.concatenate(tris), np.concatenate(tags)
    if np.any(P[S, 0] != 0.0) or np.any(UV[S, 0] != A[S]):
        raise RuntimeError("head: a shared midline vertex is off the mirror plane")

    # Mirror: the right side repeats every vertex that is not shared.
    n = len(P)
    other = np.flatnonzero(~S)
    right = np.arange(n)
    right[other] = n + np.arange(len(other))
    Pr = P[other] * np.array([-1.0, 1.0, 1.0])
    UVr = np.column_stack([2.0 * A[other] - UV[other, 0], UV[other, 1]])
    Gr = G.copy()
    Gr[G == Tag.LEFT_EYEBALL] = Tag.RIGHT_EYEBALL
    vertices = np.concatenate([P, Pr])
    uv = np.concatenate([UV, UVr])
    triangles = np.concatenate([T, right[T][:, ::-1]])
    tags_all = np.concatenate([G, Gr])
    mirror = np.concatenate([right, other])

    landmarks = np.zeros(N_LANDMARKS, dtype=np.int64)
    for i in range(N_LANDMARKS):
        if i in half.named:
            landmarks[i] = half.named[i]
        else:
            landmarks[i] = right[half.named[int(MIRROR[i])]]
    phantoms = []
    for name in PHANTOM_NAMES:
        if name.endswith("_right"):
            phantoms.append(right[half.named[name[: -len("_right")] + "_left"]])
        else:
            phantoms.append(half.named[name])
    mesh = Mesh(vertices=vertices.astype(np.float32), triangles=triangles.astype(np.int32),
                uv=uv.astype(np.float32), tags=tags_all.astype(np.uint8),
                landmarks=landmarks.astype(np.int32), phantoms=np.array(phantoms, np.int32))
    return _Built(mesh, mirror.astype(np.int32))


@lru_cache(maxsize=1)
def _built() -> _Built:
    built = _assemble()
    for a in (built.mesh.vertices, built.mesh.triangles, built.mesh.uv, built.mesh.tags,
              built.mesh.landmarks, built.mesh.phantoms, built.mirror):
        a.setflags(write=False)
    return built


def generic_head() -> Mesh:
    """The generic head mesh (module docstring); deterministic, built once per process.

    Returns:
        A new ``Mesh`` (fresh, writable arrays): vertices (N, 3) float32 mm, triangles (M, 3)
        int32, uv (N, 2) float32, tags (M,) uint8, landmarks (68,) int32, phantoms (13,)
        int32 in ``models.landmarks.PHANTOM_NAMES`` order.
    """
    m = _built().mesh
    return Mesh(vertices=m.vertices.copy(), triangles=m.triangles.copy(), uv=m.uv.copy(),
                tags=m.tags.copy(), landmarks=m.landmarks.copy(), phantoms=m.phantoms.copy())


def mirror_map() -> np.ndarray:
    """(N,) int32: for each vertex of ``generic_head()``, the vertex at its mirror image
    (x -> -x). An involution; midline vertices map to themselves, the two copies of a
    texture-seam vertex on the back of the head map to each other."""
    return _built().mirror.copy()
