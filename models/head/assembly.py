"""The generic head assembled: the half skin and its inserts, mirrored and welded into a Mesh.

The left half (x >= 0) is the skin of ``halfskin``, the socket cup behind its eye opening,
half of the mouth cavity behind its lip line and the left eyeball (``inserts``). Its midline
vertices (x = 0, but for the seam down the back of the head) are shared by both halves; every
other vertex is repeated on the right at (-x, y, z) with ``u -> 2 a - u``, a being the u of
the mirror axis of its texture part (0.4 for the skin and the sockets, the mouth disc's
centre, midway between the two eye discs), and every triangle is repeated with its winding
reversed; the right eyeball's triangles are tagged RIGHT_EYEBALL.

Landmarks and phantoms: ``Mesh.landmarks[i]`` is the vertex of iBUG point i (0-based). Eye
(36-47) and inner-lip (60-67) points are vertices of the eyelid margins and lip lines; brows,
nose, nostrils and outer lips are the skin points seen straight from the front at designed
(x, y); the jaw line (0-16) lies on the frontal silhouette of the face (``features``). A
right-side point is the mirror image of its left partner (``models.landmarks.MIRROR``).
``Mesh.phantoms`` follow ``models.landmarks.PHANTOM_NAMES``, the ``_right`` ones mirrored from
the ``_left`` ones.

``mirror_map()`` gives, for each vertex, the vertex at its mirror image: an involution with
exactly mirrored positions; midline vertices map to themselves and the two copies of a seam
vertex on the back of the head to each other.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from facewire.models.head.halfskin import HalfSkin, half_skin
from facewire.models.head.inserts import eye_socket, eyeball, mouth_cavity
from facewire.models.head.tags import skin_tags
from facewire.models.head.uvlayout import EYE_UV, MOUTH_UV, MOUTH_UV_RADIUS, SKIN_U_MAX, skin_uv
from facewire.models.landmarks import MIRROR, N_LANDMARKS, PHANTOM_NAMES
from facewire.models.mesh import Mesh, Tag


@dataclass(frozen=True)
class _Built:
    mesh: Mesh
    mirror: np.ndarray


class _LeftHalf:
    """The left half's parts in order: points (N, 3) with their uv (N, 2), the u of the mirror
    axis of their texture part (N,) and whether the right half shares them (N,); triangles
    (M, 3) with their tags (M,)."""

    def __init__(self) -> None:
        self.points: list[np.ndarray] = []
        self.uv: list[np.ndarray] = []
        self.axis: list[np.ndarray] = []
        self.shared: list[np.ndarray] = []
        self.triangles: list[np.ndarray] = []
        self.tags: list[np.ndarray] = []

    def add_points(self, points: np.ndarray, uv: np.ndarray, axis: float,
                   shared: np.ndarray) -> int:
        """Adds points (K, 3) and returns the index of the first."""
        start = sum(len(x) for x in self.points)
        self.points.append(points)
        self.uv.append(uv)
        self.axis.append(np.full(len(points), axis))
        self.shared.append(shared)
        return start

    def add_triangles(self, triangles: np.ndarray, tag: int | np.ndarray) -> None:
        self.triangles.append(triangles)
        self.tags.append(np.broadcast_to(np.asarray(tag, dtype=np.uint8), (len(triangles),)))


def _add_skin(left: _LeftHalf, half: HalfSkin) -> np.ndarray:
    """The skin, its midline (but the seam) on the mirror axis; returns its uv (N, 2)."""
    seam = half.midline & (half.dirs[:, 2] < 0.0)
    uv = skin_uv(half.dirs)
    uv[half.midline & ~seam, 0] = 0.5 * SKIN_U_MAX
    left.add_points(half.points, uv, 0.5 * SKIN_U_MAX, half.midline & ~seam)
    left.add_triangles(half.triangles, skin_tags(half.points[half.triangles].mean(axis=1)))
    return uv


def _add_socket(left: _LeftHalf, half: HalfSkin, uv: np.ndarray) -> None:
    """The socket cup, its rings mapped into the eye opening's own (empty) area of the skin
    texture ``uv`` (N, 2)."""
    margin = half.margin
    sock_p, sock_w, sock_t = eye_socket(half.points[margin])
    hole_uv = uv[margin].mean(axis=0)
    ring_uv = np.concatenate([np.tile(uv[margin], (5, 1)), [hole_uv]])
    sock_uv = (1.0 - sock_w[:, None]) * ring_uv + sock_w[:, None] * hole_uv
    start = left.add_points(sock_p, sock_uv, 0.5 * SKIN_U_MAX, np.zeros(len(sock_p), bool))
    local = np.concatenate([margin, start + np.arange(len(sock_p))])
    left.add_triangles(local[sock_t], Tag.SKIN)


def _add_cavity(left: _LeftHalf, half: HalfSkin) -> None:
    """The mouth cavity: its own copy of the lip line (a texture seam), its own texture disc."""
    lip = np.concatenate([half.lip_upper, half.lip_lower])
    cav_p, cav_polar, cav_t = mouth_cavity(half.points[lip])
    cu, cv = MOUTH_UV
    cav_uv = np.column_stack([cu + MOUTH_UV_RADIUS * cav_polar[:, 0] * np.cos(cav_polar[:, 1]),
                              cv + 2 * MOUTH_UV_RADIUS * cav_polar[:, 0] * np.sin(cav_polar[:, 1])])
    on_mid = cav_p[:, 0] == 0.0
    cav_uv[on_mid, 0] = cu
    start = left.add_points(cav_p, cav_uv, cu, on_mid)
    left.add_triangles(start + cav_t, Tag.MOUTH_INTERIOR)


def _add_eyeball(left: _LeftHalf) -> None:
    eye_p, eye_uv, eye_t = eyeball()
    start = left.add_points(eye_p, eye_uv, 0.5 * (EYE_UV["left"][0] + EYE_UV["right"][0]),
                            np.zeros(len(eye_p), bool))
    left.add_triangles(start + eye_t, Tag.LEFT_EYEBALL)


@dataclass(frozen=True)
class _Whole:
    """Both halves: the left half's arrays followed by the right half's copies."""

    vertices: np.ndarray   # (N, 3)
    uv: np.ndarray         # (N, 2)
    triangles: np.ndarray  # (M, 3)
    tags: np.ndarray       # (M,)
    right: np.ndarray      # (L,) the vertex at the mirror image of each left-half vertex
    mirror: np.ndarray     # (N,) the vertex at the mirror image of each vertex


def _mirrored(left: _LeftHalf) -> _Whole:
    """The left half and its mirror image, welded along the shared midline vertices."""
    P, UV, A, S = (np.concatenate(x) for x in (left.points, left.uv, left.axis, left.shared))
    T, G = np.concatenate(left.triangles), np.concatenate(left.tags)
    if np.any(P[S, 0] != 0.0) or np.any(UV[S, 0] != A[S]):
        raise RuntimeError("head: a shared midline vertex is off the mirror plane")
    n = len(P)
    other = np.flatnonzero(~S)
    right = np.arange(n)
    right[other] = n + np.arange(len(other))
    Pr = P[other] * np.array([-1.0, 1.0, 1.0])
    UVr = np.column_stack([2.0 * A[other] - UV[other, 0], UV[other, 1]])
    Gr = G.copy()
    Gr[G == Tag.LEFT_EYEBALL] = Tag.RIGHT_EYEBALL
    return _Whole(vertices=np.concatenate([P, Pr]), uv=np.concatenate([UV, UVr]),
                  triangles=np.concatenate([T, right[T][:, ::-1]]), tags=np.concatenate([G, Gr]),
                  right=right, mirror=np.concatenate([right, other]))


def _named_vertices(half: HalfSkin, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The landmark (68,) and phantom (13,) vertices; ``right`` (L,) as in ``_Whole``."""
    landmarks = np.zeros(N_LANDMARKS, dtype=np.int64)
    for i in range(N_LANDMARKS):
        if i in half.named:
            landmarks[i] = half.named[i]
        else:
            landmarks[i] = right[half.named[int(MIRROR[i])]]
    phantoms = []
    for name in PHANTOM_NAMES:
        if name.endswith("_right"):
            phantoms.append(right[half.named[name[: -len("_right")] + "_left"]])
        else:
            phantoms.append(half.named[name])
    return landmarks, np.array(phantoms, np.int32)


