"""Tests for models.morph: the RBF volume morph (multiquadric with Eck's stiffness, Gaussian)."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.morph import VolumeMorph

U32 = 2.0**-24  # unit roundoff of float32
MIRROR = np.diag([-1.0, 1.0, 1.0])  # x -> -x: the person's left <-> right


def _ellipsoid(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Points on a head-sized ellipsoid (mm): azimuth theta from +z toward +x, elevation phi."""
    return np.stack(
        [75 * np.sin(theta) * np.cos(phi), 100 * np.sin(phi), 90 * np.cos(theta) * np.cos(phi)],
        axis=-1,
    )


def _face_layout() -> tuple[np.ndarray, np.ndarray]:
    """31 mirror-symmetric centres on the front of the ellipsoid: 18 'features' + 13 'phantoms'.

    Returns (centres (31, 3) float32, mirror (31,) int: centres[mirror[i]] is the x-mirror of
    centres[i]).
    """
    theta = np.array([0.15, 0.35, 0.5, 0.2, 0.3, 0.25, 0.12, 0.45])  # 8 pairs of features
    phi = np.array([0.25, 0.22, 0.3, -0.05, -0.3, -0.45, 0.4, 0.05])
    ring = np.linspace(0, np.pi, 8)[1:-1]  # 6 pairs of phantoms around a ring
    half_t = np.concatenate([theta, 1.0 * np.sin(ring)])
    half_p = np.concatenate([phi, 0.2 + 0.8 * np.cos(ring)])
    mid_t = np.zeros(3)
    mid_p = np.array([0.1, -0.6, 1.0])  # nose, chin, forehead phantom
    t = np.concatenate([half_t, -half_t, mid_t])
    p = np.concatenate([half_p, half_p, mid_p])
    n = half_t.size
    mirror = np.concatenate([np.arange(n) + n, np.arange(n), 2 * n + np.arange(3)])
    return _ellipsoid(t, p).astype(np.float32), mirror


def _points(n: int, seed: int) -> np.ndarray:
    """(2n, 3) float32 points in and around the face; the second half mirrors the first."""
    rng = np.random.default_rng(seed)
    half = _ellipsoid(rng.uniform(-1.2, 1.2, n), rng.uniform(-0.9, 1.0, n))
    half *= rng.uniform(0.7, 1.1, (n, 1))  # some inside the head, some outside
    return np.concatenate([half, half @ MIRROR]).astype(np.float32)


def _displacements(m: int, seed: int, size: float = 4.0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, size, (m, 3)).astype(np.float32)


