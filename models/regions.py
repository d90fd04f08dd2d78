"""Texture regions: where on the face appearance is classified and replaced by layers.

Wrinkles, blinks, gaze and the inside of the mouth cannot be tracked as points, so the
paper classifies them: each region has k appearance states (the layers of a 3D texture on
the receiver) and k classification templates, and the packet carries one continuous value
Q in [0, k-1] per region. This module says where the regions are; ``sender.enroll`` fills
them from a video, ``sender.appearance`` samples them, ``sender.classify`` classifies.

The regions, in packet order (``REGIONS``; left and right are the person's own):

==============  ===================  =======================================  ============
region          surface              template area, generic head, mm (x, y)   axis (Q up)
==============  ===================  =======================================  ============
forehead        skin                 [-30, 30] x [30, 55]                     brows raised
brow_furrow     skin                 [-13, 13] x [4, 28]                      brows drawn
eyelid_left     left eyeball         [24, 39] x [-5, 7]                       eye closed
                (+ skin: the lids)   ([15, 48] x [-8, 12])
eyelid_right    right eyeball        [-39, -24] x [-5, 7]                     eye closed
                (+ skin: the lids)   ([-48, -15] x [-8, 12])
eyeball_left    left eyeball         [23, 40] x [-3, 4]                       gaze to +x
eyeball_right   right eyeball        [-40, -23] x [-3, 4]                     gaze to +x
mouth           mouth interior       [-16, 16] x [-72, -59]                   mouth open
==============  ===================  =======================================  ============

Each area is a box seen from the front (the model's +z) on the generic head, and only the
region's own surface counts: a ray along -z through (x, y) is cast onto the region's
triangles that face the front (+z) and its first hit is the surface point. So the eye
regions lie on the eyeball seen through the lid opening (a closed lid hides that part of
the eyeball in the camera image, which is what the eyelid classifier sees; the eyelid
boxes reach a little under the lids, so their top and bottom rows read lid skin on an open
eye too), and the mouth region lies on the back wall of the mouth's interior, seen between
the lips (the teeth and tongue of an open mouth; a closed mouth shows its lips there to
the templates, while its layers show the interior, ``sender.enroll.interior``). The back
wall is some 40 mm behind the lips, so a turned head moves the mouth's samples against
the lips (about 12 mm at 15 degrees of yaw): the mouth classifier is the most
pose-dependent one. The eyelid and eyeball regions share the eyeball's texture: the
eyeball region (gaze) is drawn first, the eyelid region over it, and the eyelid's open
states (up to its rest state) are transparent (``opacity`` 0), so the gaze shows through an
open lid and a closing lid covers it.

Further areas. A region's states may cover more of the face than its own surface: the
eyelids' states also cover the skin of both lids around the opening (``areas``; the boxes in
brackets above). A closing eye changes the lid skin as much as what the opening shows (the
lash lines meet, the crease flattens), and the mesh's lids do not move (the packet drives
no lid point), so without the skin area a closed eye kept the open eye's lash lines around
a closed-lid patch: a dark ring. A further area has the region's layers, opacities and Q; it
is found like the layer area (a front box, grown by ``LAYER_MARGIN_MM``, its UV rectangle)
and never classified.

UV rectangles. The UVs of the hits on a 33 x 33 grid over a box give its UV rectangle
(their bounding box). ``template_rect`` is that of the template area; ``uv_rect``, the
area the layer images cover, is the template area grown by the region's ``layer_margin``
(``LAYER_MARGIN_MM``; ``EYE_LAYER_MARGIN_MM`` for the eye regions, so that their layers
cover all of the eyeball the lid opening can show, not only the template area: a closed
lid's layer must hide the whole opening) on every side, plus ``RAMP_TEXELS`` + 2 texels,
snapped outward to texel edges of the model's texture (``models.texelgrid.texel_rect``), so
that a layer's pixels are the texture's own texels. The UV layout is the generic head's for
every model (fitting moves vertices, never UVs), so the rectangles are computed once, on the
generic head.

The alpha ramp (``ramp_mask``): a layer's alpha over the neutral texture is 1 inside and
falls linearly to 0 over the ``RAMP_TEXELS`` = 10 texels next to the rectangle's border:
alpha = clip(d / RAMP_TEXELS, 0, 1) with d the distance in texels from a texel's centre to
the rectangle's edge, minus 1/2 (so the outermost texel has alpha 0).

Template samples (``template_points``, ``locate``). A template is TEMPLATE_SIZE x
TEMPLATE_SIZE (16 x 16) grey values; each value is the mean of SUPERSAMPLE x SUPERSAMPLE
point samples spread evenly over its cell of ``template_rect`` (an area mean, so a fine
wrinkle or eyelash does not alias). Five samples are taken per frame: the template grid and
the grid moved diagonally by one template cell, ``OFFSETS`` = (0, 0), (+1, +1), (-1, +1),
(+1, -1), (-1, -1) cells (u, v); the best-scoring one wins (the paper's robustness to small
misplacement). Every point is stored as its triangle and barycentric weights (a, b, c),
found in UV: the point lies in exactly one triangle of the (one-to-one) UV layout, and
P = a V_i + b V_j + c V_k gives its position on the mesh however the mesh is morphed.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from facewire.models.fields import TEMPLATE_SIZE
from facewire.models.head import generic_head
from facewire.models.mesh import Tag
from facewire.models.texelgrid import texel_rect
from facewire.protocol.errors import FacewireError

SUPERSAMPLE = 2
OFFSETS = np.array([(0, 0), (1, 1), (-1, 1), (1, -1), (-1, -1)], np.float64)  # cells (u, v)
RAMP_TEXELS = 10
LAYER_MARGIN_MM = 3.0
EYE_LAYER_MARGIN_MM = 10.0
_GRID = 33  # hits per side of a box when measuring its UV rectangle


class RegionError(FacewireError, ValueError):
    """A region cannot be placed on a mesh; the message names the region."""


@dataclass(frozen=True)
class RegionSpec:
    """One region of ``REGIONS`` (module docstring).

    Attributes:
        name: the region's name, as in models and packets.
        tag: the surface it lies on.
        box: (x0, x1, y0, y1) its template area seen from the front, generic head, mm.
        layers: how many appearance states enrollment gives it.
        axis: what grows with Q, for people.
        transparent_open: its states up to the rest state are transparent (the eyelids' open
            states: the gaze layers under them show).
        layer_margin: how far, mm, the layer area reaches beyond the template area.
        areas: further layer areas, (surface, front box) each (module docstring).
    """

    name: str
    tag: Tag
    box: tuple[float, float, float, float]
    layers: int
    axis: str
    transparent_open: bool = False
    layer_margin: float = LAYER_MARGIN_MM
    areas: tuple[tuple[Tag, tuple[float, float, float, float]], ...] = ()


LEFT_LIDS = (Tag.SKIN, (15.0, 48.0, -8.0, 12.0))
RIGHT_LIDS = (Tag.SKIN, (-48.0, -15.0, -8.0, 12.0))
REGIONS = (
    RegionSpec("forehead", Tag.SKIN, (-30.0, 30.0, 30.0, 55.0), 4, "brows raised"),
    RegionSpec("brow_furrow", Tag.SKIN, (-13.0, 13.0, 4.0, 28.0), 3, "brows drawn together"),
    RegionSpec("eyelid_left", Tag.LEFT_EYEBALL, (24.0, 39.0, -5.0, 7.0), 4, "eye closed",
               transparent_open=True, layer_margin=EYE_LAYER_MARGIN_MM, areas=(LEFT_LIDS,)),
    RegionSpec("eyelid_right", Tag.RIGHT_EYEBALL, (-39.0, -24.0, -5.0, 7.0), 4, "eye closed",
               transparent_open=True, layer_margin=EYE_LAYER_MARGIN_MM, areas=(RIGHT_LIDS,)),
    RegionSpec("eyeball_left", Tag.LEFT_EYEBALL, (23.0, 40.0, -3.0, 4.0), 5,
               "gaze toward the person's left (image right)", layer_margin=EYE_LAYER_MARGIN_MM),
    RegionSpec("eyeball_right", Tag.RIGHT_EYEBALL, (-40.0, -23.0, -3.0, 4.0), 5,
               "gaze toward the person's left (image right)", layer_margin=EYE_LAYER_MARGIN_MM),
    RegionSpec("mouth", Tag.MOUTH_INTERIOR, (-16.0, 16.0, -72.0, -59.0), 4, "mouth open"),
)
REGION_NAMES = tuple(r.name for r in REGIONS)


def spec(name: str) -> RegionSpec:
    """The ``REGIONS`` entry called ``name``.

    Raises:
        RegionError: no such region.
    """
    for r in REGIONS:
        if r.name == name:
            return r
    raise RegionError(f"region {name!r}: unknown (known: {', '.join(REGION_NAMES)})")


@dataclass(frozen=True)
class Placement:
    """Where a region lies in UV (module docstring).

    Attributes:
        template_rect: (u0, v0, u1, v1) the template area, UV, v up.
        uv_rect: (u0, v0, u1, v1) the layer area, snapped to texel edges of the texture.
        areas: the further areas' rectangles, snapped like ``uv_rect``.
    """

    template_rect: tuple[float, float, float, float]
    uv_rect: tuple[float, float, float, float]
    areas: tuple[tuple[float, float, float, float], ...] = ()


def place(region: RegionSpec, texture_shape: tuple[int, int]) -> Placement:
    """The UV rectangles of a region on the generic head (module docstring).

    Args:
        region: the region.
        texture_shape: (H, W) of the model's texture, texels.

    Returns:
        Its template, layer and further areas' rectangles.
    """
    template = _box_uv_rect(region.tag, region.box)
    areas = tuple(_layer_rect(tag, box, LAYER_MARGIN_MM, texture_shape)
                  for tag, box in region.areas)
    return Placement(template, _layer_rect(region.tag, region.box, region.layer_margin,
                                           texture_shape, template), areas)


def _layer_rect(tag: Tag, box: tuple[float, float, float, float], margin: float,
                texture_shape: tuple[int, int],
                inside: tuple[float, float, float, float] | None = None
                ) -> tuple[float, float, float, float]:
    """The UV rectangle of a front box grown by ``margin`` mm (and holding ``inside``), plus
    the ramp and 2 texels, snapped outward to texels (module docstring)."""
    h, w = texture_shape
    x0, x1, y0, y1 = box
    outer = _box_uv_rect(tag, (x0 - margin, x1 + margin, y0 - margin, y1 + margin))
    if inside is not None:
        outer = (min(outer[0], inside[0]), min(outer[1], inside[1]),
                 max(outer[2], inside[2]), max(outer[3], inside[3]))
    pad_u, pad_v = (RAMP_TEXELS + 2) / w, (RAMP_TEXELS + 2) / h
    grown = (outer[0] - pad_u, outer[1] - pad_v, outer[2] + pad_u, outer[3] + pad_v)
    return texel_rect(grown, texture_shape)[0]


def ramp_mask(shape: tuple[int, int], ramp: int = RAMP_TEXELS) -> np.ndarray:
    """The alpha of a layer over the neutral texture (module docstring).

    Args:
        shape: (h, w) of the layer, texels.
        ramp: width of the linear ramp, texels.

    Returns:
        (h, w) float32 alpha in [0, 1]: 0 at the outermost texels, 1 from ``ramp`` + 1/2
        texels inside the border on.
    """
    h, w = shape
    dr = np.minimum(np.arange(h) + 0.5, h - np.arange(h) - 0.5) - 0.5
    dc = np.minimum(np.arange(w) + 0.5, w - np.arange(w) - 0.5) - 0.5
    d = np.minimum(dr[:, None], dc[None, :])
    return np.clip(d / ramp, 0.0, 1.0).astype(np.float32)


def template_samples(region: RegionSpec) -> tuple[np.ndarray, np.ndarray]:
    """The triangles and barycentric weights of a region's five offset sample grids.

    Every model shares the generic head's topology, so these hold on every model's mesh.

    Args:
        region: the region.

    Returns:
        (5, S, S) int64 triangle indices and (5, S, S, 3) float32 barycentric weights,
        S = TEMPLATE_SIZE * SUPERSAMPLE; index [o, i, j] is offset o's point in row i from
        the top (y falling) and column j from the person's right (x rising).
    """
    tri, bary = _front_hits(region.tag, region.box, TEMPLATE_SIZE * SUPERSAMPLE, True)
    return tri, bary


def _barycentric(corners: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(K, 3, 2) triangles, (..., 2) points -> (..., K, 3) weights (degenerate triangle: -1)."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    v0, v1 = b - a, c - a
    v2 = np.asarray(p)[..., None, :] - a
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    ok = np.abs(det) > 1e-15
    det = np.where(ok, det, 1.0)
    s = (v2[..., 0] * v1[:, 1] - v2[..., 1] * v1[:, 0]) / det
    t = (v0[:, 0] * v2[..., 1] - v0[:, 1] * v2[..., 0]) / det
    out = np.stack([1.0 - s - t, s, t], axis=-1)
    out[..., ~ok, :] = -1.0
    return out


@cache
def _front_hits(tag: Tag, box: tuple[float, float, float, float], n: int, offsets: bool
                ) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays along -z through an n x n grid of cell centres over ``box`` (and, with
    ``offsets``, the grids moved by ``OFFSETS`` cells, 1/SUPERSAMPLE of the grid's cells
    being one template cell) onto the generic head's ``tag`` triangles; the front-most hit.

    Returns:
        (G, n, n) int64 triangles and (G, n, n, 3) float32 barycentric weights, G = 5 with
        offsets, else 1; rows from the top (y falling).

        Without offsets a ray that misses has triangle -1.

    Raises:
        RegionError: with offsets, a ray misses the surface.
    """
    mesh = generic_head()
    x0, x1, y0, y1 = box
    s = (np.arange(n) + 0.5) / n
    cell = np.array([(x1 - x0), (y1 - y0)]) / (n / SUPERSAMPLE if offsets else n)
    shifts = OFFSETS * cell if offsets else np.zeros((1, 2))
    x, y = np.meshgrid(x0 + s * (x1 - x0), y1 - s * (y1 - y0), indexing="xy")
    points = np.stack([x, y], axis=-1)[None] + shifts[:, None, None, :]
    flat = points.reshape(-1, 2)
    all_corners = mesh.vertices[mesh.triangles].astype(np.float64)
    lo, hi = all_corners[:, :, :2].min(axis=1), all_corners[:, :, :2].max(axis=1)
    near = np.all((lo <= flat.max(axis=0)) & (hi >= flat.min(axis=0)), axis=1)
    e1, e2 = all_corners[:, 1] - all_corners[:, 0], all_corners[:, 2] - all_corners[:, 0]
    facing = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0  # seen from +z (first hits only)
    tris = np.flatnonzero((mesh.tags == tag) & near & facing)
    corners = all_corners[tris]
    tri = np.full(len(flat), -1, np.int64)
    bary = np.zeros((len(flat), 3))
    for start in range(0, len(flat), 256):
        b = _barycentric(corners[:, :, :2], flat[start:start + 256])  # (P, K, 3)
        inside = np.all(b >= -1e-9, axis=2)
        z = np.where(inside, np.einsum("pkj,kj->pk", b, corners[:, :, 2]), -np.inf)
        front = np.argmax(z, axis=1)
        rows = np.flatnonzero(inside.any(axis=1))
        tri[start + rows] = tris[front[rows]]
        bary[start + rows] = b[rows, front[rows]]
    if offsets and (tri < 0).any():
        raise RegionError(f"box {box} on {tag.name}: {int((tri < 0).sum())} of {len(tri)} "
                          f"rays from the front miss the surface")
    bary = np.clip(bary, 0.0, None)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-12)
    shape = points.shape[:-1]
    return tri.reshape(shape), bary.astype(np.float32).reshape(*shape, 3)


def _box_uv_rect(tag: Tag, box: tuple[float, float, float, float]
                 ) -> tuple[float, float, float, float]:
    """The UV bounding box of a front box's surface hits on the generic head."""
    tri, bary = _front_hits(tag, box, _GRID, False)
    hit = tri >= 0
    uv = generic_head().uv.astype(np.float64)[generic_head().triangles[tri[hit]]]
    hits = np.einsum("kj,kjc->kc", bary[hit], uv)
    lo, hi = hits.min(axis=0), hits.max(axis=0)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
