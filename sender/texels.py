"""A region's texels read from a camera frame: the layer images of an appearance state.

A layer image covers one area of a region (its UV rectangle, ``models.regions.place``) in
the model's texture. Every texel of it is a point on the mesh's surface: the triangle its
centre lies in, in UV, and the barycentric weights (a, b, c) of that centre there, which
give its model-space point P = a V_i + b V_j + c V_k and its normal, the interpolated
vertex normals (averaged over vertices that share a position, so both sides of a UV seam
agree). Read from a frame with the pose and residuals the sender sent:

    P' = P + W r    (the rig's morph, ``sender.appearance.SurfacePoints``)
    (x, y) = project(R P' + t)   and the frame read there bilinearly,

with no occlusion test by default (a closed mouth paints its lips into the hidden mouth
interior, which is what the sender's camera sees there). A texel is *seen* when its
triangle exists, its normal, rotated into the camera frame, faces the camera (z > 0.05) and
(x, y) lies on the image; others keep the base texture. With ``occlusion``, a texel is seen
only when no other texel of the area lies in front of it: the seen texels' distances
d = -Z are kept per ``DEPTH_BIN`` x ``DEPTH_BIN`` pixel bin as their least, that least
spread over the 3 x 3 bins around (a texel's own surface leaves no gaps between bins), and a
texel more than ``DEPTH_TOLERANCE`` behind the least at its bin is hidden (the neck below
the chin, a cheek behind the nose: the healing's cells, which the enrollment's depth test
also hides, read the chin there, and patched it into the neck).

Where the texels' surface comes from: enrollment has the model's UV surface from its
rasteriser (``sender.enroll.texture.uv_surface``, OpenGL) and passes each area's part of
it; the camera host need not have OpenGL, so ``area_surface`` finds the same triangles,
weights and normals on the CPU, over the one area only: for every triangle whose UV box
meets the area, the barycentric weights of the texel centres in its UV box, a texel taking
the first triangle that holds it (the layout is one-to-one; within 1e-9, so a centre on a
shared edge is inside both, which give it the same point).

Exposure and shading (``state_layers``). Each layer is scaled per colour channel by
g = sum(base) / sum(layer) over the border ramp (``models.regions.ramp_mask`` < 1) of the
region's last area (clipped to [0.5, 2]), so an exposure change between frames leaves no
step at the border; the last area is the region's only one, or for an eyelid the lid skin,
the same skin in every state (the eyeball's border under an open lid is eyeball, and
matching a closed lid to it darkened the closed states). The skin regions' layers
(``SHADED``: forehead, brow furrow) then take the base texture's broad shading: each is
multiplied by the smooth field f = (G*(B w) / G*w + 1) / (G*(g L w) / G*w + 1), clipped to
``SHADING_LIMITS``, G a Gaussian of sigma ``SHADING_SIGMA`` times the area's shorter side,
B the base, g L the scaled layer, w 1 on the texels read. A wrinkle, finer than G, stays;
a frame's own light on the skin (a highlight, the shadow of hair), broader than G, goes
(the measurements: ``sender.enroll.layers``, step 4).
"""

from __future__ import annotations

import cv2
import numpy as np

from facewire.models.geometry import Intrinsics, vertex_normals
from facewire.models.mesh import Mesh
from facewire.models.regions import ramp_mask
from facewire.models.rig import Rig
from facewire.models.texelgrid import texel_rect
from facewire.sender.appearance import SurfacePoints, bilinear, project

SHADED = ("forehead", "brow_furrow")  # skin regions whose layers take the base's shading
SHADING_SIGMA = 0.15  # the shading field's Gaussian, times the area's shorter side
SHADING_LIMITS = (0.8, 1.25)  # the shading field's bounds
FACING = 0.05  # a texel is seen when its normal's camera z is over this
DEPTH_BIN = 2  # px, the side of the occlusion test's bins
DEPTH_TOLERANCE = 10.0  # mm behind the nearest texel at a bin that a texel may lie and be seen


def welded_normals(mesh: Mesh) -> np.ndarray:
    """(N, 3) float32 area-weighted normals, shared by vertices at the same position."""
    _, group = np.unique(mesh.vertices, axis=0, return_inverse=True)
    return vertex_normals(mesh.vertices.astype(np.float64), mesh.triangles, group.ravel())


