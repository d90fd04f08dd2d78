"""Texture regions: the alpha ramp, texel snapping, where each region lies in UV and the
template sample grids cast from the front onto the generic head.

The grids are checked against points computed here from the regions' boxes and a ray test
of our own (point in triangle, seen along -z), not against ``models.regions`` internals.
"""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.head import generic_head
from facewire.models.head.uvlayout import (
    EYE_UV,
    EYE_UV_RADIUS,
    MOUTH_UV,
    MOUTH_UV_RADIUS,
    SKIN_U_MAX,
)
from facewire.models.mesh import Mesh, Tag
from facewire.models.regions import (
    OFFSETS,
    RAMP_TEXELS,
    REGION_NAMES,
    REGIONS,
    SUPERSAMPLE,
    TEMPLATE_SIZE,
    RegionError,
    RegionSpec,
    place,
    ramp_mask,
    spec,
    template_samples,
)
from facewire.models.texelgrid import texel_rect

MODEL_TEXTURE = (1024, 2048)  # (H, W) the model's texture
S = TEMPLATE_SIZE * SUPERSAMPLE
EYES = {"eyelid_left": "left", "eyeball_left": "left", "eyelid_right": "right",
        "eyeball_right": "right"}


# ---------------------------------------------------------------------------------------
# ramp_mask


