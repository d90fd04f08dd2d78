"""A head mesh: triangles with UVs, triangle tags, and the vertices that carry landmarks.

Frames and units (docs/DESIGN.md §2): model space in mm, right-handed, x toward the person's
left (image right on a frontal face), y up, z out of the face toward the camera. Triangles
wind counter-clockwise seen from outside, so ``cross(b - a, c - a)`` points outward. UVs are
in [0, 1] with v up, as OpenGL samples them: the texel row of v in an H-row image is
``(1 - v) * H``.

"Left" and "right" in tag and region names are the person's own, as in anatomy: the person's
right eye is iBUG points 36-41, which appear on the image's left.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from facewire.models.arrays import check_array
from facewire.models.geometry import vertex_normals
from facewire.models.landmarks import N_LANDMARKS, N_PHANTOMS
from facewire.protocol.errors import FacewireError


class Tag(IntEnum):
    """What a triangle is, for the texture and deformation engines."""

    SKIN = 0
    RIGHT_EYEBALL = 1
    LEFT_EYEBALL = 2
    MOUTH_INTERIOR = 3
    EAR = 4
    SCALP = 5


class MeshError(FacewireError, ValueError):
    """A mesh's arrays are inconsistent; the message names the field."""


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh with the correspondences facewire needs.

    Attributes:
        vertices: (N, 3) float32, model space, mm.
        triangles: (M, 3) int32 vertex indices, counter-clockwise from outside.
        uv: (N, 2) float32 texture coordinates in [0, 1], v up.
        tags: (M,) uint8, a ``Tag`` per triangle.
        landmarks: (68,) int32, the vertex of each iBUG 300-W landmark (0-based order).
        phantoms: (13,) int32, the vertices of the phantom points around the face boundary.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    tags: np.ndarray
    landmarks: np.ndarray
    phantoms: np.ndarray

    def __post_init__(self) -> None:
        n = check_array("vertices", self.vertices, np.float32, (None, 3), MeshError)
        m = check_array("triangles", self.triangles, np.int32, (None, 3), MeshError)
        check_array("uv", self.uv, np.float32, (n, 2), MeshError)
        check_array("tags", self.tags, np.uint8, (m,), MeshError)
        check_array("landmarks", self.landmarks, np.int32, (N_LANDMARKS,), MeshError)
        check_array("phantoms", self.phantoms, np.int32, (N_PHANTOMS,), MeshError)
        for name in ("triangles", "landmarks", "phantoms"):
            idx = getattr(self, name)
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise MeshError(f"{name}: vertex index outside [0, {n})")
        if self.tags.size and self.tags.max() > max(Tag):
            raise MeshError(f"tags: unknown tag {int(self.tags.max())}")

    def vertex_normals(self) -> np.ndarray:
        """(N, 3) float32 unit normals: area-weighted mean of the adjacent face normals
        (``models.geometry.vertex_normals``)."""
        return vertex_normals(self.vertices.astype(np.float64), self.triangles)