def _assemble() -> _Built:
    half = half_skin()
    left = _LeftHalf()
    uv = _add_skin(left, half)
    _add_socket(left, half, uv)
    _add_cavity(left, half)
    _add_eyeball(left)
    whole = _mirrored(left)
    landmarks, phantoms = _named_vertices(half, whole.right)
    mesh = Mesh(vertices=whole.vertices.astype(np.float32),
                triangles=whole.triangles.astype(np.int32), uv=whole.uv.astype(np.float32),
                tags=whole.tags.astype(np.uint8), landmarks=landmarks.astype(np.int32),
                phantoms=phantoms)
    return _Built(mesh, whole.mirror.astype(np.int32))


@lru_cache(maxsize=1)
def _built() -> _Built:
    built = _assemble()
    for a in (built.mesh.vertices, built.mesh.triangles, built.mesh.uv, built.mesh.tags,
              built.mesh.landmarks, built.mesh.phantoms, built.mirror):
        a.setflags(write=False)
    return built


def generic_head() -> Mesh:
    """The generic head mesh (the package docstring); deterministic, built once per process.

    Returns:
        A new ``Mesh`` (fresh, writable arrays): vertices (N, 3) float32 mm, triangles (M, 3)
        int32, uv (N, 2) float32, tags (M,) uint8, landmarks (68,) int32, phantoms (13,)
        int32 in ``models.landmarks.PHANTOM_NAMES`` order.
    """
    m = _built().mesh
    return Mesh(vertices=m.vertices.copy(), triangles=m.triangles.copy(), uv=m.uv.copy(),
                tags=m.tags.copy(), landmarks=m.landmarks.copy(), phantoms=m.phantoms.copy())


def mirror_map() -> np.ndarray:
    """(N,) int32: for each vertex of ``generic_head()``, the vertex at its mirror image
    (x -> -x). An involution; midline vertices map to themselves, the two copies of a
    texture-seam vertex on the back of the head map to each other."""
    return _built().mirror.copy()