def test_ramp_mask_rises_by_a_tenth_per_texel_from_zero_at_the_border() -> None:
    h, w = 31, 44
    alpha = ramp_mask((h, w))
    assert alpha.shape == (h, w) and alpha.dtype == np.float32
    assert RAMP_TEXELS == 10
    rising = np.arange(11) / 10.0  # texels 0 .. 10 from the border: 0, 0.1, .., 1
    middle_row, middle_col = alpha[h // 2], alpha[:, w // 2]
    np.testing.assert_allclose(middle_row[:11], rising, atol=1e-7)
    np.testing.assert_allclose(middle_row[::-1][:11], rising, atol=1e-7)
    np.testing.assert_allclose(middle_col[:11], rising, atol=1e-7)
    np.testing.assert_allclose(middle_col[::-1][:11], rising, atol=1e-7)
    assert (alpha[10:h - 10, 10:w - 10] == 1).all()
    # corners: the smaller of the distances to the two edges
    assert alpha[3, 7] == pytest.approx(0.3) and alpha[7, 3] == pytest.approx(0.3)
    assert alpha[h - 1 - 2, w - 1 - 6] == pytest.approx(0.2)
    assert alpha[0, 0] == alpha[0, w - 1] == alpha[h - 1, 0] == alpha[h - 1, w - 1] == 0
    rows, cols = np.indices((h, w))
    d = np.minimum.reduce([rows, h - 1 - rows, cols, w - 1 - cols])
    np.testing.assert_allclose(alpha, np.minimum(d / 10.0, 1.0), atol=1e-7)


def test_ramp_mask_with_another_ramp_and_a_layer_too_small_to_reach_one() -> None:
    alpha = ramp_mask((12, 9), ramp=4)
    np.testing.assert_allclose(alpha[6], [0, 0.25, 0.5, 0.75, 1, 0.75, 0.5, 0.25, 0], atol=1e-7)
    small = ramp_mask((5, 30))
    np.testing.assert_allclose(small[:, 15], [0, 0.1, 0.2, 0.1, 0], atol=1e-7)
    assert small.max() == pytest.approx(0.2)


# ---------------------------------------------------------------------------------------
# texel_rect


def _covered_texels(rect: tuple[float, float, float, float], shape: tuple[int, int]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the texel rows and columns whose squares overlap the rectangle (v up,
    row r spanning v in [1 - (r+1)/H, 1 - r/H])."""
    h, w = shape
    u0, v0, u1, v1 = rect
    c, r = np.arange(w), np.arange(h)
    cols = (c / w < u1) & ((c + 1) / w > u0)
    rows = (1 - (r + 1) / h < v1) & (1 - r / h > v0)
    return np.flatnonzero(rows), np.flatnonzero(cols)


@pytest.mark.parametrize("shape", [(64, 128), MODEL_TEXTURE, (37, 23)])
def test_texel_rect_snaps_outward_to_texel_edges(shape: tuple[int, int]) -> None:
    h, w = shape
    rng = np.random.default_rng(3)
    for _ in range(200):
        a, b = np.sort(rng.uniform(-0.2, 1.2, 2)), np.sort(rng.uniform(-0.2, 1.2, 2))
        rect = (a[0], b[0], a[1], b[1])
        inside = (max(rect[0], 0), max(rect[1], 0), min(rect[2], 1), min(rect[3], 1))
        if inside[0] >= inside[2] or inside[1] >= inside[3]:
            continue
        snapped, (rows, cols) = texel_rect(rect, shape)
        u0, v0, u1, v1 = snapped
        # clipped to [0, 1], contains the (clipped) input, by less than a texel per side
        assert 0 <= u0 and u1 <= 1 and 0 <= v0 and v1 <= 1
        assert u0 <= inside[0] < u0 + 1 / w and u1 - 1 / w < inside[2] <= u1
        assert v0 <= inside[1] < v0 + 1 / h and v1 - 1 / h < inside[3] <= v1
        # on texel edges
        for value, n in ((u0, w), (u1, w), (v0, h), (v1, h)):
            assert abs(value * n - round(value * n)) < 1e-9
        # the slices are exactly the texels the rectangle covers, row 0 at the top (v = v1)
        covered_rows, covered_cols = _covered_texels(rect, shape)
        np.testing.assert_array_equal(np.arange(h)[rows], covered_rows)
        np.testing.assert_array_equal(np.arange(w)[cols], covered_cols)
        assert rows.start == round((1 - v1) * h) and cols.start == round(u0 * w)


def test_texel_rect_keeps_an_aligned_rectangle_and_clips_to_the_texture() -> None:
    shape = (64, 128)
    aligned = (3 / 128, 1 - 10 / 64, 9 / 128, 1 - 2 / 64)
    snapped, (rows, cols) = texel_rect(aligned, shape)
    np.testing.assert_allclose(snapped, aligned, atol=1e-12)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (2, 10, 3, 9)
    snapped, (rows, cols) = texel_rect((-0.3, -0.1, 1.2, 1.5), shape)
    assert snapped == (0.0, 0.0, 1.0, 1.0)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (0, 64, 0, 128)
    # a rectangle at the top edge starts at row 0
    snapped, (rows, _) = texel_rect((0.5, 0.99, 0.6, 1.0), shape)
    assert rows.start == 0 and rows.stop == 1 and snapped[3] == 1.0


# ---------------------------------------------------------------------------------------
# place


def _inside_disc(u: np.ndarray, v: np.ndarray, centre: tuple[float, float], radius: float
                 ) -> np.ndarray:
    """The UV discs of the eyeballs and mouth: radius in u, twice that in v."""
    return ((u - centre[0]) / radius) ** 2 + ((v - centre[1]) / (2 * radius)) ** 2 <= 1


def _corners(rect: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    u0, v0, u1, v1 = rect
    return np.array([u0, u1, u0, u1]), np.array([v0, v0, v1, v1])


@pytest.mark.parametrize("region", REGIONS, ids=REGION_NAMES)
def test_place_puts_the_template_inside_the_snapped_layer_rect(region: RegionSpec) -> None:
    h, w = MODEL_TEXTURE
    placement = place(region, MODEL_TEXTURE)
    t, r = placement.template_rect, placement.uv_rect
    for rect in (t, r):
        assert all(0 <= x <= 1 for x in rect) and rect[0] < rect[2] and rect[1] < rect[3]
    # the layer rect holds the template area plus the ramp and 2 texels on every side
    margin_u, margin_v = (RAMP_TEXELS + 2) / w, (RAMP_TEXELS + 2) / h
    assert r[0] <= t[0] - margin_u + 1e-12 and t[2] + margin_u - 1e-12 <= r[2]
    assert r[1] <= t[1] - margin_v + 1e-12 and t[3] + margin_v - 1e-12 <= r[3]
    for value, n in zip(r, (w, h, w, h), strict=True):
        assert abs(value * n - round(value * n)) < 1e-9
    assert texel_rect(r, MODEL_TEXTURE)[0] == pytest.approx(r, abs=1e-12)
    # the template rect depends on the layout only, not on the texture's size
    assert place(region, (512, 1024)).template_rect == pytest.approx(t, abs=1e-12)


@pytest.mark.parametrize("region", REGIONS, ids=REGION_NAMES)
def test_template_rect_bounds_the_uv_of_the_template_samples(region: RegionSpec) -> None:
    mesh = generic_head()
    triangles, bary = template_samples(region)
    uv = np.einsum("...k,...kc->...c", bary[0].astype(np.float64),
                   mesh.uv.astype(np.float64)[mesh.triangles[triangles[0]]]).reshape(-1, 2)
    u0, v0, u1, v1 = place(region, MODEL_TEXTURE).template_rect
    assert (uv[:, 0] >= u0 - 1e-6).all() and (uv[:, 0] <= u1 + 1e-6).all()
    assert (uv[:, 1] >= v0 - 1e-6).all() and (uv[:, 1] <= v1 + 1e-6).all()
    # and is their extent, up to the one-sample difference between the two grids
    assert np.ptp(uv[:, 0]) > 0.9 * (u1 - u0) and np.ptp(uv[:, 1]) > 0.9 * (v1 - v0)
    # u grows with x and v with y (columns to the person's left, rows from the top)
    grid = uv.reshape(S, S, 2)
    assert (np.diff(grid[:, :, 0].mean(axis=0)) > 0).all()
    assert (np.diff(grid[:, :, 1].mean(axis=1)) < 0).all()


def test_regions_lie_on_their_own_surfaces_in_uv() -> None:
    rects = {r.name: place(r, MODEL_TEXTURE) for r in REGIONS}
    for region in REGIONS:
        t, r = rects[region.name].template_rect, rects[region.name].uv_rect
        if region.tag == Tag.SKIN:
            assert r[2] <= SKIN_U_MAX, region.name
        elif region.name in EYES:
            # on its eyeball's disc (u > 0.8): the template's corners inside it, the layer
            # centred in it and clear of the other eye's disc
            side = EYES[region.name]
            centre, other = EYE_UV[side], EYE_UV["right" if side == "left" else "left"]
            assert r[0] > SKIN_U_MAX, region.name
            assert _inside_disc(*_corners(t), centre, EYE_UV_RADIUS).all(), region.name
            assert _inside_disc(np.array([(r[0] + r[2]) / 2]), np.array([(r[1] + r[3]) / 2]),
                                centre, EYE_UV_RADIUS).all()
            assert r[0] > other[0] + EYE_UV_RADIUS or r[2] < other[0] - EYE_UV_RADIUS
        else:
            assert region.tag == Tag.MOUTH_INTERIOR
            assert _inside_disc(*_corners(t), MOUTH_UV, MOUTH_UV_RADIUS).all()
            assert _inside_disc(*_corners(r), MOUTH_UV, MOUTH_UV_RADIUS).all()
    for part in ("eyelid", "eyeball"):
        left, right = rects[f"{part}_left"], rects[f"{part}_right"]
        assert left.template_rect[0] > right.template_rect[2]
        assert left.uv_rect[0] >= right.uv_rect[2]
    # a region's layer never reaches into a surface of another kind
    skin = [rects[r.name].uv_rect for r in REGIONS if r.tag == Tag.SKIN]
    others = [rects[r.name].uv_rect for r in REGIONS if r.tag != Tag.SKIN]
    assert max(r[2] for r in skin) < min(r[0] for r in others)


def test_eyelids_also_cover_the_lid_skin_around_their_eye() -> None:
    """The eyelid's further area holds the UVs of its eye's lid landmarks (on the skin map,
    clear of the brows), and not those of the other eye."""
    mesh = generic_head()
    lids = {"left": [42, 43, 44, 45, 46, 47], "right": [36, 37, 38, 39, 40, 41]}
    for side in ("left", "right"):
        region = next(r for r in REGIONS if r.name == f"eyelid_{side}")
        (area,) = place(region, MODEL_TEXTURE).areas
        assert [tag for tag, _ in region.areas] == [Tag.SKIN] and area[2] <= SKIN_U_MAX
        for name, indices in lids.items():
            uv = mesh.uv[mesh.landmarks[indices]]
            inside = ((uv[:, 0] > area[0]) & (uv[:, 0] < area[2]) & (uv[:, 1] > area[1])
                      & (uv[:, 1] < area[3]))
            assert inside.all() if name == side else not inside.any(), (side, name)
        brows = mesh.uv[mesh.landmarks[23:26] if side == "left" else mesh.landmarks[18:21]]
        assert (brows[:, 1] > area[3]).all()
    assert all(not place(r, MODEL_TEXTURE).areas for r in REGIONS if "eyelid" not in r.name)


# ---------------------------------------------------------------------------------------
# template_samples


def _expected_grids(region: RegionSpec) -> np.ndarray:
    """(5, S, S, 2) the (x, y) each sample point is cast from: template cell (I, J) of the
    centre grid is [x0 + J cx, x0 + (J+1) cx] x [y1 - (I+1) cy, y1 - I cy] (cx, cy = the box's
    size / 16), its SUPERSAMPLE^2 points evenly inside it; offset o moves the grid by
    OFFSETS[o] cells."""
    x0, x1, y0, y1 = region.box
    cell = np.array([(x1 - x0) / TEMPLATE_SIZE, (y1 - y0) / TEMPLATE_SIZE])
    index = np.arange(S)
    big, sub = index // SUPERSAMPLE, index % SUPERSAMPLE
    within = (sub + 0.5) / SUPERSAMPLE  # position inside the template cell, 0..1
    x = x0 + (big + within) * cell[0]  # column j
    y = y1 - (big + within) * cell[1]  # row i, from the top
    centre = np.stack(np.broadcast_arrays(x[None, :], y[:, None]), axis=-1)  # (S, S, 2)
    return centre[None] + (OFFSETS * cell)[:, None, None, :]


def _edge(p: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(P, K) twice the signed area of triangle (s_k, t_k, p) in (x, y), for (P, 1, 2) points
    and (K, 3) corners."""
    return (t[:, 0] - s[:, 0]) * (p[..., 1] - s[:, 1]) - (t[:, 1] - s[:, 1]) * (p[..., 0] - s[:, 0])


def _facing(corners: np.ndarray) -> np.ndarray:
    """(..., 3, 3) triangles -> (...) bool: the triangle's front (counter-clockwise) side is
    turned toward +z."""
    e1, e2 = corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :]
    return e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0] > 0


