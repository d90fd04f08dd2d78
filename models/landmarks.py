"""The iBUG 300-W 68-point landmark scheme, the 18 feature points, and landmark measures.

Indices are 0-based, in iBUG order (the tracker's output order). "Right" and "left" are the
person's own (as in ``models/mesh.py``): the person's right eye, points 36-41, appears on the
image's left on a frontal face.

Groups::

    jaw 0-16 (from the right ear down to the chin 8 and up to the left ear)
    right brow 17-21, left brow 22-26 (outer to inner end, then inner to outer)
    nose bridge 27-30 (root to tip), nostrils 31-35 (right wing, subnasale 33, left wing)
    right eye 36-41, left eye 42-47 (clockwise in the image from the corner nearer the
        image's left: 36 outer, 39 inner; 42 inner, 45 outer)
    outer lip 48-59 (48 right corner, 51 top middle, 54 left corner, 57 bottom middle)
    inner lip 60-67 (60 right corner, 62 top middle, 64 left corner, 66 bottom middle)

Feature points (docs/DESIGN.md §2): 9 rigid points for pose (eye corners 36, 39, 42, 45; nose bridge
27; nose tip 30; nostril wings 31, 35; subnasale 33) and 9 non-rigid points for expression
(brows 19, 21, 22, 24; mouth corners 48, 54; lip middles 51, 57; chin 8). The other 50 points
are never sent; they measure how well the receiver reconstructs the face (``HELD_OUT``).

``MIRROR[i]`` is the point that ``i`` becomes when the face is reflected left-right.

Measures:

- Eye aspect ratio (Soukupova and Cech 2016) of an eye with corners p1, p4 and lids
  p2, p3 (upper) and p6, p5 (lower): ``EAR = (|p2 - p6| + |p3 - p5|) / (2 |p1 - p4|)``;
  about 0.25-0.35 for an open eye, near 0 for a closed one.
- Outer-eye distance ``d = |x_36 - x_45|``, the normaliser of the 300-W benchmark.
- Normalised mean error of a prediction ``p`` against truth ``t`` over a point set ``S``:
  ``NME = mean_{i in S} |p_i - t_i| / d(t)``, per frame.
"""

from __future__ import annotations

import numpy as np


def _index(values: list[int] | range) -> np.ndarray:
    """A read-only int64 index array, so shared constants cannot be changed by accident."""
    a = np.array(list(values), dtype=np.int64)
    a.setflags(write=False)
    return a


N_LANDMARKS = 68

JAW = _index(range(0, 17))
RIGHT_BROW = _index(range(17, 22))
LEFT_BROW = _index(range(22, 27))
NOSE_BRIDGE = _index(range(27, 31))
NOSTRILS = _index(range(31, 36))
RIGHT_EYE = _index(range(36, 42))
LEFT_EYE = _index(range(42, 48))
OUTER_LIP = _index(range(48, 60))
INNER_LIP = _index(range(60, 68))

GROUPS: dict[str, np.ndarray] = {
    "jaw": JAW,
    "right_brow": RIGHT_BROW,
    "left_brow": LEFT_BROW,
    "nose_bridge": NOSE_BRIDGE,
    "nostrils": NOSTRILS,
    "right_eye": RIGHT_EYE,
    "left_eye": LEFT_EYE,
    "outer_lip": OUTER_LIP,
    "inner_lip": INNER_LIP,
}

RIGID = _index([36, 39, 42, 45, 27, 30, 31, 35, 33])
NONRIGID = _index([19, 21, 22, 24, 48, 54, 51, 57, 8])
FEATURES = _index([*RIGID, *NONRIGID])
HELD_OUT = _index(sorted(set(range(N_LANDMARKS)) - set(FEATURES.tolist())))


def _mirror() -> np.ndarray:
    """The left-right permutation from pairs of partners; unlisted points map to themselves."""
    pairs = [(i, 16 - i) for i in range(8)]  # jaw
    pairs += [(17 + k, 26 - k) for k in range(5)]  # brows, outer end to outer end
    pairs += [(31, 35), (32, 34)]  # nostrils
    pairs += [(36, 45), (37, 44), (38, 43), (39, 42), (40, 47), (41, 46)]  # eyes
    pairs += [(48, 54), (49, 53), (50, 52), (55, 59), (56, 58)]  # outer lip
    pairs += [(60, 64), (61, 63), (65, 67)]  # inner lip
    m = np.arange(N_LANDMARKS)
    for a, b in pairs:
        m[a], m[b] = b, a
    return _index(m.tolist())


MIRROR = _mirror()

