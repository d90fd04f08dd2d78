"""The animation rig of a person model: which centres drive the RBF morph, and how a frame moves.

The sender (to lift residuals and measure geometry) and the receiver (to deform the mesh)
both need "the morph of this model"; it is defined once, here.

Centres (M of them, in this order)
----------------------------------
- the 18 feature points (``models.landmarks.FEATURES``: 9 rigid, then 9 non-rigid) at their
  landmark vertices ``mesh.landmarks[FEATURES]``;
- the 13 phantom vertices ``mesh.phantoms`` around the face boundary;
- K anchors (``ANCHORS`` = 16 at most): vertices on the back and top of the scalp, the ears and
  the neck, far from the face.

Only the 9 non-rigid feature points are driven: the pose carries all rigid motion, so the
rigid feature points, the phantoms of the skull and the anchors always have zero displacement
(the mandible phantoms follow the chin, below). The anchors exist because Hardy's
multiquadric grows with distance: with the 31 face centres alone, a 5 mm mouth-corner move
drags the back of the head about 2 mm (measured on the generic head); with the anchors it
moves at most about 0.2 mm there.

Anchor selection (deterministic, from the mesh alone). Candidates are the vertices of SKIN,
SCALP and EAR triangles (never eyeballs or the mouth cavity) that lie

- behind the face, ``z < min_z`` of the 12 ring phantoms (all but the crown; the face looks
  along +z), or on the neck, more than ``NECK_BELOW`` mm below the lowest face centre; and
- at least ``ANCHOR_CLEARANCE`` mm from every face centre (an anchor next to a moving centre
  would pin the skin the face needs, and near-coincident centres condition the system badly).

From these, farthest-point sampling seeded with the 31 face centres picks each next anchor as
the candidate farthest from every centre chosen so far. Picks are made in mirror pairs so
that the rig is left-right symmetric on a symmetric mesh: a pick within ``MIDLINE`` mm of
the midsagittal plane x = 0 is first replaced by the candidate nearest its projection onto
that plane; the pick is then taken with the candidate nearest its mirror image ``(-x, y, z)``
(itself, on the midline). Sampling stops before a pair would exceed ``ANCHORS``, or when no
candidate is left (a mesh without a back of the head gets fewer, possibly no, anchors). The
generic head gets 15: back of the head, occiput, nape and neck, crown-side, ears, temples
behind the hairline.

Mandible phantoms (a departure from the paper, where all 13 phantoms move rigidly with the
head). Five phantoms sit on the lower jaw, which the chin belongs to: the jaw angles (gonion),
jaw_right/left (below the mouth corners) and under_chin (``MANDIBLE_PHANTOMS``). Held at zero
they pin the jaw line while the chin drops: measured on the held-out frames of four shared
clips (hdtf_katiehill, openface_default, lp_d3, lp_d0; slope of each tracked contour
point's vertical image motion, relative to the pose-only projection, against the chin's), the
tracker's contour points 4-6 and 10-12 follow the chin by 0.2-0.84 (0.4-0.73 at 5 and 11),
the rig with rigid phantoms by 0.01-0.44 (0.04-0.23 at 5 and 11; on lp_d0, where the mouth
opens wide, the lower lip's column even pushed them up, -0.13 to -0.24). So each mandible
phantom moves with the chin's residual, scaled by ``follow`` = its distance from the jaw's
hinge axis divided by the chin's: the mandible turns about the temporomandibular joints, and
a rotation moves a point in proportion to its distance from the axis. The axis is the line
through the two cheekbone phantoms (the outer end of the zygomatic arch, in front of the ear,
just above the joint). On the generic head ``follow`` is 0.56 at the jaw angles, 0.79 at
jaw_right/left and 0.85 under the chin; the direction is the chin's own (the packet carries
the chin's frontal-plane move only). With it the rig's contour follows by 0.34-0.74 at points
3-6 and 10-13 on hdtf_katiehill (tracker 0.37-0.84; before, 0.04-0.44).

Lips apart
----------
The mouth is a slit: its upper and lower lips touch at rest, and opening the mouth moves
them apart. A smooth field fitted to the lip middles 51 and 57 (and the chin) cannot tear
there: an inner-lip vertex lies between 51 and 57, a few mm from each, so it takes a blend
of both moves and the two inner lips move nearly together (on lp_d18, a yawn of 40 mm
between 51 and 57 parted the rendered lips by a few mm, and the mouth's interior never
showed). So the kernel, and only the kernel, measures distances in a space where the lips
lie ``MOUTH_GAP`` mm apart (``lips_apart``): every point below the slit (the mean height of
the upper and lower inner-lip landmarks 60-67 at its x, interpolated; outside their range
the end values), less than ``MOUTH_DEPTH`` behind the mouth corners and between them, moves
down by the gap, which grows from 0 at the corners (48, 54, which belong to both lips) to
its full size ``CORNER_RAMP`` mm inside them (smoothstep). The upper lip is then far from the
lower lip's centre and the lower lip far from the upper's, and each lip follows its own
centre. The chin, the jaw below the mouth and the mouth's interior below the slit move down
together in that space, so their distances to each other, and the jaw's to the chin, stay
what they are. The fitted displacements are added to the real vertices as before.

Per-frame math
--------------
``VolumeMorph`` (``models/morph.py``) gives the (N, M) matrix ``W`` of cardinal weights:
moving every centre by ``d`` (M, 3) moves vertex n to ``v_n + W[n] @ d``. Here ``d``
(``Rig.centre_displacements``) is zero except in the 9 rows of the non-rigid feature points,
which hold the residuals ``r`` (9, 3), and the rows of the mandible phantoms, ``follow_j r_chin``.
Hence, with ``B = W[:, cols]`` (N, 9) the columns of the non-rigid centres and the chin's
column plus ``sum_j follow_j W[:, phantom_j]``,

    morph(r) = v + B @ r,

which equals ``VolumeMorph.apply`` of the full displacement array for every vertex but the
eyeballs' (equal up to float32 summation order). One (N, 9) @ (9, 3) float32 product and one
add per frame.

Eyeballs do not deform and do not move: their rows of ``B`` are zero. An eyeball sits in
the bony orbit, which is part of the skull: expressions move the lids over it, not the eyeball
itself, so it stays rigid with the head and the pose carries it (gaze is a texture matter).
Bending it would distort the iris; translating it with the field (at its centre, or by the
field's mean over it) would make the iris drift with the brows and the mouth. The lids and
the socket cup around it (SKIN) still follow the field; under a strong expression (mouth
open 10 mm, chin down 8 mm, smile 4 mm, brows up 4 mm) the skin within 2 mm of an eyeball
moves toward it by at most 0.25 mm and keeps at least 0.03 mm of its 0.2 mm neutral gap
(tested; 0.17 and 0.08 mm before the mandible phantoms followed the chin: the jaw's pull
reaches the lower lids, 0.12 mm on average).

``landmarks(r)`` is ``v[L] + B[L] @ r`` for the 68 landmark vertices ``L``: the model's
landmarks after the morph, in model space.

Tangent frames (the packet's residual coordinates)
--------------------------------------------------
The packet carries each non-rigid point's residual as two numbers (u, v): a 2D image residual
lifted onto a surface has two degrees of freedom. ``tangents`` (9, 2, 3) holds, per point k
(``NONRIGID`` order), an orthonormal basis (t1_k, t2_k) of the plane through the point's
NEUTRAL position with normal n_k; the residual (u, v) of point k is the 3D model-space
displacement

    d_k = u t1_k + v t2_k,

``from_tangent`` computes it, and ``to_tangent`` is the orthogonal projection back,
(u, v) = (d . t1, d . t2) (exact for displacements in the plane, the normal component is
dropped otherwise). t1 is the model x axis projected onto the plane and normalised (the y axis
if x is within 0.1 % of the normal), t2 = n x t1, so (t1, t2, n) is right-handed.

n_k is the area-weighted vertex normal of the neutral mesh (copies of the vertex at the same
position, e.g. on a UV seam, welded) for the brows and the mouth corners, which slide over
the forehead and the cheeks. For the lip middles 51, 57 and the chin 8 (``FRONTAL_POINTS``)
it is the model's forward axis z. Why: those points move mostly up and down (the mouth
opens, the jaw drops), and on a mesh their surfaces face up or down: on the generic head the
chin's normal is (0, -0.98, 0.17), the lower lip's (0, -0.75, 0.66), the upper lip's
(0, 0.58, 0.81). A vertical move is then largely along the normal, which a tangent plane
cannot carry (the rig's own test expression, chin 8 mm down, would keep 1.4 mm of it), and
lifting a downward image move onto the chin's plane multiplies it by 1/0.17 along the plane,
toward the neck: a chin that drops 10 mm would be sent as 58 mm. With n = z the plane is the
face's frontal plane at the point, so a drop is carried as a drop.
"""

