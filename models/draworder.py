"""The order a model's triangles are drawn in: grouped by the region areas they meet.

The receiver (``receiver.render``) draws each group of triangles with a program that
composites only the region areas the group meets (on a CPU rasterizer every fragment pays
for every region its shader samples), so it draws the triangles group by group, not in the
mesh's order. Where two surfaces meet at equal depth (the lid margins, the eye sockets and
the eyeballs at the corners of the eyes), the one drawn first wins the depth test, so the
order decides a few pixels. The model's preview (``sender.enroll.build.render_preview``) draws its
triangles in this same order, so a face at rest renders pixel-identical on both.

Areas. Each region's ``parts()`` (its main area, then its further ones), the regions in
``draw_order``: opaque regions first, then those with a transparent state, each set in the
model's (packet) order, so the eyeballs' gaze goes first and the eyelids over it.

Padded rectangles. The receiver stores an area's k layers of h x w texels padded with
``PAD`` = 2^``MIP_LEVELS`` transparent texels on every side (more on the right and at the
bottom, to sizes that are multiples of ``PAD``: ``padded``), so that every mip level halves
exactly and the outermost texels stay transparent at every level; ``padded_rect`` is the UV
rectangle of that padded image.

Groups. A triangle meets an area when its UV bounding box meets the area's padded
rectangle (its fragments' UVs lie in that box). Triangles with the same set of areas (a bit
mask) form a group; the groups are sorted by mask and keep the mesh's order within each.
"""

from __future__ import annotations

import numpy as np

from facewire.models.modelfile import Area, Region

MIP_LEVELS = 4  # mip levels below full resolution: regions stay smooth down to 1/16 scale
PAD = 1 << MIP_LEVELS  # transparent texels around each area's layers (at least)
MAX_AREAS = 62  # areas a group's bit mask can hold


def draw_order(regions: tuple[Region, ...]) -> list[int]:
    """The order regions are composited in (module docstring): opaque ones first.

    Args:
        regions: the model's regions, packet order.

    Returns:
        Indices into ``regions``.
    """
    opaque = [i for i, r in enumerate(regions) if min(r.opacity) >= 1.0]
    return opaque + [i for i in range(len(regions)) if i not in opaque]


def region_areas(regions: tuple[Region, ...]) -> list[tuple[int, Area]]:
    """Every area of every region, in drawing order: (region index, area) pairs."""
    return [(i, part) for i in draw_order(regions) for part in regions[i].parts()]


def padded(n: int) -> int:
    """The smallest multiple of PAD that holds n texels and PAD more on either side."""
    return -(-(n + 2 * PAD) // PAD) * PAD


def padded_rect(area: Area) -> tuple[float, float, float, float]:
    """The UV rectangle (u0, v0, u1, v1) of an area's padded layers (module docstring)."""
    h, w = area.layers.shape[1:3]
    u0, v0, u1, v1 = area.uv_rect
    du, dv = (u1 - u0) / w, (v1 - v0) / h
    return (u0 - PAD * du, v1 - (padded(h) - PAD) * dv, u0 + (padded(w) - PAD) * du,
            v1 + PAD * dv)


def triangle_groups(uv: np.ndarray, triangles: np.ndarray, areas: list[tuple[int, Area]]
                    ) -> tuple[np.ndarray, list[tuple[int, int, int]],
                               list[tuple[float, float, float, float]]]:
    """Triangles grouped by the areas their UV footprint meets (module docstring).

    Args:
        uv: (N, 2) texture coordinates.
        triangles: (M, 3) vertex indices.
        areas: ``region_areas`` of the model, at most ``MAX_AREAS``.

    Returns:
        (M, 3) int32 triangles sorted by group (stable, so each group keeps the mesh's
        order); per group (bit mask of its areas, first triangle, triangle count); and the
        areas' padded rectangles.

    Raises:
        ValueError: more than ``MAX_AREAS`` areas.
    """
    if len(areas) > MAX_AREAS:
        raise ValueError(f"areas: {len(areas)} region areas, at most {MAX_AREAS}")
    rects = [padded_rect(area) for _, area in areas]
    corners = uv[triangles]
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    masks = np.zeros(len(triangles), np.int64)
    for i, (u0, v0, u1, v1) in enumerate(rects):
        meets = (hi[:, 0] >= u0) & (lo[:, 0] <= u1) & (hi[:, 1] >= v0) & (lo[:, 1] <= v1)
        masks |= meets.astype(np.int64) << i
    order = np.argsort(masks, kind="stable")
    kinds, first, count = np.unique(masks[order], return_index=True, return_counts=True)
    groups = [(int(m), int(f), int(n)) for m, f, n in zip(kinds, first, count)]
    return np.ascontiguousarray(triangles[order], np.int32), groups, rects
