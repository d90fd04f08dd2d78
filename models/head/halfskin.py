"""The generic head's skin over the half x >= 0, sampled and triangulated.

The samples are the fixed ones (``features``), the midline ones and the relaxed free ones
(``sampling``; seeded, so the mesh is deterministic). Their spherical Delaunay triangulation
(``sphere``) without the flat lid on the midline is the half's; no free sample lies in the
circle on any margin or lip-line segment, so these segments are mesh edges (one flip recovers
one still missing at a sharp corner), and the openings are cut out exactly by dropping the
triangles inside them. The vertices are the skin points of the directions (``rays``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facewire.models.head.anatomy import LIP_STEPS
from facewire.models.head.features import fixed_samples
from facewire.models.head.primitives import unit
from facewire.models.head.rays import raycast
from facewire.models.head.sampling import (
    RELAXATIONS,
    RayLengths,
    midline_samples,
    poisson_samples,
    relax,
)
from facewire.models.head.sphere import in_hole, recover_edges, spherical_delaunay


@dataclass(frozen=True)
class HalfSkin:
    """The skin over the half sphere x >= 0 (directions, points, triangles) and its features."""

    dirs: np.ndarray        # (N, 3) unit ray directions
    points: np.ndarray      # (N, 3) skin points, mm
    triangles: np.ndarray   # (M, 3) counter-clockwise from outside
    midline: np.ndarray     # (N,) bool, x == 0
    margin: np.ndarray      # (2 * LID_STEPS,) vertex loop of the left eye opening
    lip_upper: np.ndarray   # (LIP_STEPS + 1,) vertices from 62 to the corner 64
    lip_lower: np.ndarray   # (LIP_STEPS,) vertices after the corner, down to 66
    named: dict[int | str, int]  # landmark index or phantom name -> vertex


def half_skin() -> HalfSkin:
    """The triangulated skin of the half x >= 0 (module docstring); deterministic."""
    lengths = RayLengths()
    fixed = fixed_samples()
    base = np.concatenate([fixed.dirs, midline_samples(lengths, fixed)])
    free = poisson_samples(lengths, fixed, base, np.random.default_rng(20240611))
    holes, segments = fixed.holes(), fixed.segments()
    for _ in range(RELAXATIONS):
        free = relax(base, free, lengths, holes, segments)
    dirs = np.concatenate([base, free])
    midline = dirs[:, 0] == 0.0
    if np.any(dirs[:, 0] < 0.0) or np.any(dirs[~midline, 0] < 1e-4):
        raise RuntimeError("head: a direction sample is on the wrong side of the midline")

    tri = spherical_delaunay(dirs)
    tri = tri[~midline[tri].all(axis=1)]  # the flat lid of the half sphere's hull
    loop_edges = (list(zip(fixed.margin, np.roll(fixed.margin, -1)))
                  + list(zip(fixed.lip[:-1], fixed.lip[1:])))
    tri = recover_edges(tri, loop_edges)
    tri = tri[~in_hole(unit(dirs[tri].sum(axis=1)), holes)]
    edges = {tuple(e) for t in tri for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    for i, j in loop_edges:
        if (i, j) not in edges and (j, i) not in edges:
            raise RuntimeError(f"head: the margin or lip-line segment {i}-{j} is not a mesh edge")
    points = raycast(dirs, start=lengths.start(dirs))
    return HalfSkin(dirs, points, tri, midline, fixed.margin, fixed.lip[:LIP_STEPS + 1],
                     fixed.lip[LIP_STEPS + 1:], fixed.named)
