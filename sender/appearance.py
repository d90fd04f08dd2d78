"""Locating and sampling appearance: the regions' template grids read from each frame.

Appearance areas do not track well, so they are not tracked: each sample point is stored
once as a triangle of the model and barycentric weights (a, b, c) of its vertices
(``models.regions.template_samples``; S x S = 32 x 32 points for each of a region's five
offset grids). Per frame, with the pose and residuals the packet carries:

    P      = P0 + W r                   the points on the morphed mesh, model space, mm
                                        (P0 = sum a V, W = sum a B: the rig's morph
                                        ``V + B r`` restricted to the points, precomputed)
    X      = R P + t                    GL camera frame
    (x, y) = (cx + fx X / d, cy - fy Y / d),   d = -Z

and the grey frame is read at (x, y) by bilinear interpolation, all regions and offsets in
one ``cv2.remap``; each template cell is the mean of its SUPERSAMPLE x SUPERSAMPLE points.
The five offset grids of a region are the same grid moved by whole template cells, so they
share most of their points: (S + 2 SUPERSAMPLE)^2 = 1,296 distinct points per region instead
of 5 S^2 = 5,120 (exactly equal triangle and weights; ``AppearanceSampler`` projects and
reads each distinct point once and gathers the cells' points from those reads).
A point behind the camera (d < 1 mm) or off the image reads the nearest border pixel (such
a sample matches no template well and loses to the others). Because the points ride on the
morphed, posed mesh, a sample is normalised against head pose and expression: the same
skin lands in the same template cell.
"""

from __future__ import annotations

import cv2
import numpy as np

from facewire.models.geometry import Intrinsics
from facewire.models.mesh import Mesh
from facewire.models.regions import SUPERSAMPLE, TEMPLATE_SIZE, spec, template_samples
from facewire.models.rig import Rig

N_OFFSETS = 5
_REMAP_COLUMNS = 32766