from __future__ import annotations

import numpy as np

from facewire.models.landmarks import FEATURES, NONRIGID, PHANTOM_NAMES, RIGID
from facewire.models.mesh import Mesh, Tag
from facewire.models.morph import VolumeMorph

ANCHORS = 16  # at most this many anchors
ANCHOR_CLEARANCE = 40.0  # mm from every face centre
NECK_BELOW = 25.0  # mm below the lowest face centre counts as neck
MIDLINE = 10.0  # mm: picks this close to x = 0 snap to the midline
N_RESIDUALS = len(NONRIGID)
FRONTAL_POINTS = (51, 57, 8)  # iBUG points whose lift plane faces the model's z (docstring)
WELD_MM = 1e-4  # vertices closer than this are copies of one vertex (UV seams)
# Phantoms on the lower jaw: they follow the chin (docstring, "Mandible phantoms").
MANDIBLE_PHANTOMS = ("jaw_angle_right", "jaw_angle_left", "jaw_right", "jaw_left", "under_chin")
HINGE_PHANTOMS = ("cheekbone_right", "cheekbone_left")  # the jaw's hinge axis runs through these
CHIN = 8
MOUTH_GAP = 40.0  # mm the lips are set apart in the kernel space (docstring, "Lips apart")
CORNER_RAMP = 10.0  # mm in from the mouth corners over which the gap grows to MOUTH_GAP
MOUTH_DEPTH = 60.0  # mm behind the mouth corners the kernel space still sets lips apart