def _front_surface(mesh: Mesh, tag: Tag, points: np.ndarray, facing_only: bool
                   ) -> np.ndarray:
    """For (n, 2) points: the largest z of ``tag`` triangles over each (x, y) (-inf if none).
    ``facing_only`` ignores triangles whose front side is turned away from +z."""
    corners = mesh.vertices[mesh.triangles].astype(np.float64)
    facing = _facing(corners)
    lo, hi = corners[:, :, :2].min(axis=1), corners[:, :, :2].max(axis=1)
    keep = (mesh.tags == tag) & np.all((lo <= points.max(axis=0)) & (hi >= points.min(axis=0)),
                                       axis=1)
    if facing_only:
        keep &= facing
    ids = np.flatnonzero(keep)
    a, b, c = corners[ids, 0], corners[ids, 1], corners[ids, 2]
    best = np.full(len(points), -np.inf)
    for start in range(0, len(points), 512):
        p = points[start:start + 512, None, :]  # (P, 1, 2)
        # (P, K) area-weighted barycentrics: twice the signed areas of (p, b, c), (p, c, a) ...
        wa, wb, wc = _edge(p, b, c), _edge(p, c, a), _edge(p, a, b)
        area = wa + wb + wc
        tol = 1e-9 * np.abs(area)
        inside = (((wa >= -tol) & (wb >= -tol) & (wc >= -tol))
                  | ((wa <= tol) & (wb <= tol) & (wc <= tol))) & (np.abs(area) > 1e-12)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = (wa * a[:, 2] + wb * b[:, 2] + wc * c[:, 2]) / area
        best[start:start + 512] = np.where(inside, z, -np.inf).max(axis=1, initial=-np.inf)
    return best


