"""The generic head's free samples: directions on the open half sphere x > 0 (and the midline).

The target edge length on the skin is 1.6 mm at the eyelids, 1.7 mm at the lips, 2.6 mm on
the nose, 4.4 mm on the rest of the face, 3.6 mm on the ears and 10 mm elsewhere (smooth
transitions). It is turned into angles with the local metric of the parameterisation,
``m(d) = max(|dp / d el|, |dp / d az| / cos el)`` in mm per radian (from differences on a
3-degree (az, el) grid of ray casts, clamped to [t / 2, 4 t] for a ray length t): the
Poisson-disk radius is ``rho(d) = h(p(d)) / (1.8 m(d))``, 1.8 being the mean Delaunay edge of
such sets in disk radii.

- Midline: evenly spaced in units of the local spacing, by inverting the integral of
  ``1 / step`` over the angle in the plane x = 0.
- Elsewhere: random candidates (a uniform cover of the half sphere plus a denser one of the
  middle of the face, thinned by rejection to about five per disk), then Poisson-disk
  thinning in a random order.
- All away from the fixed samples, the openings and the Gabriel circles of their boundary
  segments.
- Then Lloyd (centroidal Voronoi) relaxation: each free sample moves to the mean of the
  centroids of its Delaunay triangles, weighted by area / rho^2 (density 1 / rho^2), where the
  move keeps it clear of the midline, the openings and the Gabriel circles.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from facewire.models.head.anatomy import MOUTH_Y
from facewire.models.head.features import FixedSamples
from facewire.models.head.primitives import sstep, unit
from facewire.models.head.rays import az_el, directions_to, from_az_el, ray_origins, raycast
from facewire.models.head.sphere import gabriel_conflicts, in_hole, spherical_delaunay, uniform_cap

_EDGE_PER_RADIUS = 1.8  # mean Delaunay edge length of our Poisson-disk sets, in disk radii
_CANDIDATES_PER_DISK = 5.0


def _spacing(p: np.ndarray) -> np.ndarray:
    """Target edge length (mm) on the skin near the points p (N, 3)."""
    ax, y, z = np.abs(p[:, 0]), p[:, 1], p[:, 2]
    face = sstep(0.0, 35.0, z) * sstep(90.0, 75.0, y) * sstep(-125.0, -112.0, y)
    h = 10.0 - 5.6 * face
    ear = np.hypot(np.hypot((ax - 78.0) / 16.0, (y + 5.0) / 36.0), (z + 24.0) / 26.0)
    h = np.minimum(h, 3.6 + 6.4 * sstep(1.0, 1.5, ear))
    front = z > 45.0  # the feature terms below are for the face only
    eye = np.hypot((ax - 31.25) / 14.25, (y - 0.3) / 4.5)
    h = np.where(front, np.minimum(h, 1.6 + 1.3 * np.maximum(eye - 1.3, 0.0)), h)
    lips = np.hypot(ax / 26.0, (y - MOUTH_Y + 1.5) / 10.0)
    h = np.where(front, np.minimum(h, 1.7 + 2.5 * np.maximum(lips - 0.85, 0.0)), h)
    nose = np.hypot(ax / 18.0, (y + 20.0) / 28.0)
    return np.where(front, np.minimum(h, 2.6 + 2.2 * np.maximum(nose - 0.8, 0.0)), h)


class RayLengths:
    """The skin on a coarse (az, el) grid of the half sphere: ray lengths, and the metric
    m(d) = max(|dp/d el|, |dp/d az| / cos el) in mm per radian (how far a small turn of
    the ray moves its skin point), from differences on the grid, clamped to [t / 2, 4 t]."""

    STEP = np.radians(3.0)

    def __init__(self) -> None:
        self.az = np.linspace(0.0, np.pi, int(round(np.pi / self.STEP)) + 1)
        self.el = np.linspace(-np.pi / 2 + self.STEP / 2, np.pi / 2 - self.STEP / 2,
                              int(round(np.pi / self.STEP)))
        A, E = np.meshgrid(self.az, self.el, indexing="ij")
        d = from_az_el(A.ravel(), E.ravel())
        p = raycast(d).reshape(A.shape + (3,))
        t = np.linalg.norm(p.reshape(-1, 3) - ray_origins(d), axis=1).reshape(A.shape)
        d_az = np.linalg.norm(np.gradient(p, self.az, axis=0), axis=2) / np.cos(E)
        d_el = np.linalg.norm(np.gradient(p, self.el, axis=1), axis=2)
        self.length = t
        self.metric = np.clip(np.maximum(d_az, d_el), 0.5 * t, 4.0 * t)

    def _cell(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Grid cell (ia, ie) of each direction and its position in the cell (wa, we)."""
        az, el = az_el(d)
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
        plus 6 mm (``raycast`` checks it)."""
        ia, ie, _, _ = self._cell(d)
        t = self.length
        return np.maximum.reduce([t[ia, ie], t[ia + 1, ie], t[ia, ie + 1], t[ia + 1, ie + 1]]) + 6.0

    def disk_radius(self, d: np.ndarray) -> np.ndarray:
        """Poisson-disk radius (radians) for directions d: target spacing over the metric."""
        t = self._lookup(self.length, d)
        h = _spacing(ray_origins(d) + d * t[:, None])
        return h / (_EDGE_PER_RADIUS * self._lookup(self.metric, d))


RELAXATIONS = 3


def relax(base: np.ndarray, free: np.ndarray, lengths: RayLengths, holes: list[np.ndarray],
           segments: np.ndarray) -> np.ndarray:
    """One Lloyd step for the free samples: each moves to the density-weighted mean of the
    centroids of its Delaunay triangles (a centroidal Voronoi relaxation with density
    1 / rho^2). A move that would leave the open half sphere, enter an opening or break the
    Gabriel condition of a margin or lip segment is not made."""
    dirs = np.concatenate([base, free])
    tri = spherical_delaunay(dirs)
    tri = tri[~(dirs[tri, 0] == 0.0).all(axis=1)]
    a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
    centroid = unit(a + b + c)
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    weight = area / lengths.disk_radius(centroid) ** 2
    acc = np.zeros_like(dirs)
    total = np.zeros(len(dirs))
    for k in range(3):
        np.add.at(acc, tri[:, k], weight[:, None] * centroid)
        np.add.at(total, tri[:, k], weight)
    moved = unit(acc[len(base):])
    ok = (moved[:, 0] > 0.4 * lengths.disk_radius(moved)) & ~in_hole(moved, holes)
    ok &= ~gabriel_conflicts(moved, segments)
    return np.where(ok[:, None], moved, free)


def midline_samples(lengths: RayLengths, fixed: FixedSamples) -> np.ndarray:
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
    keep &= ~gabriel_conflicts(dirs, fixed.segments())
    return dirs[keep]


def poisson_samples(lengths: RayLengths, fixed: FixedSamples, base: np.ndarray,
                     rng: np.random.Generator) -> np.ndarray:
    """Free directions on the open half sphere: Poisson-disk thinning of random candidates
    (about ``_CANDIDATES_PER_DISK`` per disk, by rejection sampling from a uniform cover of
    the half sphere plus a denser one of the middle of the face), keeping away from the
    ``base`` samples, the midline, the openings and the Gabriel circles."""
    centre_axis = directions_to(np.array([[0.0, -20.0, 100.0]]))[0]
    cos_cap = np.cos(np.radians(42.0))
    A, E = np.meshgrid(lengths.az, lengths.el, indexing="ij")
    grid = from_az_el(A.ravel(), E.ravel())
    wanted = _CANDIDATES_PER_DISK / (np.pi * lengths.disk_radius(grid) ** 2)
    in_cap = grid @ centre_axis >= cos_cap
    n_coarse = int(1.3 * wanted[~in_cap].max() * 2.0 * np.pi)
    cap_area = np.pi * (1.0 - cos_cap)
    n_fine = int(1.3 * max(wanted[in_cap].max() - n_coarse / (2.0 * np.pi), 0.0) * cap_area)
    cand = np.concatenate([uniform_cap(rng, n_coarse, np.array([1.0, 0.0, 0.0]), 0.0),
                           uniform_cap(rng, n_fine, centre_axis, cos_cap)])
    offered = n_coarse / (2.0 * np.pi) + (cand @ centre_axis >= cos_cap) * n_fine / cap_area
    rho = lengths.disk_radius(cand)
    keep = rng.random(len(cand)) * offered < _CANDIDATES_PER_DISK / (np.pi * rho ** 2)
    keep &= cand[:, 0] > 0.4 * rho
    cand, rho = cand[keep], rho[keep]
    ok = ~in_hole(cand, fixed.holes()) & ~gabriel_conflicts(cand, fixed.segments())
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