class SurfacePoints:
    """Points fixed on a mesh by barycentric weights, followed through the rig's morph.

    Args:
        mesh: the model's mesh (neutral).
        rig: its rig (``Rig(mesh)``).
        triangles: (...,) int triangle indices.
        bary: (..., 3) barycentric weights of the triangles' vertices.
    """

    def __init__(self, mesh: Mesh, rig: Rig, triangles: np.ndarray, bary: np.ndarray) -> None:
        triangles = np.asarray(triangles)
        bary = np.asarray(bary, np.float32)
        if not np.issubdtype(triangles.dtype, np.integer):
            raise ValueError(f"triangles: expected integer indices, got {triangles.dtype}")
        if bary.shape != (*triangles.shape, 3):
            raise ValueError(f"bary: expected shape {(*triangles.shape, 3)}, got {bary.shape}")
        if not np.isfinite(bary).all():
            raise ValueError("bary: contains NaN or infinity")
        if triangles.size and not (0 <= triangles.min() and triangles.max() < len(mesh.triangles)):
            raise ValueError(f"triangles: indices outside [0, {len(mesh.triangles)})")
        self.shape = triangles.shape
        corners = mesh.triangles[triangles.ravel()]  # (n, 3)
        b = bary.reshape(-1, 3, 1)
        self.neutral = np.ascontiguousarray((b * mesh.vertices[corners]).sum(axis=1), np.float32)
        self.weights = np.ascontiguousarray((b * rig.weights[corners]).sum(axis=1), np.float32)
        # (12, n): the transposed product below writes x, y and z as contiguous rows
        self._stacked = np.ascontiguousarray(np.hstack([self.neutral, self.weights]).T)

    def positions(self, residuals: np.ndarray) -> np.ndarray:
        """(n, 3) float32 model-space positions after the morph by (9, 3) ``residuals``, mm."""
        return self.neutral + self.weights @ np.asarray(residuals, np.float32)

    def project(self, residuals: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                camera: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """``project(positions(residuals), ...)`` in one product: R (P0 + W r) + t =
        [R  R r^T] [P0 W]^T + t, a (3, 12) @ (12, n) float32 product.

        Returns:
            x, y: (n,) float32 pixel coordinates.
        """
        rt = np.asarray(rotation, np.float32).T
        m = np.vstack([rt, np.asarray(residuals, np.float32) @ rt]).T  # (3, 12)
        cam = np.ascontiguousarray(m) @ self._stacked
        cam += np.asarray(translation, np.float32)[:, None]
        return _pixels(cam[0], cam[1], cam[2], camera)


def project(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
            camera: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of model-space points (module docstring).

    Args:
        points: (n, 3) float32 model space, mm.
        rotation: (3, 3) model -> GL camera.
        translation: (3,) mm.
        camera: the intrinsics.

    Returns:
        x, y: (n,) float32 pixel coordinates, origin top-left (points less than 1 mm in front
        of the camera are pushed to 1 mm).
    """
    cam = points @ np.asarray(rotation, np.float32).T + np.asarray(translation, np.float32)
    return _pixels(cam[:, 0], cam[:, 1], cam[:, 2], camera)


def _pixels(xc: np.ndarray, yc: np.ndarray, zc: np.ndarray, camera: Intrinsics
            ) -> tuple[np.ndarray, np.ndarray]:
    """(n,) float32 GL camera-frame coordinates X, Y, Z -> pixel x, y (n,) float32."""
    inverse = np.float32(-1.0) / np.maximum(-zc, np.float32(1.0))
    x = xc * inverse
    x *= -np.float32(camera.fx)
    x += np.float32(camera.cx)
    y = yc * inverse
    y *= np.float32(camera.fy)
    y += np.float32(camera.cy)
    return x, y


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Read an image at float pixel positions, bilinearly (borders replicated).

    Args:
        image: (H, W) or (H, W, C) uint8 or float32, sides under 32767.
        x, y: (...) float32 pixel coordinates, the same shape; (0, 0) the top-left pixel's
            centre.

    Returns:
        (...,) or (..., C) float32 values.
    """
    shape = x.shape
    n = x.size
    if n == 0:
        return np.zeros((*shape, *image.shape[2:]), np.float32)
    columns = min(n, _REMAP_COLUMNS)  # cv2.remap wants both sides of its maps under 32767
    rows = -(-n // columns)
    if rows == 1:  # one row of maps: the points as they are
        mx = np.ascontiguousarray(x, np.float32).reshape(1, n)
        my = np.ascontiguousarray(y, np.float32).reshape(1, n)
    else:
        mx = np.zeros((rows, columns), np.float32)
        my = np.zeros((rows, columns), np.float32)
        mx.ravel()[:n] = x.ravel()
        my.ravel()[:n] = y.ravel()
    out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(rows * columns, *image.shape[2:])[:n]
    return out.reshape(*shape, *image.shape[2:]).astype(np.float32, copy=False)


class AppearanceSampler:
    """The five offset samples of every region, per frame (module docstring).

    Args:
        mesh: the model's mesh.
        rig: its rig.
        camera: the sender camera's intrinsics.
        names: the regions to sample, in packet order (``models.regions.REGIONS`` names).

    Raises:
        RegionError: a name is not a known region.
    """

    def __init__(self, mesh: Mesh, rig: Rig, camera: Intrinsics, names: tuple[str, ...]) -> None:
        self.names = tuple(names)
        self.camera = camera
        grids = [template_samples(spec(name)) for name in self.names]
        if grids:
            triangles = np.stack([t for t, _ in grids])
            bary = np.stack([b for _, b in grids])
        else:
            triangles = np.zeros((0, N_OFFSETS, 1, 1), np.int64)
            bary = np.zeros((0, N_OFFSETS, 1, 1, 3), np.float32)
        triangles, bary, index = _distinct(triangles, bary)
        self.points = SurfacePoints(mesh, rig, triangles, bary)
        # (s^2, R * 5 * 16 * 16): the distinct points averaged into each template cell
        n, s = TEMPLATE_SIZE, SUPERSAMPLE
        self._cells = np.ascontiguousarray(
            index.reshape(len(self.names) * N_OFFSETS, n, s, n, s).transpose(2, 4, 0, 1, 3)
            .reshape(s * s, -1))

    def sample(self, gray: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
               residuals: np.ndarray) -> np.ndarray:
        """Sample every region's five offset grids from one frame.

        Args:
            gray: (H, W) uint8 grey frame.
            rotation: (3, 3) the pose's rotation, model -> GL camera.
            translation: (3,) mm.
            residuals: (9, 3) model-space residuals, mm (``NONRIGID`` order), as sent.

        Returns:
            (R, 5, 16, 16) float32 grey levels, 0..255, R = len(names).
        """
        r = len(self.names)
        if r == 0:
            return np.zeros((0, N_OFFSETS, TEMPLATE_SIZE, TEMPLATE_SIZE), np.float32)
        n = TEMPLATE_SIZE
        x, y = self.points.project(residuals, rotation, translation, self.camera)
        values = bilinear(gray, x, y)  # integer grey levels: the cells' sums are exact
        cells = np.add.reduce(values[self._cells], axis=0)
        cells *= np.float32(1.0 / SUPERSAMPLE**2)
        return cells.reshape(r, N_OFFSETS, n, n)


def _distinct(triangles: np.ndarray, bary: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct points of sample grids, in order of first appearance.

    Args:
        triangles: (...) int triangle indices; bary: (..., 3) float32 weights.

    Returns:
        (U,) triangles, (U, 3) weights, and (...) int64 the index of each input point among
        them (equal triangle and bit-equal weights make one point).
    """
    tri = triangles.reshape(-1).astype(np.int64)
    weights = np.ascontiguousarray(bary, np.float32).reshape(-1, 3)
    key = np.column_stack([tri, weights.view(np.int32).astype(np.int64)])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # distinct points in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[inverse.reshape(-1)].reshape(triangles.shape)
    return tri[first[order]], weights[first[order]], index