def _rounding_bound(morph: VolumeMorph, d: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-component bound on float32 rounding in ``y = morph.apply(d)`` (see rigid test)."""
    m = morph.centres.shape[0]
    return (m + 3) * U32 * (np.abs(morph.weights.astype(np.float64)) @ np.abs(d)) + U32 * np.abs(y)


def test_neutral_is_exact():
    centres, _ = _face_layout()
    points = _points(500, 1)
    for kernel in ("multiquadric", "gaussian"):
        morph = VolumeMorph(centres, points, kernel=kernel)
        zero = np.zeros_like(centres)
        np.testing.assert_array_equal(morph.apply(zero), points)
        assert morph.apply(zero).dtype == np.float32
        # float64 input: the output is the float32 neutral points, still exactly
        morph64 = VolumeMorph(centres.astype(np.float64), points.astype(np.float64), kernel=kernel)
        np.testing.assert_array_equal(morph64.apply(zero.astype(np.float64)), points)


@pytest.mark.parametrize("kernel", ["multiquadric", "gaussian"])
def test_interpolates_at_the_centres_as_lambda_goes_to_zero(kernel):
    centres, _ = _face_layout()
    d = _displacements(len(centres), 2)
    errors = []
    for lam in (1e-1, 1e-2, 1e-3, 1e-5, 1e-9):
        y = VolumeMorph(centres, centres, kernel=kernel, lam=lam).apply(d)
        errors.append(float(np.abs(y.astype(np.float64) - centres - d).max()))
    assert all(a > b for a, b in zip(errors, errors[1:])), errors
    assert errors[1] > 1e-3  # the default lam=0.01 does smooth (it is not a no-op)
    assert errors[-1] < 1e-5 * np.abs(d).max()
    # Without regularisation the fit is exact, so what is left is float32 rounding.
    exact = VolumeMorph(centres, centres, kernel=kernel, lam=0.0)
    y = exact.apply(d)
    assert (np.abs(y.astype(np.float64) - centres - d) <= _rounding_bound(exact, d, y)).all()


def test_rigid_motion_is_reproduced():
    """A rigid motion of all centres moves every point rigidly, up to float32 rounding.

    Exactness: d_i = (R - I) x_i + t is affine in x_i, so (c = 0, a = that affine map) solves
    the augmented system for any lambda (module docstring); the field is (R - I) p + t and the
    moved point R p + t, exactly.

    Rounding (u = 2^-24, per component n, j; W = weights, M centres), with y* = R p_n + t:
    - d is rounded to float32:              |d32 - d| <= u |d|
    - W is rounded to float32:              |W32 - W| <= u |W| (W's float64 error,
                                            ~cond(A) 2^-53 < 1e-11, is far below u)
    - the M-term float32 dot product:       error <= gamma_M |W32| |d32|, gamma_M = M u/(1-M u)
    - the final add p + F:                  error <= u |y|
    so |y - y*| <= (M + 2) u (1 + O(M u)) (|W| @ |d|) + u |y| <= (M + 3) u (|W| @ |d|) + u |y|,
    the extra u absorbing the second-order terms. For 100-mm points and ~20-mm displacements
    that is ~1e-5 mm, while a morph that does not reproduce rigid motion is off by millimetres.
    """
    centres, _ = _face_layout()
    points = _points(1000, 3)
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    angle = np.radians(12.0)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    shift = np.array([3.0, -2.0, 5.0])
    x = centres.astype(np.float64)
    d = (x @ rotation.T + shift - x).astype(np.float32)
    for lam in (0.0, 0.01, 1.0):
        morph = VolumeMorph(centres, points, lam=lam)
        y = morph.apply(d)
        expected = points.astype(np.float64) @ rotation.T + shift
        bound = _rounding_bound(morph, d, y)
        assert bound.max() < 1e-3
        assert (np.abs(y - expected) <= bound).all(), np.abs(y - expected).max()


def _reference(centres: np.ndarray, points: np.ndarray, d: np.ndarray, kernel: str,
               lam: float) -> np.ndarray:
    """The module docstring's formulas, written out plainly in float64 (no balancing, no
    folding of the solve into the weights)."""
    x, p, d = (a.astype(np.float64) for a in (centres, points, d))
    m = len(x)
    r = np.linalg.norm(x[:, None] - x[None], axis=-1)
    rp = np.linalg.norm(p[:, None] - x[None], axis=-1)
    s = (r + np.diag(np.full(m, np.inf))).min(axis=1)  # Eck: nearest other centre
    if kernel == "multiquadric":
        h = np.sqrt(r**2 + s**2) - lam * s.mean() * np.eye(m)  # H[j, i] uses s_i
        poly = np.hstack([x, np.ones((m, 1))])
        system = np.block([[h, poly], [poly.T, np.zeros((4, 4))]])
        coef = np.linalg.solve(system, np.vstack([d, np.zeros((4, 3))]))
        return p + np.hstack([np.sqrt(rp**2 + s**2), p, np.ones((len(p), 1))]) @ coef
    w = 2 * s.mean()
    coef = np.linalg.solve(np.exp(-((r / w) ** 2)) + lam * np.eye(m), d)
    return p + np.exp(-((rp / w) ** 2)) @ coef


@pytest.mark.parametrize("kernel", ["multiquadric", "gaussian"])
@pytest.mark.parametrize("lam", [0.0, 0.01, 0.5])
def test_matches_the_stated_formula(kernel, lam):
    centres, _ = _face_layout()
    points = _points(300, 11)
    d = _displacements(len(centres), 11)
    y = VolumeMorph(centres, points, kernel=kernel, lam=lam).apply(d)
    expected = _reference(centres, points, d, kernel, lam)
    assert np.abs(y - expected).max() < 1e-4


def test_regularisation_damps_the_non_affine_part():
    """The sign choice: with H - lambda I the multiquadric's departure from the best affine fit
    shrinks steadily as lam grows (to the fit itself as lam -> infinity); with the paper's
    H + lambda I it grows instead (by 7 % at lam = 0.01 here, and without bound where the
    system turns singular, first near lam = 0.048)."""
    centres, _ = _face_layout()
    d = _displacements(len(centres), 12)
    rows = np.hstack([centres.astype(np.float64), np.ones((len(centres), 1))])
    affine_fit = rows @ np.linalg.lstsq(rows, d.astype(np.float64), rcond=None)[0]
    departure = []
    for lam in (0.0, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 1e4):
        y = VolumeMorph(centres, centres, lam=lam).apply(d)
        departure.append(float(np.linalg.norm(y - centres - affine_fit)))
    assert all(a > b for a, b in zip(departure, departure[1:])), departure
    assert departure[-1] < 1e-3 * departure[0]


def test_mirror_symmetry():
    centres, mirror = _face_layout()
    points = _points(400, 5)
    n = len(points) // 2
    point_mirror = np.concatenate([np.arange(n) + n, np.arange(n)])
    d = _displacements(len(centres), 6).astype(np.float64)
    d = 0.5 * (d + d[mirror] @ MIRROR)  # d[mirror[i]] == MIRROR d[i]
    d = d.astype(np.float32)
    np.testing.assert_array_equal(d[mirror], d @ MIRROR)
    for kernel in ("multiquadric", "gaussian"):
        morph = VolumeMorph(centres, points, kernel=kernel)
        y = morph.apply(d)
        assert np.abs(y - points).max() > 1.0  # the points do move
        tolerance = _rounding_bound(morph, d, y)
        tolerance = tolerance + tolerance[point_mirror]
        assert (np.abs(y[point_mirror] - y @ MIRROR) <= tolerance).all()


@pytest.mark.parametrize("kernel", ["multiquadric", "gaussian"])
def test_lambda_is_relative_so_units_do_not_matter(kernel):
    """The same face in metres morphs like the face in millimetres (lam is relative)."""
    centres, _ = _face_layout()
    points = _points(300, 7)
    d = _displacements(len(centres), 7)
    in_mm = VolumeMorph(centres, points, kernel=kernel).apply(d) - points
    metre = np.float32(1e-3)
    in_m = VolumeMorph(centres * metre, points * metre, kernel=kernel).apply(d * metre)
    moved_m = (in_m - points * metre) / metre
    assert np.abs(in_mm).max() > 1.0
    np.testing.assert_allclose(moved_m, in_mm, atol=1e-3)


def test_gaussian_decays_to_zero_far_away():
    centres, _ = _face_layout()
    far = np.array([[0, 0, -2000], [3000, 0, 0], [0, -1500, 500]], np.float32)
    morph = VolumeMorph(centres, far, kernel="gaussian")
    d = _displacements(len(centres), 8)
    assert np.abs(morph.apply(d) - far).max() < 1e-6 * np.abs(d).max()


def test_at_shares_the_fit():
    centres, _ = _face_layout()
    points = _points(200, 9)
    morph = VolumeMorph(centres, points)
    d = _displacements(len(centres), 9)
    np.testing.assert_array_equal(morph.at(points).apply(d), morph.apply(d))
    few = points[:7]
    np.testing.assert_array_equal(morph.at(few).apply(d), morph.apply(d)[:7])
    assert morph.apply(d).shape == (len(points), 3)  # the original is unchanged
    with pytest.raises(ValueError):
        morph.weights[0, 0] = 1.0  # precomputation is read-only


def test_bad_input_raises_clear_errors():
    centres, _ = _face_layout()
    points = _points(10, 10)
    cases = [
        (dict(centres=centres[:, :2]), "centres: expected shape"),
        (dict(centres=centres.astype(np.int32)), "centres: expected float32 or float64"),
        (dict(centres=centres.tolist()), "centres: expected a numpy array"),
        (dict(centres=np.where(np.arange(31)[:, None] == 4, np.nan, centres)), "centres: .*NaN"),
        (dict(centres=np.concatenate([centres, centres[3:4]])), r"centres: rows 3 and 31 are"),
        (dict(centres=centres[:1]), "centres: need at least 2"),
        (dict(centres=centres * np.float32([1, 1, 0])), "centres: all lie in one plane"),
        (dict(points=points[:, :1]), "points: expected shape"),
        (dict(points=np.full((2, 3), np.inf, np.float32)), "points: .*infinity"),
        (dict(kernel="thin_plate"), "kernel: expected one of"),
        (dict(lam=-0.1), "lam: expected a finite number >= 0"),
        (dict(lam=float("nan")), "lam: expected a finite number >= 0"),
        (dict(lam="0.01"), "lam: expected a real number"),
        (dict(lam=True), "lam: expected a real number"),
    ]
    for change, message in cases:
        args = dict(centres=centres, points=points) | change
        with pytest.raises(ValueError, match=message):
            VolumeMorph(**args)
    # coplanar centres are fine for the Gaussian, which has no affine term
    VolumeMorph(centres * np.float32([1, 1, 0]), points, kernel="gaussian")
    morph = VolumeMorph(centres, points)
    d = np.zeros((31, 3), np.float32)
    for bad, message in [
        (d[:30], r"displacements: expected shape \(31, 3\)"),
        (d.astype(np.int64), "displacements: expected float32 or float64"),
        (d.tolist(), "displacements: expected a numpy array"),
        (np.where(d == 0, np.nan, d), "displacements: .*NaN"),
    ]:
        with pytest.raises(ValueError, match=message):
            morph.apply(bad)
    with pytest.raises(ValueError, match="points: expected shape"):
        morph.at(points[:, :2])


# --------------------------------------------------------------- the real head scan

# The scan is in arbitrary units (about 8.6 wide, shoulders included). At 48 mm a unit the
# outer eye corners found below are 90 mm apart and the mouth corners 47 mm: adult sizes.
MM_PER_UNIT = 48.0


def _head_centres(v: np.ndarray) -> tuple[dict[int, int], list[int]]:
    """Pick 18 feature vertices (keyed by iBUG index) and 13 phantom vertices on the scan.

    Rules (v in mm, +z out of the face, y up):
    - "surface seen from the front at (x, y)": of the 6 vertices nearest (x, y) in the xy plane
      among those within 60 mm of the nose tip's depth, the front-most one;
    - nose tip (30): the front-most vertex; the midline is x = its x; along the midline profile
      z(y) (1-mm steps): nose bridge (27) = deepest point 15-60 mm above the tip; subnasale (33)
      = deepest 5-25 mm below; upper lip (51) = front-most in the 20 mm below the subnasale;
      mouth slit = deepest in the 15 mm below that; lower lip (57) = front-most in the 15 mm
      below the slit; chin (8) = front-most 10-50 mm below the lower lip;
    - at typical adult offsets from the midline, surface points at eye height (8 mm below the
      bridge): eye corners 36/39/42/45 at x = -47, -16, 16, 47 mm; nostrils 31/35 at +-13 mm,
      3 mm above the subnasale; mouth corners 48/54 at +-25 mm at the slit's height; brows
      19/21/22/24 at x = -30, -12, 12, 30 mm, 25/20/20/25 mm above the eyes;
    - 13 phantoms: surface points on an ellipse (semi-axes 70 mm wide, 95 mm tall) around the
      middle of eyes and chin, evenly spaced in angle from the top.
    """
    tip = int(np.argmax(v[:, 2]))
    x0, y0, z0 = v[tip]
    front = np.flatnonzero(v[:, 2] > z0 - 60)

    def surface(x: float, y: float) -> int:
        near = front[np.argsort(np.hypot(v[front, 0] - x, v[front, 1] - y))[:6]]
        return int(near[np.argmax(v[near, 2])])

    ys = np.arange(-90.0, 71.0)
    profile = np.array([v[surface(x0, y0 + y), 2] for y in ys])

    def along(lo: float, hi: float, pick) -> float:
        inside = (ys >= lo) & (ys <= hi)
        return float(ys[inside][pick(profile[inside])])

    bridge = along(15, 60, np.argmin)
    subnasale = along(-25, -5, np.argmin)
    upper_lip = along(subnasale - 20, subnasale - 3, np.argmax)
    slit = along(upper_lip - 15, upper_lip - 2, np.argmin)
    lower_lip = along(slit - 15, slit - 2, np.argmax)
    chin = along(lower_lip - 50, lower_lip - 10, np.argmax)
    eyes = bridge - 8
    offsets = {
        27: (0, bridge), 33: (0, subnasale), 51: (0, upper_lip), 57: (0, lower_lip), 8: (0, chin),
        36: (-47, eyes), 39: (-16, eyes), 42: (16, eyes), 45: (47, eyes),
        31: (-13, subnasale + 3), 35: (13, subnasale + 3), 48: (-25, slit), 54: (25, slit),
        19: (-30, eyes + 25), 21: (-12, eyes + 20), 22: (12, eyes + 20), 24: (30, eyes + 25),
    }
    features = {30: tip} | {k: surface(x0 + dx, y0 + dy) for k, (dx, dy) in offsets.items()}
    middle = (eyes + chin) / 2
    angles = np.pi / 2 + np.linspace(0, 2 * np.pi, 13, endpoint=False)
    phantoms = [surface(x0 + 70 * np.cos(a), y0 + middle + 95 * np.sin(a)) for a in angles]
    return features, phantoms


def _face_normals(v: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (v[triangles[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def test_expression_on_the_real_head_scan(shared_data):
    """Smile + jaw drop + brow raise on the Lee Perry-Smith scan: smooth, no fold-over, local.

    The rigid features and the phantoms stay; mouth corners go 3 mm up and 2 mm out, the
    upper lip 1 mm up, the lower lip 4 mm down, the chin 6 mm down and 1 mm back, the brows
    2-3 mm up.
    """
    from facewire.models.gltf import read_glb

    scan = read_glb(shared_data / "meshes/lee-perry-smith/LeePerrySmith.glb",
                    mm_per_unit=MM_PER_UNIT)
    v = scan.positions
    features, phantoms = _head_centres(v.astype(np.float64))
    assert len(set(features.values()) | set(phantoms)) == 31  # 31 distinct vertices
    order = list(features) + [None] * len(phantoms)
    centres = v[list(features.values()) + phantoms]
    moves = {48: (-2, 3, 0), 54: (2, 3, 0), 51: (0, 1, 0), 57: (0, -4, 0), 8: (0, -6, -1),
             19: (0, 3, 0), 24: (0, 3, 0), 21: (0, 2, 0), 22: (0, 2, 0)}
    d = np.zeros((31, 3), np.float32)
    for k, move in moves.items():
        d[order.index(k)] = move
    largest = np.linalg.norm(d, axis=1).max()

    morph = VolumeMorph(centres, v)
    y = morph.apply(d).astype(np.float64)
    moved = np.linalg.norm(y - v, axis=1)

    # The centres follow their displacements up to the (default) regularisation.
    at_centres = np.linalg.norm(y[list(features.values()) + phantoms] - centres - d, axis=1)
    assert at_centres.max() < 0.1 * largest

    # No fold-over: every triangle keeps its orientation.
    before = _face_normals(v.astype(np.float64), scan.triangles)
    after = _face_normals(y, scan.triangles)
    assert ((before * after).sum(axis=1) > 0).all()

    # No amplification anywhere on the head.
    assert moved.max() < 1.25 * largest

    # Inside the face (vertices nearer a feature than a phantom) the motion fades with the
    # distance to the nearest moving centre.
    def nearest(points: np.ndarray) -> np.ndarray:
        p = points.astype(np.float64)
        return np.linalg.norm(v[:, None, :] - p[None, :, :], axis=-1).min(axis=1)

    moving = centres[[order.index(k) for k in moves]]
    inside = nearest(centres[:18]) < nearest(centres[18:])
    to_moving = nearest(moving)
    bands = [(0, 10), (10, 20), (20, 30), (30, 45)]
    means = [moved[inside & (to_moving >= lo) & (to_moving < hi)].mean() for lo, hi in bands]
    assert all(a > b for a, b in zip(means, means[1:])), means
    assert means[-1] < 0.25 * means[0], means
