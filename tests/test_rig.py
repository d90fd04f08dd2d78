"""Tests for models.rig: the model's animation rig (centres, anchors, fast per-frame morph)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from facewire.models.head import generic_head, mirror_map
from facewire.models.head.anatomy import EYE_RADIUS
from facewire.models.landmarks import FEATURES, MIRROR, NONRIGID, PHANTOM_NAMES
from facewire.models.mesh import Mesh, Tag
from facewire.models.rig import (
    ANCHOR_CLEARANCE,
    ANCHORS,
    MANDIBLE_PHANTOMS,
    Rig,
    anchor_vertices,
    mandible_follow,
)

SLOT = {int(p): k for k, p in enumerate(NONRIGID)}  # iBUG index -> row of the residuals
FLIP_X = np.array([-1.0, 1.0, 1.0], dtype=np.float32)


@pytest.fixture(scope="module")
def mesh() -> Mesh:
    return generic_head()


@pytest.fixture(scope="module")
def rig(mesh: Mesh) -> Rig:
    return Rig(mesh)


def _residuals(moves: dict[int, tuple[float, float, float]]) -> np.ndarray:
    r = np.zeros((len(NONRIGID), 3), dtype=np.float32)
    for point, d in moves.items():
        r[SLOT[point]] = d
    return r


def _expression() -> np.ndarray:
    """Mouth open 10 mm (57) and chin 8 mm down, smile (48/54 4 mm outward and up), brows up
    4 mm (19, 21, 22, 24)."""
    s = 4 / np.sqrt(2)
    return _residuals({57: (0, -10, 0), 8: (0, -8, 0), 48: (-s, s, 0), 54: (s, s, 0),
                       19: (0, 4, 0), 21: (0, 4, 0), 22: (0, 4, 0), 24: (0, 4, 0)})


def _mouth_corner() -> np.ndarray:
    """The person's right mouth corner (48, at -x) 5 mm outward and up."""
    return _residuals({48: tuple(np.array([-3.0, 3.0, 0.0]) * 5 / np.sqrt(18))})


def _full_displacements(rig: Rig, r: np.ndarray) -> np.ndarray:
    """The (M, 3) displacements of all centres: r at the non-rigid features, the chin's
    residual scaled by ``follow`` at the mandible phantoms, zero elsewhere."""
    d = np.zeros((len(rig.centres), 3), dtype=np.float32)
    d[np.arange(len(FEATURES))[np.isin(FEATURES, NONRIGID)]] = r
    d[len(FEATURES):len(FEATURES) + len(PHANTOM_NAMES)] = rig.follow[:, None] * r[SLOT[8]]
    return d


def test_centres_and_anchors(mesh: Mesh, rig: Rig) -> None:
    n_face = len(FEATURES) + len(mesh.phantoms)
    assert 12 <= len(rig.anchors) <= ANCHORS
    np.testing.assert_array_equal(rig.centres[:len(FEATURES)], mesh.landmarks[FEATURES])
    np.testing.assert_array_equal(rig.centres[len(FEATURES):n_face], mesh.phantoms)
    np.testing.assert_array_equal(rig.centres[n_face:], rig.anchors)
    assert len(np.unique(rig.centres)) == len(rig.centres)
    np.testing.assert_array_equal(anchor_vertices(mesh), rig.anchors)  # deterministic
    v = mesh.vertices
    face = v[rig.centres[:n_face]]
    gaps = np.linalg.norm(v[rig.anchors][:, None] - face[None], axis=-1).min(axis=1)
    assert gaps.min() >= ANCHOR_CLEARANCE
    behind = v[rig.anchors, 2] < v[mesh.phantoms[:-1], 2].min()
    neck = v[rig.anchors, 1] < face[:, 1].min() - 25
    assert (behind | neck).all()
    skull = np.unique(mesh.triangles[np.isin(mesh.tags, [Tag.SKIN, Tag.SCALP, Tag.EAR])])
    assert np.isin(rig.anchors, skull).all()
    # as positions, the anchor set is its own mirror image (seam copies share a position)
    a = v[rig.anchors]
    assert cKDTree(a).query(a * FLIP_X)[0].max() < 1e-4
    assert len(anchor_vertices(mesh, count=4)) <= 4
    assert len(anchor_vertices(mesh, count=0)) == 0
    with pytest.raises(ValueError, match="count"):
        anchor_vertices(mesh, count=-1)