# Phantom points: RBF centres around the face boundary that move rigidly with the head, so
# the morph leaves the edge of the face and the scalp in place. The head model gives each a
# vertex, in this order (``Mesh.phantoms``).
PHANTOM_NAMES: tuple[str, ...] = (
    "forehead_top",  # hairline, on the midline
    "forehead_right",  # hairline above the outer end of the right brow
    "forehead_left",
    "temple_right",
    "temple_left",
    "cheekbone_right",  # outer end of the zygomatic arch, in front of the ear
    "cheekbone_left",
    "jaw_angle_right",  # gonion
    "jaw_angle_left",
    "jaw_right",  # on the mandible below the mouth corner, just outside the jaw line
    "jaw_left",
    "under_chin",  # submental point, on the midline
    "crown",  # top of the head, on the midline
)
N_PHANTOMS = len(PHANTOM_NAMES)


def _phantom_mirror() -> np.ndarray:
    """Left-right permutation of the phantom points, from their names."""
    index = {name: i for i, name in enumerate(PHANTOM_NAMES)}
    swap = {"_right": "_left", "_left": "_right"}
    m = []
    for name in PHANTOM_NAMES:
        partner = name
        for a, b in swap.items():
            if name.endswith(a):
                partner = name[: -len(a)] + b
        m.append(index[partner])
    return _index(m)


PHANTOM_MIRROR = _phantom_mirror()


def _check_points(name: str, points: np.ndarray, batch: bool) -> np.ndarray:
    """Validate a (68, 2) (or (..., 68, 2) when ``batch``) array of finite numbers."""
    a = np.asarray(points)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{name}: expected numbers, got dtype {a.dtype}")
    ok = a.shape[-2:] == (N_LANDMARKS, 2) and (batch or a.ndim == 2)
    if not ok:
        want = "(..., 68, 2)" if batch else "(68, 2)"
        raise ValueError(f"{name}: expected shape {want}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN or infinity")
    return a


def eye_aspect_ratio(points: np.ndarray) -> np.ndarray:
    """Eye aspect ratio of each eye (formula in the module docstring).

    Args:
        points: (68, 2) landmarks, pixels.

    Returns:
        (2,) float32: (right eye, left eye); 0 for an eye whose corners coincide.
    """
    p = _check_points("points", points, batch=False).astype(np.float32)
    ear = np.zeros(2, dtype=np.float32)
    for k, eye in enumerate((RIGHT_EYE, LEFT_EYE)):
        p1, p2, p3, p4, p5, p6 = p[eye]
        width = np.linalg.norm(p1 - p4)
        if width > 0:
            ear[k] = (np.linalg.norm(p2 - p6) + np.linalg.norm(p3 - p5)) / (2 * width)
    return ear


def outer_eye_distance(points: np.ndarray) -> np.ndarray:
    """Distance between the outer eye corners 36 and 45.

    Args:
        points: (..., 68, 2) landmarks.

    Returns:
        (...) float64 distances (0-d for one face).
    """
    p = _check_points("points", points, batch=True).astype(np.float64)
    return np.linalg.norm(p[..., 36, :] - p[..., 45, :], axis=-1)


def nme(pred: np.ndarray, truth: np.ndarray, indices: np.ndarray | None = None) -> np.ndarray:
    """Normalised mean error per face: mean point error over ``indices`` / outer-eye distance.

    Args:
        pred: (..., 68, 2) predicted landmarks.
        truth: (..., 68, 2) reference landmarks, same shape; outer-eye distance must be > 0.
        indices: (K,) distinct point indices in [0, 68) to average over; all 68 when None.

    Returns:
        (...) float64 NME per face (0-d for one face); multiply by 100 for percent.
    """
    p = _check_points("pred", pred, batch=True).astype(np.float64)
    t = _check_points("truth", truth, batch=True).astype(np.float64)
    if p.shape != t.shape:
        raise ValueError(f"pred and truth: shapes differ, {p.shape} vs {t.shape}")
    idx = np.arange(N_LANDMARKS) if indices is None else np.asarray(indices)
    if idx.ndim != 1 or idx.size == 0 or idx.dtype.kind not in "iu":
        raise ValueError(f"indices: expected a non-empty 1-D integer array, got {idx!r}")
    if idx.min() < 0 or idx.max() >= N_LANDMARKS or np.unique(idx).size != idx.size:
        raise ValueError(f"indices: expected distinct values in [0, {N_LANDMARKS})")
    d = outer_eye_distance(t)
    if np.any(d <= 0):
        raise ValueError("truth: outer eye corners 36 and 45 coincide; NME is undefined")
    err = np.linalg.norm(p[..., idx, :] - t[..., idx, :], axis=-1).mean(axis=-1)
    return err / d
