"""The generic head: topology (closed, oriented, symmetric), landmarks, phantoms, UVs, tags."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from facewire.models.head import generic_head, mirror_map
from facewire.models.head.anatomy import EYE_RADIUS
from facewire.models.head.uvlayout import (
    EYE_BACK_UV,
    EYE_BACK_UV_RADIUS,
    EYE_UV,
    EYE_UV_RADIUS,
    MOUTH_UV,
    SKIN_U_MAX,
)
from facewire.models.landmarks import FEATURES, MIRROR, PHANTOM_MIRROR, PHANTOM_NAMES
from facewire.models.mesh import Mesh, Tag

SKIN_TAGS = (Tag.SKIN, Tag.SCALP, Tag.EAR, Tag.MOUTH_INTERIOR)


@pytest.fixture(scope="module")
def mesh() -> Mesh:
    return generic_head()


@pytest.fixture(scope="module")
def welded(mesh: Mesh) -> np.ndarray:
    """Triangles over welded vertices: copies at one position (texture seams) become one."""
    _, inverse = np.unique(mesh.vertices, axis=0, return_inverse=True)
    return inverse.ravel()[mesh.triangles]


def _directed_edges(tri: np.ndarray) -> np.ndarray:
    return np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])


def _ray_hits(origin: np.ndarray, direction: np.ndarray,
              mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Distances and triangle indices of all hits of one ray with the mesh (Moller-Trumbore)."""
    v = mesh.vertices.astype(np.float64)
    a, b, c = (v[mesh.triangles[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    p = np.cross(direction, e2)
    det = (e1 * p).sum(1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - a
    u = (s * p).sum(1) * inv
    q = np.cross(s, e1)
    w = (q @ direction) * inv
    t = (e2 * q).sum(1) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
    order = np.argsort(t[hit])
    return t[hit][order], np.flatnonzero(hit)[order]


def test_size_dtypes_and_validation(mesh: Mesh) -> None:
    assert 5000 <= len(mesh.vertices) <= 20000
    assert mesh.vertices.dtype == np.float32 and mesh.triangles.dtype == np.int32
    # The constructor validates; build one again from the same arrays.
    Mesh(mesh.vertices, mesh.triangles, mesh.uv, mesh.tags, mesh.landmarks, mesh.phantoms)
    assert len(np.unique(mesh.triangles)) == len(mesh.vertices)  # no unused vertices


def test_deterministic_and_fresh_arrays(mesh: Mesh) -> None:
    again = generic_head()
    assert again.vertices is not mesh.vertices
    again.vertices[:] = 0.0  # the caller owns the arrays
    third = generic_head()
    np.testing.assert_array_equal(third.vertices, mesh.vertices)
    np.testing.assert_array_equal(third.triangles, mesh.triangles)
    np.testing.assert_array_equal(third.uv, mesh.uv)


def test_no_degenerate_triangles(mesh: Mesh, welded: np.ndarray) -> None:
    v = mesh.vertices.astype(np.float64)
    a, b, c = (v[mesh.triangles[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    assert area.min() > 1e-3
    assert np.all((welded[:, 0] != welded[:, 1]) & (welded[:, 1] != welded[:, 2])
                  & (welded[:, 2] != welded[:, 0]))


def test_coincident_vertices_are_texture_seams_only(mesh: Mesh) -> None:
    _, first, inverse, counts = np.unique(mesh.vertices, axis=0, return_index=True,
                                          return_inverse=True, return_counts=True)
    dup = np.flatnonzero(counts[inverse.ravel()] > 1)
    assert dup.size > 0
    assert counts.max() == 2
    partner = first[inverse.ravel()[dup]]
    copies = dup[dup != partner]
    original = first[inverse.ravel()[copies]]
    assert np.all(np.abs(mesh.uv[copies] - mesh.uv[original]).max(axis=1) > 1e-3)


def test_closed_consistently_oriented_components(mesh: Mesh, welded: np.ndarray) -> None:
    n = int(welded.max()) + 1
    edges = _directed_edges(welded)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    count, label = connected_components(graph, directed=False)
    assert count == 3  # skin with sockets and mouth cavity, and two eyeballs
    v = mesh.vertices.astype(np.float64)
    for k in range(count):
        mask = label[welded[:, 0]] == k
        tri = welded[mask]
        e = _directed_edges(tri)
        keys = e[:, 0].astype(np.int64) * n + e[:, 1]
        rev = e[:, 1].astype(np.int64) * n + e[:, 0]
        # Every directed edge once, and its reverse once: closed, manifold, one orientation.
        assert len(np.unique(keys)) == len(keys)
        assert np.all(np.isin(rev, keys))
        raw = mesh.triangles[mask]
        volume = np.einsum("ij,ij->i", v[raw[:, 0]], np.cross(v[raw[:, 1]], v[raw[:, 2]])).sum() / 6
        assert volume > 0.0
        tags = set(np.unique(mesh.tags[mask]).tolist())
        assert tags <= set(SKIN_TAGS) or tags in ({Tag.LEFT_EYEBALL}, {Tag.RIGHT_EYEBALL})


def test_mirror_map_is_a_symmetry(mesh: Mesh) -> None:
    m = mirror_map()
    assert m.shape == (len(mesh.vertices),) and m.dtype == np.int32
    np.testing.assert_array_equal(m[m], np.arange(len(m)))
    v = mesh.vertices
    np.testing.assert_array_equal(v[m], v * np.array([-1.0, 1.0, 1.0], np.float32))
    assert np.all(v[m == np.arange(len(m)), 0] == 0.0)
    # Mirrored triangles (reversed) are triangles, with eyeball tags swapped.
    n = len(v)
    key = lambda t: np.sort(t, axis=1) @ np.array([n * n, n, 1], np.int64)  # noqa: E731
    original = dict(zip(key(mesh.triangles.astype(np.int64)).tolist(), mesh.tags.tolist()))
    mirrored = key(m[mesh.triangles].astype(np.int64)).tolist()
    swap = {Tag.LEFT_EYEBALL: Tag.RIGHT_EYEBALL, Tag.RIGHT_EYEBALL: Tag.LEFT_EYEBALL}
    assert all(original[k] == swap.get(t, t) for k, t in zip(mirrored, mesh.tags.tolist()))
    # Landmarks and phantoms follow the iBUG and phantom mirror orders.
    np.testing.assert_array_equal(m[mesh.landmarks], mesh.landmarks[MIRROR])
    np.testing.assert_array_equal(m[mesh.phantoms], mesh.phantoms[PHANTOM_MIRROR])


def test_landmark_geometry(mesh: Mesh) -> None:
    p = mesh.vertices[mesh.landmarks].astype(np.float64)
    assert len(np.unique(mesh.landmarks)) == 68
    skin = np.unique(mesh.triangles[mesh.tags == Tag.SKIN])
    assert np.all(np.isin(mesh.landmarks, skin))
    np.testing.assert_allclose(p[MIRROR] * [-1, 1, 1], p, atol=1e-5)
    outer = np.linalg.norm(p[36] - p[45])
    assert 88.0 <= outer <= 96.0
    assert 30.0 <= np.linalg.norm(p[39] - p[42]) <= 38.0
    assert p[36, 0] < p[39, 0] < 0.0 < p[42, 0] < p[45, 0]  # person's right eye at -x
    assert np.argmax(p[:, 2]) == 30  # the nose tip is the most forward landmark
    assert 20.0 <= p[30, 2] - p[[39, 42], 2].mean() <= 35.0
    assert np.argmin(p[:, 1]) == 8  # the chin is the lowest
    assert 44.0 <= np.linalg.norm(p[48] - p[54]) <= 56.0
    heights = [p[36:48, 1].mean(), *p[[30, 33, 51, 62, 66, 57, 8], 1]]
    assert np.all(np.diff(heights) < 0)
    assert p[17:27, 1].min() > p[36:48, 1].max()  # brows above the eyes
    assert np.all(np.diff(p[:9, 0]) > 0) and np.all(np.diff(p[8:17, 0]) > 0)  # jaw, right to left
    # Open eyes (eye aspect ratio of a relaxed eye) and lips apart at the midline.
    for c1, u1, u2, c2, l2, l1 in ((36, 37, 38, 39, 40, 41), (42, 43, 44, 45, 46, 47)):
        lids = np.linalg.norm(p[u1] - p[l1]) + np.linalg.norm(p[u2] - p[l2])
        ear = lids / (2 * np.linalg.norm(p[c1] - p[c2]))
        assert 0.2 <= ear <= 0.4
    assert p[62, 1] - p[66, 1] > 1.0
    # Jaw points lie on the frontal silhouette: their normals are nearly sideways.
    normals = mesh.vertex_normals()[mesh.landmarks]
    assert np.all(np.abs(normals[:17, 2]) < 0.35)


def test_phantoms_around_the_face(mesh: Mesh) -> None:
    v = mesh.vertices.astype(np.float64)
    ph = dict(zip(PHANTOM_NAMES, v[mesh.phantoms]))
    lm = v[mesh.landmarks]
    assert len(np.unique(mesh.phantoms)) == 13
    # Well apart from the tracked feature points and from each other (RBF centres).
    centres = np.concatenate([lm[FEATURES], v[mesh.phantoms]])
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=2) + np.eye(len(centres)) * 1e9
    assert dist[len(FEATURES):].min() > 15.0
    assert ph["crown"][1] == max(q[1] for q in ph.values())
    assert ph["forehead_top"][1] > lm[17:27, 1].max() + 30.0
    assert ph["under_chin"][1] < lm[57, 1] and ph["under_chin"][2] < lm[8, 2]
    assert ph["jaw_angle_left"][0] > lm[12, 0] - 10.0 and ph["jaw_angle_left"][2] < lm[12, 2]
    assert ph["temple_left"][0] > lm[45, 0] and ph["cheekbone_left"][0] > lm[45, 0]


def test_eyeballs_sit_in_open_eyelids(mesh: Mesh) -> None:
    v = mesh.vertices.astype(np.float64)
    skin = np.unique(mesh.triangles[mesh.tags == Tag.SKIN])
    p = v[mesh.landmarks]
    for tag, eye in ((Tag.RIGHT_EYEBALL, range(36, 42)), (Tag.LEFT_EYEBALL, range(42, 48))):
        ball = v[np.unique(mesh.triangles[mesh.tags == tag])]
        centre = 0.5 * (ball.min(axis=0) + ball.max(axis=0))
        centre[2] = ball[:, 2].min() + EYE_RADIUS  # the cornea bulges at the front
        radius = np.linalg.norm(ball - centre, axis=1)
        assert radius.min() > EYE_RADIUS - 0.1 and radius.max() < EYE_RADIUS + 1.2
        # No skin inside the eyeball.
        assert np.linalg.norm(v[skin] - centre, axis=1).min() > EYE_RADIUS + 0.2
        # The pupil is between the lids and the corners, and nothing covers it from the front.
        apex = ball[np.argmax(ball[:, 2])]
        lids = p[list(eye)]
        assert lids[:, 0].min() < apex[0] < lids[:, 0].max()
        assert lids[[4, 5], 1].max() < apex[1] < lids[[1, 2], 1].min()
        _, hit = _ray_hits(apex + [0.0, 0.0, 0.01], np.array([0.0, 0.0, 1.0]), mesh)
        assert hit.size == 0
    balls = [v[np.unique(mesh.triangles[mesh.tags == t])].mean(axis=0) for t in
             (Tag.RIGHT_EYEBALL, Tag.LEFT_EYEBALL)]
    assert 60.0 <= balls[1][0] - balls[0][0] <= 66.0  # interpupillary distance


def test_mouth_slit_leads_into_the_cavity(mesh: Mesh) -> None:
    v = mesh.vertices.astype(np.float64)
    p = v[mesh.landmarks]
    between = 0.5 * (p[62] + p[66])
    _, hit = _ray_hits(np.array([0.0, between[1], 200.0]), np.array([0.0, 0.0, -1.0]), mesh)
    assert mesh.tags[hit[0]] == Tag.MOUTH_INTERIOR
    # Looking through the slit a little off the midline, too.
    mid = 0.5 * (p[63] + p[65])
    _, hit = _ray_hits(np.array([mid[0], mid[1], 200.0]), np.array([0.0, 0.0, -1.0]), mesh)
    assert mesh.tags[hit[0]] == Tag.MOUTH_INTERIOR
    cavity = v[np.unique(mesh.triangles[mesh.tags == Tag.MOUTH_INTERIOR])]
    assert cavity[:, 2].min() < p[62, 2] - 30.0  # a pocket reaching well into the head
    assert np.abs(cavity[:, 0]).max() <= np.abs(p[48, 0]) + 1.0


def test_uv_layout(mesh: Mesh) -> None:
    uv = mesh.uv.astype(np.float64)
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    tri = mesh.triangles
    texel = uv[tri] * [1024.0, 512.0]
    e1, e2 = texel[:, 1] - texel[:, 0], texel[:, 2] - texel[:, 0]
    signed = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    # No folds on the skin, ears and mouth (v up, counter-clockwise like the triangles); the
    # cylindrical map may turn the few scalp triangles at the very top of the head.
    flat = np.isin(mesh.tags, [Tag.SKIN, Tag.EAR, Tag.MOUTH_INTERIOR])
    assert np.all(signed[flat] > 0.0)
    top = mesh.vertices[tri].mean(axis=1)[:, 1] > 110.0
    assert np.all(signed[(mesh.tags == Tag.SCALP) & ~top] > 0.0)
    # Areas: skin left of u = 0.8; eyeballs in their discs; mouth cavity in its disc.
    skin = np.unique(tri[np.isin(mesh.tags, [Tag.SKIN, Tag.SCALP, Tag.EAR])])
    assert uv[skin, 0].max() <= SKIN_U_MAX + 1e-6
    for tag, side in ((Tag.LEFT_EYEBALL, "left"), (Tag.RIGHT_EYEBALL, "right")):
        ball = np.unique(tri[mesh.tags == tag])
        front = mesh.vertices[ball, 2] >= mesh.vertices[ball, 2].max() - EYE_RADIUS - 1e-3
        d = (uv[ball] - EYE_UV[side]) / [EYE_UV_RADIUS, 2 * EYE_UV_RADIUS]
        back = (uv[ball] - EYE_BACK_UV[side]) / [EYE_BACK_UV_RADIUS, 2 * EYE_BACK_UV_RADIUS]
        in_front, in_back = (np.linalg.norm(x, axis=1) <= 1.0 for x in (d, back))
        assert np.all(in_front | in_back) and np.all(in_front[front])
        apex = ball[np.argmax(mesh.vertices[ball, 2])]
        np.testing.assert_allclose(uv[apex], EYE_UV[side], atol=1e-6)  # the iris is central
    cavity = np.unique(tri[mesh.tags == Tag.MOUTH_INTERIOR])
    assert np.all(uv[cavity, 0] > SKIN_U_MAX)
    assert np.linalg.norm(uv[cavity] - MOUTH_UV, axis=1).max() < 0.2
    # The face gets most of the texture: the skin in front, between hairline and chin.
    centre = mesh.vertices[tri].mean(axis=1)
    face = (mesh.tags == Tag.SKIN) & (centre[:, 2] > 20.0) & (np.abs(centre[:, 1] + 20.0) < 100.0)
    assert signed[face].sum() > 0.4 * 1024 * 512
    assert signed[face].sum() > signed[~face].sum() * 0.75


def test_face_landmarks_have_distinct_ordered_uvs(mesh: Mesh) -> None:
    uv = mesh.uv[mesh.landmarks].astype(np.float64) * [1024.0, 512.0]
    p = mesh.vertices[mesh.landmarks].astype(np.float64)
    gap = np.linalg.norm(uv[:, None] - uv[None], axis=2) + np.eye(68) * 1e9
    assert gap.min() > 2.0  # texels
    # Left-right order along rows and up-down order along columns survive the map (no seam
    # or fold across the face; it is cylindrical, so only nearby rows and columns compare).
    dx, du = p[:, None, 0] - p[None, :, 0], uv[:, None, 0] - uv[None, :, 0]
    dy, dv = p[:, None, 1] - p[None, :, 1], uv[:, None, 1] - uv[None, :, 1]
    row = (np.abs(dx) > 2.0) & (np.abs(dy) < 10.0)
    assert np.all(np.sign(du[row]) == np.sign(dx[row]))
    column = (np.abs(dy) > 2.0) & (np.abs(dx) < 20.0)
    assert np.all(np.sign(dv[column]) == np.sign(dy[column]))


def test_tags(mesh: Mesh) -> None:
    assert set(np.unique(mesh.tags).tolist()) == {int(t) for t in Tag}
    centre = mesh.vertices[mesh.triangles].mean(axis=1)
    assert np.all(centre[mesh.tags == Tag.LEFT_EYEBALL, 0] > 0.0)
    assert np.all(centre[mesh.tags == Tag.RIGHT_EYEBALL, 0] < 0.0)
    assert np.all(np.abs(centre[mesh.tags == Tag.EAR, 0]) > 60.0)
    scalp = centre[mesh.tags == Tag.SCALP]
    assert np.all((scalp[:, 1] > 3.0) | (scalp[:, 2] < 0.0))
    face = mesh.vertices[mesh.landmarks]
    assert not np.isin(mesh.landmarks, mesh.triangles[mesh.tags == Tag.SCALP]).any()
    assert face[:, 2].min() > 0.0


def test_uv_layout_is_one_to_one(mesh: Mesh) -> None:
    """No texel holds two surface points: the texture projection refuses a stacked layout."""
    from facewire.sender.enroll.texture import uv_surface

    uv_surface(mesh, (512, 1024))  # raises TextureError on > 1 % overlapping texels