def area_surface(mesh: Mesh, rect: tuple[float, float, float, float], shape: tuple[int, int],
                 normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The surface behind an area's texels, found on the CPU (module docstring).

    Args:
        mesh: the model's mesh (its UV layout one-to-one in [0, 1]^2).
        rect: (u0, v0, u1, v1) the area's UV rectangle.
        shape: (H, W) of the model's texture.
        normals: (N, 3) ``welded_normals(mesh)``, if already at hand.

    Returns:
        (h, w) int32 each texel's triangle (-1: none) and (h, w, 3) float32 its unit
        normal (0 where none), over ``texel_rect(rect, shape)``'s texels.
    """
    if normals is None:
        normals = welded_normals(mesh)
    height, width = shape
    rows, cols = texel_rect(rect, shape)[1]
    h, w = rows.stop - rows.start, cols.stop - cols.start
    triangles = np.full((h, w), -1, np.int32)
    out = np.zeros((h, w, 3), np.float32)
    corners = mesh.uv[mesh.triangles].astype(np.float64)  # (T, 3, 2)
    # texel (r, c) has its centre at u = (c + 1/2) / W, v = 1 - (r + 1/2) / H
    c_lo = np.maximum(np.ceil(corners[..., 0].min(axis=1) * width - 0.5).astype(int)
                      - cols.start, 0)
    c_hi = np.minimum(np.floor(corners[..., 0].max(axis=1) * width - 0.5).astype(int)
                      - cols.start, w - 1)
    r_lo = np.maximum(np.ceil((1.0 - corners[..., 1].max(axis=1)) * height - 0.5).astype(int)
                      - rows.start, 0)
    r_hi = np.minimum(np.floor((1.0 - corners[..., 1].min(axis=1)) * height - 0.5)
                      .astype(int) - rows.start, h - 1)
    near = np.flatnonzero((c_hi >= c_lo) & (r_hi >= r_lo))
    det = _det(corners[near])
    near, det = near[np.abs(det) > 1e-15], det[np.abs(det) > 1e-15]  # degenerate: no texel
    # every (triangle, texel of its UV box) pair at once
    bw, bh = c_hi[near] - c_lo[near] + 1, r_hi[near] - r_lo[near] + 1
    count = bw * bh
    which = np.repeat(np.arange(len(near)), count)  # each pair's triangle among ``near``
    tri = near[which]
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    r = np.repeat(r_lo[near], count) + k // np.repeat(bw, count)
    c = np.repeat(c_lo[near], count) + k % np.repeat(bw, count)
    a = corners[near, 0]
    v0, v1 = corners[near, 1] - a, corners[near, 2] - a
    du = (c + cols.start + 0.5) / width - a[which, 0]
    dv = 1.0 - (r + rows.start + 0.5) / height - a[which, 1]
    s_ = (du * v1[which, 1] - dv * v1[which, 0]) / det[which]
    t_ = (v0[which, 0] * dv - v0[which, 1] * du) / det[which]
    bary = np.stack([1.0 - s_ - t_, s_, t_], axis=-1)
    inside = np.all(bary >= -1e-9, axis=-1)
    texel = (r * w + c)[inside]
    texel, first = np.unique(texel, return_index=True)  # the first triangle holding it
    hit = np.flatnonzero(inside)[first]
    triangles.ravel()[texel] = tri[hit]
    n = np.einsum("pk,pkj->pj", bary[hit], normals[mesh.triangles[tri[hit]]].astype(np.float64))
    out.reshape(-1, 3)[texel] = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True),
                                               1e-12)
    return triangles, out


class AreaTexels:
    """One area's texels as surface points (module docstring).

    Args:
        mesh: the model's mesh; rig: its rig.
        rect: (u0, v0, u1, v1) the area's UV rectangle; shape: (H, W) of the texture.
        triangles: (h, w) int the triangle behind each of its texels (-1: none), and
        normals: (h, w, 3) their unit normals (``area_surface``, or the slices of
            ``sender.enroll.texture.uv_surface``).
    """

    def __init__(self, mesh: Mesh, rig: Rig, rect: tuple[float, float, float, float],
                 shape: tuple[int, int], triangles: np.ndarray, normals: np.ndarray) -> None:
        rows, cols = texel_rect(rect, shape)[1]
        tri = np.asarray(triangles)
        self.valid = tri >= 0
        tri = np.where(self.valid, tri, 0)
        v = 1.0 - (np.arange(rows.start, rows.stop) + 0.5) / shape[0]
        u = (np.arange(cols.start, cols.stop) + 0.5) / shape[1]
        uv = np.stack(np.meshgrid(u, v, indexing="xy"), axis=-1)
        self.slices = (rows, cols)
        self.triangles = np.where(self.valid, tri, -1)
        self.points = SurfacePoints(mesh, rig, tri, _uv_barycentric(mesh, tri, uv))
        self.normals = np.asarray(normals, np.float32)

    def read(self, camera: Intrinsics, image: np.ndarray, rotation: np.ndarray,
             translation: np.ndarray, residuals: np.ndarray, occlusion: bool = False
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The area's texels read from a frame (module docstring).

        Args:
            camera: the intrinsics; image: (H, W, 3) uint8 BGR frame.
            rotation: (3, 3) the sent pose's rotation; translation: (3,) mm.
            residuals: (9, 3) the sent residuals, mm.
            occlusion: texels behind others of the area are not seen.

        Returns:
            (h, w, 3) float32 RGB, (h, w) bool where seen, and the texels' projections
            x, y: (h, w) float32 px each.
        """
        h, w = self.valid.shape
        positions = self.points.positions(residuals)
        x, y = project(positions, rotation, translation, camera)
        x, y = x.reshape(h, w), y.reshape(h, w)
        colour = bilinear(image, x, y)[..., ::-1]  # BGR read, RGB out
        r = np.asarray(rotation, np.float32)
        facing = (self.normals @ r.T)[..., 2] > FACING
        on_image = (x >= 0) & (y >= 0) & (x <= image.shape[1] - 1) & (y <= image.shape[0] - 1)
        seen = self.valid & facing & on_image
        if occlusion:
            distance = -(positions @ r[2] + np.float32(translation[2])).reshape(h, w)
            seen &= _in_front(x, y, distance, seen, image.shape[:2])
        return colour, seen, x, y


def _in_front(x: np.ndarray, y: np.ndarray, distance: np.ndarray, seen: np.ndarray,
              shape: tuple[int, int]) -> np.ndarray:
    """(h, w) bool: the texels no seen texel lies in front of (module docstring), of
    (h, w) float32 projections x, y (px), distances (mm) and (h, w) bool seen ones on an
    image of (H, W) ``shape``."""
    rows, cols = -(-shape[0] // DEPTH_BIN), -(-shape[1] // DEPTH_BIN)
    bx = np.clip((x // DEPTH_BIN).astype(np.intp), 0, cols - 1)
    by = np.clip((y // DEPTH_BIN).astype(np.intp), 0, rows - 1)
    nearest = np.full(rows * cols, np.inf, np.float32)
    np.minimum.at(nearest, (by * cols + bx)[seen], distance[seen])
    spread = cv2.erode(nearest.reshape(rows, cols), np.ones((3, 3), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    return distance <= spread[by, bx] + DEPTH_TOLERANCE


def state_layers(name: str, reads: list[tuple[np.ndarray, np.ndarray]],
                 base: list[np.ndarray]) -> list[np.ndarray]:
    """A state's layer images from its areas' reads (module docstring, exposure and shading).

    Args:
        name: the region's name.
        reads: per area of the region, main first, ``AreaTexels.read``'s colour (h, w, 3)
            float32 RGB and seen (h, w) bool.
        base: per area, (h, w, 3) the base texture there.

    Returns:
        Per area, (h, w, 3) uint8 RGB; texels not seen keep the base texture.
    """
    base = [b.astype(np.float32) for b in base]
    colour, ok = reads[-1]
    border = ok & (ramp_mask(ok.shape) < 1.0)
    gain = np.ones(3, np.float32)
    if border.sum() >= 50:
        gain = base[-1][border].sum(axis=0) / np.maximum(colour[border].sum(axis=0), 1.0)
    gain = np.clip(gain, 0.5, 2.0)
    out = []
    for (colour, ok), b in zip(reads, base, strict=True):
        colour = colour * gain
        if name in SHADED:
            colour = colour * _shading(colour, ok, b)
        out.append(np.clip(np.rint(np.where(ok[..., None], colour, b)), 0, 255)
                   .astype(np.uint8))
    return out


def _shading(layer: np.ndarray, seen: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 the field f that matches a layer's broad shading to the base
    texture's (module docstring).

    Args:
        layer: (h, w, 3) float32 the layer's colours, exposure-scaled.
        seen: (h, w) bool the texels read from the frame.
        base: (h, w, 3) float32 the base texture there.
    """
    sigma = SHADING_SIGMA * min(seen.shape)
    weight = seen.astype(np.float32)
    total = np.maximum(cv2.GaussianBlur(weight, (0, 0), sigma), 1e-3)[..., None]

    def local(x: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(x * weight[..., None], (0, 0), sigma) / total + 1.0

    return np.clip(local(base) / local(layer), *SHADING_LIMITS).astype(np.float32)


def _uv_barycentric(mesh: Mesh, tri: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(..., 3) barycentric weights of UV points ``uv`` (..., 2) in triangles ``tri`` (...),
    clipped to the triangle and summing to 1."""
    corners = mesh.uv[mesh.triangles[tri]].astype(np.float64)  # (..., 3, 2)
    bary = np.clip(_barycentric(corners, uv), 0.0, 1.0)
    return (bary / np.maximum(bary.sum(axis=-1, keepdims=True), 1e-12)).astype(np.float32)


def _barycentric(corners: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(..., 3, 2) triangles' UV corners, (..., 2) points -> (..., 3) weights (a degenerate
    triangle gives the first corner all the weight)."""
    a, b, c = corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    v0, v1, v2 = b - a, c - a, uv - a
    det = _det(corners)
    det = np.where(np.abs(det) > 1e-15, det, 1.0)
    s = (v2[..., 0] * v1[..., 1] - v2[..., 1] * v1[..., 0]) / det
    t = (v0[..., 0] * v2[..., 1] - v0[..., 1] * v2[..., 0]) / det
    return np.stack([1.0 - s - t, s, t], axis=-1)


def _det(corners: np.ndarray) -> np.ndarray:
    """(...,) twice the signed UV area of triangles (..., 3, 2)."""
    v0, v1 = corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :]
    return v0[..., 0] * v1[..., 1] - v0[..., 1] * v1[..., 0]