@pytest.mark.parametrize("region", REGIONS, ids=REGION_NAMES)
def test_template_samples_are_the_front_surface_under_each_grid_point(region: RegionSpec
                                                                      ) -> None:
    mesh = generic_head()
    triangles, bary = template_samples(region)
    assert triangles.shape == (5, S, S) and triangles.dtype == np.int64
    assert bary.shape == (5, S, S, 3) and bary.dtype == np.float32
    assert len(OFFSETS) == 5 and (bary >= 0).all()
    np.testing.assert_allclose(bary.sum(axis=-1), 1.0, atol=1e-6)
    assert (triangles >= 0).all() and (triangles < len(mesh.triangles)).all()
    assert (mesh.tags[triangles] == region.tag).all()

    points = np.einsum("...k,...kc->...c", bary.astype(np.float64),
                       mesh.vertices.astype(np.float64)[mesh.triangles[triangles]])
    expected = _expected_grids(region)
    np.testing.assert_allclose(points[..., :2], expected, atol=1e-3)
    # the centre grid's template cells tile the box: their means are the cell centres
    x0, x1, y0, y1 = region.box
    cells = points[0, ..., :2].reshape(TEMPLATE_SIZE, SUPERSAMPLE, TEMPLATE_SIZE, SUPERSAMPLE,
                                       2).mean(axis=(1, 3))
    cx, cy = (x1 - x0) / TEMPLATE_SIZE, (y1 - y0) / TEMPLATE_SIZE
    np.testing.assert_allclose(cells[0, 0], [x0 + cx / 2, y1 - cy / 2], atol=1e-3)
    np.testing.assert_allclose(cells[-1, -1], [x1 - cx / 2, y0 + cy / 2], atol=1e-3)

    # each hit is the front-most surface of the region's kind seen from +z: it faces +z, and
    # no triangle of that tag facing +z lies over that (x, y) at a larger z
    assert _facing(mesh.vertices.astype(np.float64)[mesh.triangles[triangles]]).all()
    flat = points.reshape(-1, 3)
    top = _front_surface(mesh, region.tag, flat[:, :2], facing_only=True)
    assert (top <= flat[:, 2] + 1e-3).all()
    if region.tag != Tag.MOUTH_INTERIOR:
        # skin and eyeballs: nothing of that tag, of either side, is in front either. (Behind
        # the lips, a ray from the front crosses the cavity's wall on the lips' inner side,
        # which faces back into the mouth, before it reaches the back of the cavity.)
        top = _front_surface(mesh, region.tag, flat[:, :2], facing_only=False)
        assert (top <= flat[:, 2] + 1e-3).all()


def test_offset_grids_move_by_one_template_cell_diagonally() -> None:
    region = spec("forehead")
    mesh = generic_head()
    triangles, bary = template_samples(region)
    points = np.einsum("...k,...kc->...c", bary.astype(np.float64),
                       mesh.vertices.astype(np.float64)[mesh.triangles[triangles]])
    x0, x1, y0, y1 = region.box
    cell = np.array([(x1 - x0), (y1 - y0)]) / TEMPLATE_SIZE
    for o, (du, dv) in enumerate([(0, 0), (1, 1), (-1, 1), (1, -1), (-1, -1)]):
        shift = (points[o, ..., :2] - points[0, ..., :2]).reshape(-1, 2).mean(axis=0)
        np.testing.assert_allclose(shift, [du * cell[0], dv * cell[1]], atol=1e-3)


def test_an_unknown_region_is_named_in_the_error() -> None:
    with pytest.raises(RegionError, match="'nose'"):
        spec("nose")
    assert issubclass(RegionError, ValueError)
    assert spec("mouth").tag == Tag.MOUTH_INTERIOR
    assert [spec(name).name for name in REGION_NAMES] == list(REGION_NAMES)
