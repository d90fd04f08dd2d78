"""Geometry on the unit sphere of ray directions: sampling caps, triangulating, holes.

- uniform samples on a cap ``{d : d . axis >= cos_max}``:
  ``d = w axis + sqrt(1 - w^2) (cos phi e1 + sin phi e2)``, ``w ~ U(cos_max, 1)``,
  ``phi ~ U(0, 2 pi)``;
- the spherical Delaunay triangulation of unit vectors is their convex hull (every sample
  must be a hull vertex), its triangles turned counter-clockwise seen from outside;
- the Gabriel condition of a segment (a, b): no other sample in its diametral circle (centre
  ``(a + b) / |a + b|``, radius ``|a - b| / 2``, here with 5 % to spare). A sampling that keeps
  it has the segment as a Delaunay edge; where one is still missing at a sharp corner, one
  flip of the edge that crosses it recovers it;
- a hole (a closed loop of directions) contains the directions inside it in the gnomonic
  projection about the loop's mean direction c, ``d -> (d . e1, d . e2) / (d . c)``, which maps
  great circles to straight lines (a crossing-number test).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from facewire.models.head.primitives import unit


def uniform_cap(rng: np.random.Generator, n: int, axis: np.ndarray, cos_max: float) -> np.ndarray:
    """n uniform unit vectors within the cap {d : d . axis >= cos_max}, with x >= 0."""
    w = rng.uniform(cos_max, 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    e1 = unit(np.cross(axis, [0.0, 1.0, 0.0]))
    e2 = np.cross(axis, e1)
    r = np.sqrt(1.0 - w * w)
    d = w[:, None] * axis + r[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    d[:, 0] = np.abs(d[:, 0])
    return d


def _gnomonic(d: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Tangent-plane coordinates (N, 2) of directions d around the unit vector centre."""
    e1 = unit(np.cross([0.0, 1.0, 0.0], centre))
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


def in_hole(d: np.ndarray, holes: list[np.ndarray]) -> np.ndarray:
    """Whether directions d (N, 3) fall inside any hole (closed loops of unit directions)."""
    out = np.zeros(len(d), dtype=bool)
    for loop in holes:
        centre = unit(loop.mean(axis=0))
        out |= (d @ centre > 0.9) & _inside_polygon(_gnomonic(d, centre), _gnomonic(loop, centre))
    return out


def gabriel_conflicts(d: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Whether directions d (N, 3) lie in the diametral circle of any segment (S, 2, 3)."""
    mid = unit(segments[:, 0] + segments[:, 1])
    radius = 0.5 * np.linalg.norm(segments[:, 0] - segments[:, 1], axis=1) * 1.05
    bad = np.zeros(len(d), dtype=bool)
    tree = cKDTree(d)
    for m, r in zip(mid, radius):
        bad[tree.query_ball_point(m, r)] = True
    return bad


def spherical_delaunay(dirs: np.ndarray) -> np.ndarray:
    """Triangles (M, 3) of the convex hull of unit vectors, counter-clockwise from outside."""
    hull = ConvexHull(dirs)
    if len(hull.vertices) != len(dirs):
        raise RuntimeError("head: a direction sample is not a hull vertex")
    tri = hull.simplices.astype(np.int64)
    a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) < 0.0
    tri[flip] = tri[flip][:, ::-1]
    return tri


def recover_edges(tri: np.ndarray, wanted: list[tuple[int, int]]) -> np.ndarray:
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