# Columns of the non-rigid feature points among the centres: FEATURES lists RIGID first.
_NONRIGID_COLUMNS = np.arange(len(RIGID), len(FEATURES))
_CHIN_SLOT = int(np.flatnonzero(NONRIGID == CHIN)[0])


class Rig:
    """The RBF morph of one mesh driven by the 9 non-rigid feature residuals.

    Args:
        mesh: the person's (or the generic) head mesh, model space, mm.
        kernel: ``"multiquadric"`` (default) or ``"gaussian"``, as ``VolumeMorph``.
        lam: relative Tikhonov weight, as ``VolumeMorph`` (0.01: the paper's).

    Attributes:
        mesh: the mesh.
        anchors: (K,) int64 anchor vertex indices, K <= ``ANCHORS``.
        centres: (M,) int64 vertex indices of all centres: ``mesh.landmarks[FEATURES]``, then
            ``mesh.phantoms``, then ``anchors`` (M = 31 + K).
        field: the ``VolumeMorph`` of the centres, evaluated at every vertex, both in the
            kernel space (``lips_apart``).
        weights: (N, 9) float32, read-only: ``morph(r) == mesh.vertices + weights @ r``.
        eyeball_vertices: (E,) int64, the vertices of both eyeballs, which never move.
        tangents: (9, 2, 3) float32, read-only: per non-rigid point (``NONRIGID`` order) the
            orthonormal basis (t1, t2) of its lift plane (module docstring); the packet's
            residual (u, v) of point k is the displacement ``u t1_k + v t2_k``, mm.
        follow: (13,) float64, read-only: per phantom, the fraction of the chin's residual it
            moves by (``mandible_follow``; 0 for the phantoms of the skull).

    Raises:
        ValueError: not a Mesh, or the centres are degenerate (from ``VolumeMorph``).
    """

    def __init__(self, mesh: Mesh, kernel: str = "multiquadric", lam: float = 0.01) -> None:
        if not isinstance(mesh, Mesh):
            raise ValueError(f"mesh: expected a Mesh, got {type(mesh).__name__}")
        self.mesh = mesh
        face = np.concatenate([mesh.landmarks[FEATURES], mesh.phantoms]).astype(np.int64)
        self.anchors = _frozen(anchor_vertices(mesh))
        self.centres = _frozen(np.concatenate([face, self.anchors]))
        vertices = mesh.vertices
        apart = lips_apart(mesh, vertices)
        self.field = VolumeMorph(apart[self.centres], apart, kernel=kernel, lam=lam)
        self.follow = _frozen(mandible_follow(mesh))
        phantom_columns = len(FEATURES) + np.arange(len(mesh.phantoms))
        weights = self.field.weights[:, _NONRIGID_COLUMNS].copy()
        weights[:, _CHIN_SLOT] += (self.field.weights[:, phantom_columns]
                                   @ self.follow.astype(np.float32))
        self.eyeball_vertices = _frozen(
            _tagged_vertices(mesh, (Tag.RIGHT_EYEBALL, Tag.LEFT_EYEBALL)))
        weights[self.eyeball_vertices] = 0.0
        self.weights = _frozen(weights)
        self._neutral = _frozen(vertices.astype(np.float32, copy=True))
        self._landmark_weights = _frozen(weights[mesh.landmarks].copy())
        self._landmark_neutral = _frozen(self._neutral[mesh.landmarks].copy())
        self.tangents = _frozen(tangent_frames(mesh))

    def morph(self, residuals: np.ndarray) -> np.ndarray:
        """Deform the mesh by the non-rigid feature points' residuals.

        Args:
            residuals: (9, 3) float32 (float64 accepted and rounded) displacements, mm, model
                space, of the non-rigid feature points in ``NONRIGID`` order.

        Returns:
            (N, 3) float32 vertices, mm; exactly ``mesh.vertices`` for zero residuals.
        """
        out = self.weights @ _check_residuals(residuals)
        out += self._neutral
        return out

    def landmarks(self, residuals: np.ndarray) -> np.ndarray:
        """The 68 landmark vertices after ``morph(residuals)``.

        Args:
            residuals: (9, 3) float32 displacements, mm, as ``morph``.

        Returns:
            (68, 3) float32 positions, mm, model space, iBUG order.
        """
        out = self._landmark_weights @ _check_residuals(residuals)
        out += self._landmark_neutral
        return out

    def centre_displacements(self, residuals: np.ndarray) -> np.ndarray:
        """The displacement of every centre under ``residuals`` (module docstring).

        Args:
            residuals: (9, 3) float32 displacements, mm, as ``morph``.

        Returns:
            (M, 3) float32: ``residuals`` at the non-rigid feature points, ``follow_j`` times
            the chin's residual at phantom j, zero elsewhere; ``field.apply`` of it equals
            ``morph(residuals)`` except at the eyeballs.
        """
        r = _check_residuals(residuals)
        d = np.zeros((len(self.centres), 3), np.float32)
        d[_NONRIGID_COLUMNS] = r
        d[len(FEATURES): len(FEATURES) + len(self.follow)] = \
            self.follow[:, None] * r[_CHIN_SLOT]
        return d

    def from_tangent(self, uv: np.ndarray) -> np.ndarray:
        """Model-space displacements of the packet's tangent-frame residuals.

        Args:
            uv: (9, 2) finite float32 (float64 accepted) residuals (u, v), mm, NONRIGID order.

        Returns:
            (9, 3) float32 displacements ``u t1_k + v t2_k``, mm, model space.
        """
        uv = _check_array("uv", uv, (N_RESIDUALS, 2))
        return np.einsum("kc,kcj->kj", uv, self.tangents).astype(np.float32, copy=False)

    def to_tangent(self, d: np.ndarray) -> np.ndarray:
        """Project model-space displacements on the tangent frames.

        Args:
            d: (9, 3) finite float32 (float64 accepted) displacements, mm, NONRIGID order.

        Returns:
            (9, 2) float32 (u, v) = (d . t1, d . t2), mm; the normal component is dropped.
        """
        d = _check_array("d", d, (N_RESIDUALS, 3))
        return np.einsum("kj,kcj->kc", d, self.tangents).astype(np.float32, copy=False)