def test_zero_residuals_give_the_neutral_mesh(mesh: Mesh, rig: Rig) -> None:
    zero = np.zeros((9, 3), dtype=np.float32)
    y = rig.morph(zero)
    assert y.dtype == np.float32 and y.shape == mesh.vertices.shape
    np.testing.assert_array_equal(y, mesh.vertices)
    np.testing.assert_array_equal(rig.morph(zero.astype(np.float64)), mesh.vertices)
    np.testing.assert_array_equal(rig.landmarks(zero), mesh.vertices[mesh.landmarks])


def test_anchors_hold_the_skull(mesh: Mesh, rig: Rig) -> None:
    r = _mouth_corner()
    moved = np.linalg.norm(rig.morph(r) - mesh.vertices, axis=1)
    assert moved[rig.anchors].max() < 0.05
    back = mesh.vertices[:, 2] < -20  # behind the ears
    assert moved[back].max() < 0.4  # about 2 mm without anchors (module docstring)
    # the same, with the realistic expression: its 8 mm chin drop also moves the mandible
    # phantoms (up to 6.8 mm), whose pull the regularised fit lets reach the anchors (0.067 mm
    # measured; 0.019 mm with rigid mandible phantoms)
    moved = np.linalg.norm(rig.morph(_expression()) - mesh.vertices, axis=1)
    assert moved[rig.anchors].max() < 0.1


def test_features_land_near_their_targets(mesh: Mesh) -> None:
    """lam = 0.01 (relative Tikhonov) smooths: a feature may miss its target by a few percent
    of the largest residual (measured 6.7 % for the expression); as lam -> 0 the morph
    interpolates."""
    r = _expression()
    largest = float(np.linalg.norm(r, axis=1).max())
    for lam, bound in ((0.01, 0.1 * largest), (1e-7, 0.01)):
        rig = Rig(mesh, lam=lam)
        got = rig.landmarks(r)[NONRIGID] - mesh.vertices[mesh.landmarks[NONRIGID]]
        assert np.linalg.norm(got - r, axis=1).max() < bound, lam
        rigid = [int(p) for p in FEATURES if int(p) not in SLOT]
        held = np.linalg.norm(rig.landmarks(r)[rigid] - mesh.vertices[mesh.landmarks[rigid]],
                              axis=1)
        assert held.max() < bound, lam


def test_fast_path_equals_volume_morph(mesh: Mesh, rig: Rig) -> None:
    r = np.random.default_rng(3).uniform(-5, 5, (9, 3)).astype(np.float32)
    # the field lives in the kernel space (lips apart): its displacements, added to the mesh
    full = rig.field.apply(_full_displacements(rig, r)) - rig.field.points + mesh.vertices
    fast = rig.morph(r)
    others = np.setdiff1d(np.arange(len(mesh.vertices)), rig.eyeball_vertices)
    # the same float32 product without the columns multiplied by zero: bit-exact, or within
    # float32 rounding if BLAS sums the 9 terms in another order
    np.testing.assert_allclose(fast[others], full[others], rtol=0, atol=1e-4)
    np.testing.assert_array_equal(rig.landmarks(r), fast[mesh.landmarks])
    assert np.abs(full[rig.eyeball_vertices] - mesh.vertices[rig.eyeball_vertices]).max() > 0.01


def test_centre_displacements_match_the_docstring(rig: Rig) -> None:
    r = np.random.default_rng(5).uniform(-5, 5, (9, 3)).astype(np.float32)
    np.testing.assert_array_equal(rig.centre_displacements(r), _full_displacements(rig, r))


def test_mandible_phantoms_follow_the_chin(mesh: Mesh, rig: Rig) -> None:
    """Jaw angles, jaw and under-chin phantoms take a fraction of the chin's move (their
    distance from the hinge axis through the cheekbones over the chin's); the skull's
    phantoms none. A chin drop then carries the jaw line: contour points 5 and 11 follow
    the chin by more than a third (with rigid phantoms: 0.11 on the generic head)."""
    follow = mandible_follow(mesh)
    np.testing.assert_array_equal(rig.follow, follow)
    names = np.array(PHANTOM_NAMES)
    jaw = np.isin(names, MANDIBLE_PHANTOMS)
    assert jaw.sum() == 5
    assert (follow[~jaw] == 0).all()
    assert ((follow[jaw] > 0.4) & (follow[jaw] < 1.0)).all()
    index = {n: i for i, n in enumerate(PHANTOM_NAMES)}
    # further from the hinge, further along: under the chin > jaw > jaw angle
    under, jaw, angle = (follow[index[n]] for n in ("under_chin", "jaw_left", "jaw_angle_left"))
    assert under > jaw > angle
    assert follow[index["jaw_left"]] == pytest.approx(follow[index["jaw_right"]], abs=1e-6)
    drop = _residuals({8: (0, -10, 0)})
    moved = rig.landmarks(drop) - mesh.vertices[mesh.landmarks]
    for point in (5, 11):
        assert -moved[point, 1] > 10 / 3, point
    assert -moved[8, 1] > 9.0
    assert abs(moved[0, 1]) < 1.0 and abs(moved[16, 1]) < 1.0  # by the ear: little motion


