"""What closes the generic head's openings, and the eyeballs (the left side; the right is
mirrored).

- The slit between the lips (2 mm at the middle) leads into a mouth cavity: the lip line
  again (its own copy: a texture seam), six rings shrinking 45 mm back into the head, and a
  fan. Its texture is the disc at ``MOUTH_UV``: the inner lip line on the rim (the person's
  left half on the right, the midline at top and bottom), the back of the cavity at the
  centre.
- Each eye opening leads into a socket cup: a narrow roll that rounds the lid edge, then
  rings on a sphere 0.35 mm outside the eyeball, slerped from the margin's directions toward
  -z, that turn back to a cap behind it. Its texture fills the eye opening of the skin map.
- Skin, sockets and cavity are one closed genus-0 surface once the texture-seam copies are
  welded by position. Each eyeball is a separate closed sphere (radius 12.2 mm, corneal bulge
  ``0.8 (1 - (theta / 35.5 deg)^2)^2`` mm) looking along +z; the angle theta from the gaze
  axis goes to the radius ``0.98 (theta / 90 deg) ** 0.75`` of its texture disc, so the
  cornea apex is the centre and the iris (theta < 29.5 deg) the inner 44 %. The back half
  has its own small disc (a seam at the 90-degree ring), so no texel holds two surface
  points.
"""

from __future__ import annotations

import numpy as np

from facewire.models.head.anatomy import (
    CORNEA_BULGE,
    EYE_CENTRE,
    EYE_RADIUS,
    IRIS_ANGLE_DEG,
    MOUTH_Y,
)
from facewire.models.head.primitives import unit
from facewire.models.head.uvlayout import EYE_BACK_UV, EYE_BACK_UV_RADIUS, EYE_UV, EYE_UV_RADIUS

_SOCKET_GAP = 0.35  # socket cup radius minus eyeball radius


def _slerp(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """Spherical interpolation between unit vectors a (N, 3) and b (3,)."""
    angle = np.arccos(np.clip(a @ b, -1.0, 1.0))[:, None]
    return (np.sin((1.0 - t) * angle) * a + np.sin(t * angle) * b) / np.sin(angle)


def eye_socket(margin_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The socket cup behind the eyelid margin loop (L, 3): a narrow roll just inside the
    margin (so the lid edge is rounded), then rings on a sphere just outside the eyeball,
    turning back to a cap behind it.

    Returns the new points (5 L + 1, 3), their ring weights for the UV (0 at the margin,
    1 at the cap), and triangles with the margin as indices 0..L-1 and the new points after."""
    back = np.array([0.0, 0.0, -1.0])
    offset = margin_points - EYE_CENTRE
    omega = unit(offset)
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


def mouth_cavity(lip_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    yc = MOUTH_Y - 2.0
    design = [(-1.2, 21.0, 3.0), (-7.0, 23.0, 8.0), (-15.0, 24.0, 13.0), (-25.0, 22.0, 15.0),
              (-35.0, 17.0, 12.0), (-42.0, 9.0, 7.0)]
    rings = [lip_points]
    for k, (dz, a, b) in enumerate(design):
        ring = np.column_stack([a * np.cos(alpha), yc + b * np.sin(alpha), np.full(n, z0 + dz)])
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
        i = np.arange(n - 1) + k * n  # ring k's vertices, bar the last
        j = i + n  # the same on ring k + 1
        tri += [np.column_stack([i, j + 1, i + 1]), np.column_stack([i, j, j + 1])]
    last = np.arange(n - 1) + (len(rings) - 1) * n
    tri.append(np.column_stack([last, np.full(n - 1, len(points) - 1), last + 1]))
    return points, np.column_stack([radius, angle]), np.concatenate(tri)


_EYE_THETA_DEG = [4.5, 9.0, 15.0, 22.0, IRIS_ANGLE_DEG, 37.0, 45.0, 55.0, 66.0, 78.0, 90.0,
                  105.0, 120.0, 135.0, 150.0, 165.0]
_EYE_LONGITUDES = 24


def eyeball() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
