"""The generic head's skin parameterised by ray directions, and ray casting.

Each unit direction ``d`` meets the skin once on the ray ``o(d) + t d``, t > 0, with ``o(d)``
on the vertical axis x = 0, z = -5: at y = -40 for directions above -40 deg of elevation and
lower (down to y = -120, a smoothstep in the elevation) for steeper ones, so that rays meet
the neck at a good angle; the height of ``o`` never decreases with the elevation, so rays
never cross and each skin point belongs to exactly one direction. The skin point ``p(d)`` is
the outermost root of ``f`` on the ray: marched inward in steps of 1.5 mm from a bounding
ellipsoid (or from a given start), then bisected 15 times.

The inverse, the direction of the ray through a point, keeps the point's azimuth about the
axis and solves ``tan(el) = (y - y_o(el)) / r`` for the elevation by bisection. Directions
are also written as azimuth (from the front, about the vertical, on the |x| side, [0, pi])
and elevation: ``d = (cos el sin az, sin el, cos el cos az)``.
"""

from __future__ import annotations

import numpy as np

from facewire.models.head.primitives import sstep, unit
from facewire.models.head.skin import skin_field

# Rays start on the vertical axis x = 0, z = -5: at y = -40 for directions above 40 degrees
# below the horizon, lower (down to y = -120) for steeper ones, so that they meet the neck
# at a good angle. The origin height never decreases with the elevation, so no two rays
# cross and each skin point belongs to exactly one direction.
RAY_AXIS_Z = -5.0
_RAY_Y = (-40.0, -120.0)
_RAY_EL = (np.radians(-40.0), np.radians(-90.0))
# An ellipsoid around the whole skin: rays are marched inward from it.
_BOUND_CENTRE = np.array([0.0, -23.0, -5.0])
_BOUND_RADII = np.array([100.0, 150.0, 135.0])


def raycast(dirs: np.ndarray, origins: np.ndarray | None = None,
            start: np.ndarray | None = None, field=skin_field, step: float = 1.5) -> np.ndarray:
    """The outermost root of ``field`` on each ray o + t d, t > 0 (d unit, (N, 3); o the ray
    origins (N, 3), by default those of the skin parameterisation): marched inward from
    ``start`` (N,) where the field is positive there, else from the bounding ellipsoid, then
    bisected. Returns the points (N, 3)."""
    o = ray_origins(dirs) if origins is None else np.broadcast_to(origins, dirs.shape)
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


def _origin_height(el: np.ndarray) -> np.ndarray:
    return _RAY_Y[0] + (_RAY_Y[1] - _RAY_Y[0]) * sstep(_RAY_EL[0], _RAY_EL[1], el)


def ray_origins(dirs: np.ndarray) -> np.ndarray:
    """The ray origins (N, 3) of unit directions (N, 3)."""
    el = np.arcsin(np.clip(dirs[:, 1], -1.0, 1.0))
    n = len(dirs)
    return np.column_stack([np.zeros(n), _origin_height(el), np.full(n, RAY_AXIS_Z)])


def directions_to(points: np.ndarray) -> np.ndarray:
    """The ray directions (N, 3) whose rays pass through the points (N, 3): the azimuth is
    that of the point about the axis; the elevation solves tan(el) = (y - y_o(el)) / r by
    bisection (the left side rises with el, the right side does not)."""
    rel = points - np.array([0.0, 0.0, RAY_AXIS_Z])
    r = np.hypot(rel[:, 0], rel[:, 2])
    lo, hi = np.full(len(points), -np.pi / 2), np.full(len(points), np.pi / 2)
    for _ in range(40):
        el = 0.5 * (lo + hi)
        above = np.arctan2(points[:, 1] - _origin_height(el), r) > el
        lo, hi = np.where(above, el, lo), np.where(above, hi, el)
    el = 0.5 * (lo + hi)
    h = np.cos(el)[:, None] * unit(np.column_stack([rel[:, 0], np.zeros(len(points)), rel[:, 2]]))
    d = np.column_stack([h[:, 0], np.sin(el), h[:, 2]])
    d[points[:, 0] == 0.0, 0] = 0.0
    return d


def front_directions(xy: np.ndarray) -> np.ndarray:
    """Ray directions of the skin points seen straight from the front at (x, y) (N, 2)."""
    origins = np.column_stack([xy, np.full(len(xy), -150.0)])
    dirs = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    return directions_to(raycast(dirs, origins, np.full(len(xy), 275.0)))


def seen_from_front(xy: np.ndarray, field, z_min: float) -> np.ndarray:
    """Whether a line along z through each (x, y) meets field < 0 at some z >= z_min
    (sampled every 1.5 mm): the frontal silhouette test."""
    z = np.arange(z_min, 130.0, 1.5)
    p = np.column_stack([np.repeat(xy, len(z), axis=0), np.tile(z, len(xy))])
    return (field(p) < 0.0).reshape(len(xy), len(z)).any(axis=1)


def az_el(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth from the front about the vertical (|x| side, [0, pi]) and elevation."""
    return np.arctan2(np.abs(d[:, 0]), d[:, 2]), np.arcsin(np.clip(d[:, 1], -1.0, 1.0))


def from_az_el(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """Unit directions (N, 3) of azimuths and elevations (N,) (module docstring)."""
    return np.column_stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