def test_eyeballs_stay_rigid_and_clear_of_the_lids(mesh: Mesh, rig: Rig) -> None:
    """Eyeballs are fixed in the skull; the lids and socket move around them without
    cutting into them under the realistic expression."""
    r = _expression()
    y = rig.morph(r)
    balls = np.unique(mesh.triangles[np.isin(mesh.tags, [Tag.RIGHT_EYEBALL, Tag.LEFT_EYEBALL])])
    np.testing.assert_array_equal(np.sort(rig.eyeball_vertices), balls)
    np.testing.assert_array_equal(y[balls], mesh.vertices[balls])
    skin = np.unique(mesh.triangles[mesh.tags == Tag.SKIN])
    for tag in (Tag.RIGHT_EYEBALL, Tag.LEFT_EYEBALL):
        ball = np.unique(mesh.triangles[mesh.tags == tag])
        tree = cKDTree(mesh.vertices[ball])
        dist, _ = tree.query(mesh.vertices[skin])
        near = skin[dist < 2.0]  # eyelid margins and the socket cup
        assert len(near) > 100
        _, j = tree.query(mesh.vertices[near])
        # The eyeball's outward normal is radial: the back pole is one radius behind the centre.
        lo, hi = mesh.vertices[ball].min(axis=0), mesh.vertices[ball].max(axis=0)
        centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] + EYE_RADIUS])
        n = mesh.vertices[ball][j] - centre
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        before = ((mesh.vertices[near] - mesh.vertices[ball][j]) * n).sum(axis=1)
        after = ((y[near] - y[ball][j]) * n).sum(axis=1)
        assert before.min() > 0.1
        assert after.min() > 0.02  # still outside the eyeball (0.03 mm measured)


def test_no_triangle_flips_under_an_expression(mesh: Mesh, rig: Rig) -> None:
    y = rig.morph(_expression()).astype(np.float64)
    v = mesh.vertices.astype(np.float64)
    t = mesh.triangles

    def normals(p: np.ndarray) -> np.ndarray:
        return np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])

    n0, n1 = normals(v), normals(y)
    cos = (n0 * n1).sum(axis=1) / np.linalg.norm(n0, axis=1) / np.linalg.norm(n1, axis=1)
    moved = np.linalg.norm(y - v, axis=1)
    assert moved.max() > 7.0  # the expression did move the face
    for tag in (Tag.SKIN, Tag.SCALP, Tag.EAR, Tag.MOUTH_INTERIOR):
        assert cos[mesh.tags == tag].min() > 0.5, tag.name
    area = np.linalg.norm(n1, axis=1) / np.linalg.norm(n0, axis=1)
    assert area.min() > 0.5


def test_left_right_symmetric(mesh: Mesh, rig: Rig) -> None:
    rng = np.random.default_rng(7)
    for r in (_mouth_corner(), _expression(), rng.uniform(-5, 5, (9, 3)).astype(np.float32)):
        # the mirrored residuals: point i takes its partner's residual with x negated
        mirrored = (r * FLIP_X)[[SLOT[int(MIRROR[p])] for p in NONRIGID]]
        y, ym = rig.morph(r), rig.morph(mirrored)
        np.testing.assert_allclose(ym[mirror_map()], y * FLIP_X, rtol=0, atol=2e-4)
    # a one-sided move is not symmetric by itself (the check above can fail)
    y = rig.morph(_mouth_corner())
    assert np.abs(y[mirror_map()] - y * FLIP_X).max() > 1.0


def test_bad_input(rig: Rig) -> None:
    with pytest.raises(ValueError, match="mesh"):
        Rig("head.fwm")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"residuals: expected shape \(9, 3\)"):
        rig.morph(np.zeros((18, 3), np.float32))
    with pytest.raises(ValueError, match="residuals: expected float32"):
        rig.landmarks(np.zeros((9, 3), np.int32))
    with pytest.raises(ValueError, match="NaN"):
        rig.morph(np.full((9, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="numpy array"):
        rig.morph([[0.0] * 3] * 9)  # type: ignore[arg-type]