def lips_apart(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """The points in the morph's kernel space, where the lips lie ``MOUTH_GAP`` mm apart.

    Args:
        mesh: the neutral mesh (its inner-lip landmarks 60-67 and mouth corners 48, 54).
        points: (P, 3) model-space points, mm.

    Returns:
        (P, 3) float64: the points below the mouth's slit (module docstring, "Lips apart")
        moved down by the gap at their x, the others unchanged.
    """
    lm = mesh.vertices[mesh.landmarks].astype(np.float64)
    upper, lower = lm[[60, 61, 62, 63, 64]], lm[[60, 67, 66, 65, 64]]
    order = np.argsort(upper[:, 0])
    slit = np.interp(points[:, 0], upper[order, 0], 0.5 * (upper[order, 1] + lower[order, 1]))
    centre, half = 0.5 * (lm[48, 0] + lm[54, 0]), 0.5 * abs(lm[54, 0] - lm[48, 0])
    inside = np.clip((half - np.abs(points[:, 0] - centre)) / CORNER_RAMP, 0.0, 1.0)
    gap = MOUTH_GAP * inside * inside * (3.0 - 2.0 * inside)  # smoothstep to the corners
    front = points[:, 2] > min(lm[48, 2], lm[54, 2]) - MOUTH_DEPTH
    out = points.astype(np.float64, copy=True)
    out[:, 1] -= np.where((points[:, 1] < slit) & front, gap, 0.0)
    return out


def tangent_frames(mesh: Mesh) -> np.ndarray:
    """The lift planes' bases (t1, t2) of the 9 non-rigid points (module docstring).

    Args:
        mesh: the neutral mesh, model space, mm.

    Returns:
        (9, 2, 3) float32, rows t1 and t2 of each point in ``NONRIGID`` order.
    """
    v = mesh.vertices.astype(np.float64)
    a, b, c = (v[mesh.triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)  # length = twice the area: area-weighted sums
    out = np.zeros((N_RESIDUALS, 2, 3))
    for k, point in enumerate(NONRIGID):
        vertex = mesh.landmarks[point]
        if int(point) in FRONTAL_POINTS:
            n = np.array([0.0, 0.0, 1.0])
        else:
            copies = np.flatnonzero(np.linalg.norm(v - v[vertex], axis=1) < WELD_MM)
            n = face[np.isin(mesh.triangles, copies).any(axis=1)].sum(axis=0)
            length = np.linalg.norm(n)
            if length < 1e-12:
                raise ValueError(f"mesh: landmark {point} (vertex {vertex}) has no normal "
                                 f"(no triangle of non-zero area uses it)")
            n /= length
        t1 = np.array([1.0, 0.0, 0.0]) - n[0] * n
        if np.linalg.norm(t1) < 1e-3:
            t1 = np.array([0.0, 1.0, 0.0]) - n[1] * n
        t1 /= np.linalg.norm(t1)
        out[k] = t1, np.cross(n, t1)
    return out.astype(np.float32)


def mandible_follow(mesh: Mesh) -> np.ndarray:
    """Per phantom, the fraction of the chin's residual it follows (module docstring).

    ``MANDIBLE_PHANTOMS`` get their distance from the hinge axis (the line through the
    ``HINGE_PHANTOMS``) over the chin's (landmark 8), capped at 1; the others get 0.

    Args:
        mesh: the neutral mesh, model space, mm.

    Returns:
        (13,) float64, ``PHANTOM_NAMES`` order.

    Raises:
        ValueError: the hinge phantoms coincide, or the chin lies on the axis.
    """
    v = mesh.vertices.astype(np.float64)
    index = {name: i for i, name in enumerate(PHANTOM_NAMES)}
    a, b = (v[mesh.phantoms[index[name]]] for name in HINGE_PHANTOMS)
    axis = b - a
    length = np.linalg.norm(axis)
    if length < 1e-6:
        raise ValueError("mesh: the cheekbone phantoms coincide; no jaw hinge axis")
    axis /= length

    def distance(p: np.ndarray) -> float:
        q = p - a
        return float(np.linalg.norm(q - (q @ axis) * axis))

    chin = distance(v[mesh.landmarks[CHIN]])
    if chin < 1e-6:
        raise ValueError("mesh: the chin lies on the jaw hinge axis")
    out = np.zeros(len(mesh.phantoms))
    for name in MANDIBLE_PHANTOMS:
        out[index[name]] = min(1.0, distance(v[mesh.phantoms[index[name]]]) / chin)
    return out


def anchor_vertices(mesh: Mesh, count: int = ANCHORS) -> np.ndarray:
    """The anchor vertices of a mesh (module docstring: candidates, then paired sampling).

    Args:
        mesh: the head mesh.
        count: at most this many anchors, >= 0.

    Returns:
        (K,) int64 vertex indices, K <= count, in the order picked.
    """
    if count < 0:
        raise ValueError(f"count: expected >= 0, got {count}")
    v = mesh.vertices.astype(np.float64)
    face = v[np.concatenate([mesh.landmarks[FEATURES], mesh.phantoms])]
    ring_z = v[mesh.phantoms[:-1], 2].min()  # the crown (last) sits on top, not on the ring
    candidates = _tagged_vertices(mesh, (Tag.SKIN, Tag.SCALP, Tag.EAR))
    p = v[candidates]
    clearance = np.full(len(p), np.inf)
    for centre in face:
        clearance = np.minimum(clearance, np.linalg.norm(p - centre, axis=1))
    behind = (p[:, 2] < ring_z) | (p[:, 1] < face[:, 1].min() - NECK_BELOW)
    keep = behind & (clearance >= ANCHOR_CLEARANCE)
    candidates, p, near = candidates[keep], p[keep], clearance[keep]
    picked: list[int] = []
    while len(p) and near.max() > 0:
        best = int(np.argmax(near))
        i = best
        if abs(p[i, 0]) < MIDLINE:  # snap to the midline
            i = int(np.argmin(np.linalg.norm(p - p[i] * (0.0, 1.0, 1.0), axis=1)))
        mirror = int(np.argmin(np.linalg.norm(p - p[i] * (-1.0, 1.0, 1.0), axis=1)))
        group = list(dict.fromkeys(g for g in (i, mirror) if near[g] > 0))  # one on the midline
        if len(picked) + len(group) > count:
            break
        for g in group:
            picked.append(g)
            near = np.minimum(near, np.linalg.norm(p - p[g], axis=1))
        near[best] = 0.0  # taken, or its snapped or mirrored partner was taken already
    return candidates[np.array(picked, dtype=np.int64)]


def _tagged_vertices(mesh: Mesh, tags: tuple[Tag, ...]) -> np.ndarray:
    """(K,) int64 sorted vertices of the triangles carrying any of ``tags``."""
    mask = np.isin(mesh.tags, np.array(tags, dtype=np.uint8))
    return np.unique(mesh.triangles[mask]).astype(np.int64)


def _check_residuals(r: np.ndarray) -> np.ndarray:
    """Validate (9, 3) finite float32/float64 residuals; return them as float32."""
    return _check_array("residuals", r, (N_RESIDUALS, 3))


def _check_array(name: str, r: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Validate a finite float32/float64 array of ``shape``; return it as float32."""
    if not isinstance(r, np.ndarray):
        raise ValueError(f"{name}: expected a numpy array, got {type(r).__name__}")
    if r.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {r.shape}")
    if r.dtype not in (np.float32, np.float64):
        raise ValueError(f"{name}: expected float32 or float64, got {r.dtype.name}")
    if not np.isfinite(r).all():
        raise ValueError(f"{name}: contains NaN or infinity")
    return r.astype(np.float32, copy=False)


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a`` made read-only (the precomputation must not be edited behind our back)."""
    a.setflags(write=False)
    return a
