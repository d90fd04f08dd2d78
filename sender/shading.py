"""The light that follows, measured: the face's shading relative to the model's texture.

The packet's ``shade`` is a log-gain field over model space (``models.shading``):
g(x, y) = s0 + s1 x / 100 mm + s2 y / 100 mm, by whose exponential the receiver multiplies
the texture. The sender fits it per frame where the face is plain skin and compares the
frame with the texture there.

Points (chosen once per model, ``skin_points``). The centroids of the mesh's SKIN triangles
on the face (model x in [-60, 60] mm, y in [-108, 68] mm on the neutral mesh) that face the
front (normal z > ``MIN_FRONT``), one per ``GRID_MM`` square (the centroid nearest its
centre), leaving out the parts an expression changes: the eyes and lids, the brows and the
mouth (``_EXCLUDED`` boxes, mm, on the generic head's proportions, which every model keeps
near enough). Each point rides on the morphed, posed mesh as the appearance samples do
(``sender.appearance.SurfacePoints``).

Reference. The texture's grey level at each point's UV, after a Gaussian blur of
sigma = 0.4 ``CELL_MM`` in texels (the texture's texels per mm measured on the chosen
triangles, UV area against model area), so that texture and frame are compared at the same
scale, about ``CELL_MM`` (a 1-pixel error of the tracker on a sharp edge would otherwise
swamp the light). Points whose reference is darker than ``MIN_LEVEL`` (brows, nostrils,
hair) are left out: a ratio of small numbers is noise.

Per frame. The points are projected with the sent pose and residuals; the grey frame's
crop around them is reduced by a Gaussian pyramid (``cv2.pyrDown``, L times, 2^L the
largest power of 2 not above ``CELL_MM`` in pixels, ``fx / -t_z`` pixels per mm, L at most
``MAX_LEVELS``: about the texture's blur) and read bilinearly at the points. A point counts
when it is on the image, faces the camera (cos of the angle between its normal and the
view ray to the model origin > ``MIN_FACING``; the face spans a few degrees of the view)
and its frame level is in (``MIN_LEVEL``, ``MAX_LEVEL``) (not black, not clipped). With I_i
the frame's level and T_i the reference,

    y_i = ln I_i - ln T_i ≈ s0 + s1 x_i / 100 + s2 y_i / 100        (x_i, y_i neutral, mm)

is fitted by iteratively reweighted least squares with Tukey's biweight (c = 4.685 times
the residuals' MAD scale, taken about the median and again after the first step;
``IRLS_STEPS`` steps), so that what is not the light (a hand, hair falling over the brow,
a shadow's edge, a misplaced point) weighs nothing. The neutral positions stand for the
morphed ones in the fit: an expression moves these points a few mm, a change of the field
under 0.01 at a steep s1 = 0.3.

Over time. A frame's fit is taken when at least ``MIN_POINTS`` points count and at least
``MIN_INLIERS`` of them keep a weight (else the last value is held: a hand over half the
face does not move the light). Light changes slowly, so the taken fits are smoothed
exponentially, s <- s + a (fit - s), a = 1 - exp(-dt / ``TAU_S``); the first fit of a stream
(or of a newly acquired face) is taken as it is. Without a pose the value is held. ``TAU_S``
= 0.3 s, measured on the tuning clips whose light changes (a camera's exposure following a
window; frames K: as ``bench.clips`` says): 0.1 s gained face SSIM 0.0006 / 0.0003 and PSNR
0.2 / 0.26 dB on openface_default / openface_gaze but made twice the 1/64 steps of s0 on a
steady light (lp_d14 214:400: 10 a second against 5, 24 reversals within 3 frames against
12); 1.0 s lost 0.0016 SSIM and 0.5 dB on openface_default.

On the wire. The packet carries each value on its quantiser's grid (step 1/64); a smoothed
value sitting near the middle between two codes would flip between them frame after frame
(1.6 % of brightness, a shimmer a viewer may see on a steady light). So the value sent
(``sent``) moves to the nearest code only when the smoothed value is more than
``HYSTERESIS`` steps from it, and is the nearest code at a stream's first fit: at most
``HYSTERESIS`` of a step (1.2 % of gain) behind the smoothed value, never flickering. On
lp_d14 214:400 (a steady light) s0 changed 1.8 times a second instead of 5 and never went
back within 3 frames (12 times without); on openface_gaze 336:600, 11.5 instead of 13.4
changes a second, no reversal instead of 5.

Cost: some 570 points, a pyramid of the face's crop, one remap and three 3 x 3 solves:
``SenderOutput.timings["shade"]``, 0.30 ms median in ``bench speed`` on openface_default
(640 x 480; classification 0.23 ms there), 0.11 ms as the best of 15 runs per frame.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from facewire.models.geometry import Intrinsics
from facewire.models.mesh import Mesh, Tag
from facewire.models.modelfile import PersonModel
from facewire.models.rig import Rig
from facewire.models.shading import basis
from facewire.protocol.packet import QUANTISERS
from facewire.sender.appearance import SurfacePoints, bilinear

FACE_BOX = (-60.0, 60.0, -108.0, 68.0)  # x0, x1, y0, y1 on the neutral mesh, mm
# (|x| from, |x| to, y from, y to), mm: the eyes and lids, the brows, the mouth
_EXCLUDED = ((10.0, 56.0, -14.0, 14.0), (3.0, 66.0, 10.0, 34.0), (0.0, 34.0, -90.0, -48.0))
GRID_MM = 5.0
CELL_MM = 4.0
MIN_FRONT = 0.35
MIN_FACING = 0.3
MIN_LEVEL = 20.0
MAX_LEVEL = 245.0
IRLS_STEPS = 3
TUKEY_C = 4.685
MIN_POINTS = 40
MIN_INLIERS = 0.5
TAU_S = 0.3
MAX_LEVELS = 4
HYSTERESIS = 0.75
STEP = next(q.step for q in QUANTISERS if q.name == "shade")


def skin_points(mesh: Mesh) -> np.ndarray:
    """The plain-skin points the light is measured at (module docstring).

    Returns:
        (n,) int64 triangle indices, one per ``GRID_MM`` square of the face; their
        centroids are the points (barycentric weights 1/3 each).
    """
    corners = mesh.vertices[mesh.triangles].astype(np.float64)  # (M, 3, 3)
    centroid = corners.mean(axis=1)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    front = normal[:, 2] / np.maximum(np.linalg.norm(normal, axis=1), 1e-12)
    x, y = centroid[:, 0], centroid[:, 1]
    x0, x1, y0, y1 = FACE_BOX
    keep = (mesh.tags == Tag.SKIN) & (front > MIN_FRONT) & (x >= x0) & (x <= x1) \
        & (y >= y0) & (y <= y1)
    for ax0, ax1, by0, by1 in _EXCLUDED:
        keep &= ~((np.abs(x) >= ax0) & (np.abs(x) <= ax1) & (y >= by0) & (y <= by1))
    candidates = np.flatnonzero(keep)
    cell = np.floor((centroid[candidates, :2] - (x0, y0)) / GRID_MM)
    centre = (cell + 0.5) * GRID_MM + (x0, y0)
    distance = np.linalg.norm(centroid[candidates, :2] - centre, axis=1)
    key = cell[:, 0] * 1000 + cell[:, 1]
    order = np.lexsort((distance, key))  # by square, nearest first
    first = np.flatnonzero(np.diff(key[order], prepend=np.nan) != 0)
    return np.sort(candidates[order[first]]).astype(np.int64)


class ShadingEstimator:
    """The light's log-gain field of each frame, smoothed over time (module docstring).

    Args:
        model: the person model (its mesh and texture).
        rig: its rig (``Rig(model.mesh)``).
        camera: the sender camera's intrinsics.

    Attributes:
        triangles: (n,) the points' triangles (``skin_points``, dark references removed).
        shade: (3,) float32 the current smoothed field (s0, s1, s2).
        sent: (3,) float32 the field the packet carries: ``shade`` on the quantiser's grid,
            with hysteresis (module docstring).
    """

    def __init__(self, model: PersonModel, rig: Rig, camera: Intrinsics) -> None:
        mesh = model.mesh
        triangles = skin_points(mesh)
        corners = mesh.triangles[triangles]
        uv = mesh.uv[corners].astype(np.float64).mean(axis=1)
        reference = _texture_levels(model.texture, mesh, triangles, uv)
        bright = reference > MIN_LEVEL
        self.triangles = triangles[bright]
        corners = corners[bright]
        bary = np.full((len(self.triangles), 3), 1.0 / 3.0, np.float32)
        self.camera = camera
        self._points = SurfacePoints(mesh, rig, self.triangles, bary)
        v = mesh.vertices.astype(np.float64)
        normal = np.cross(v[corners[:, 1]] - v[corners[:, 0]], v[corners[:, 2]] - v[corners[:, 0]])
        self._normals = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        self._basis = basis(self._points.neutral)
        self._log_reference = np.log(reference[bright])
        self.reset()

    def reset(self) -> None:
        """Forget the stream: the next fit is taken as it is."""
        self.shade = np.zeros(3, np.float32)
        self.sent = np.zeros(3, np.float32)
        self._fresh = True

    def restart(self) -> None:
        """A new face: keep the value until its first fit, which is then taken as it is."""
        self._fresh = True

    def estimate(self, gray: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                 residuals: np.ndarray, dt: float) -> np.ndarray:
        """Update the field with one frame and return it.

        Args:
            gray: (H, W) uint8 grey frame.
            rotation: (3, 3) the sent pose's rotation, model -> GL camera.
            translation: (3,) mm.
            residuals: (9, 3) model-space residuals, mm, as sent.
            dt: the time since the last frame, s.

        Returns:
            (3,) float32 the field to send (``sent``); a copy.
        """
        fit = self.fit(gray, rotation, translation, residuals)
        if fit is not None:
            nearest = np.rint(fit / STEP) * STEP
            if self._fresh:
                self.shade = fit.astype(np.float32)
                self.sent = nearest.astype(np.float32)
                self._fresh = False
            else:
                a = 1.0 - math.exp(-max(dt, 0.0) / TAU_S)
                self.shade = (self.shade + a * (fit - self.shade)).astype(np.float32)
                moved = np.abs(self.shade - self.sent) > HYSTERESIS * STEP
                self.sent = np.where(moved, np.rint(self.shade / STEP) * STEP,
                                     self.sent).astype(np.float32)
        return self.sent.copy()

    def fit(self, gray: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
            residuals: np.ndarray) -> np.ndarray | None:
        """One frame's robust fit (module docstring), or None when too few points count.

        Returns:
            (3,) float64 (s0, s1, s2), or None.
        """
        rotation = np.asarray(rotation, np.float64)
        translation = np.asarray(translation, np.float64)
        height, width = gray.shape[:2]
        x, y = self._points.project(residuals, rotation, translation, self.camera)
        depth = max(-float(translation[2]), 1.0)
        # the view ray to the model origin, in model space: the face spans a few degrees
        toward = -(rotation.T @ translation) / np.linalg.norm(translation)
        facing = self._normals @ toward
        ok = (facing > MIN_FACING) & (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
        if np.count_nonzero(ok) < MIN_POINTS:
            return None
        x, y = x[ok], y[ok]
        levels = self._read(gray, x, y, depth)
        ok_level = (levels > MIN_LEVEL) & (levels < MAX_LEVEL)
        if ok_level.sum() < MIN_POINTS:
            return None
        index = np.flatnonzero(ok)[ok_level]
        return _robust_fit(self._basis[index],
                           np.log(levels[ok_level]) - self._log_reference[index])

    def _read(self, gray: np.ndarray, x: np.ndarray, y: np.ndarray, depth: float) -> np.ndarray:
        """The frame's levels at (x, y), at the pyramid level of about ``CELL_MM`` pixels."""
        cell_px = CELL_MM * self.camera.fx / max(depth, 1.0)
        levels = int(min(max(math.floor(math.log2(max(cell_px, 1.0))), 0), MAX_LEVELS))
        x0, y0 = int(x.min()), int(y.min())
        crop = gray[y0:int(np.ceil(y.max())) + 1, x0:int(np.ceil(x.max())) + 1]
        for _ in range(levels):  # pixel i of the next level is centred on pixel 2 i
            crop = cv2.pyrDown(crop)
        step = np.float32(1.0 / (1 << levels))
        return bilinear(crop, (x - x0) * step, (y - y0) * step)


def _texture_levels(texture: np.ndarray, mesh: Mesh, triangles: np.ndarray,
                    uv: np.ndarray) -> np.ndarray:
    """(n,) float64 the blurred grey texture at the points' UVs (module docstring)."""
    h, w = texture.shape[:2]
    v = mesh.vertices.astype(np.float64)[mesh.triangles[triangles]]
    t = mesh.uv.astype(np.float64)[mesh.triangles[triangles]] * (w, h)
    area_mm = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area_texels = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    texels_per_mm = math.sqrt(area_texels / max(area_mm, 1e-9))
    grey = cv2.cvtColor(texture, cv2.COLOR_RGB2GRAY).astype(np.float32)
    blurred = cv2.GaussianBlur(grey, (0, 0), max(0.4 * CELL_MM * texels_per_mm, 0.5))
    return bilinear(blurred, (uv[:, 0] * w - 0.5).astype(np.float32),
                    ((1.0 - uv[:, 1]) * h - 0.5).astype(np.float32)).astype(np.float64)


def _robust_fit(a: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """Tukey-weighted least squares of y (n,) on a (n, 3), from the median (module
    docstring); None when fewer than ``MIN_INLIERS`` of the points keep a weight or the
    kept points do not span the field (all on one line)."""
    half = len(y) // 2
    s = np.array([np.partition(y, half)[half], 0.0, 0.0])
    weight = np.ones(len(y))
    for step in range(IRLS_STEPS):
        r = y - a @ s
        if step < 2:
            spread = np.abs(r)
            scale = 1.4826 * float(np.partition(spread, half)[half]) + 1e-3
        u = r * (1.0 / (TUKEY_C * scale))
        weight = np.maximum(1.0 - u * u, 0.0) ** 2
        aw = a.T * weight
        solved = _solve3(aw @ a, aw @ y)
        if solved is None:
            return None
        s = solved
    if np.count_nonzero(weight) < MIN_INLIERS * len(y):
        return None
    return s


def _solve3(normal: np.ndarray, rhs: np.ndarray) -> np.ndarray | None:
    """The solution of a symmetric 3 x 3 system by Cramer's rule (a tenth of
    ``np.linalg.solve``'s time at this size), or None when the matrix is singular to working
    precision: its determinant under 1e-9 of the product of its diagonal (1 for independent
    columns, 0 for dependent ones)."""
    (a, b, c), (_, e, f), (_, _, i) = normal.tolist()
    r0, r1, r2 = rhs.tolist()
    ei_ff, bi_fc, bf_ec = e * i - f * f, b * i - f * c, b * f - e * c
    det = a * ei_ff - b * bi_fc + c * bf_ec
    if not det > 1e-9 * a * e * i:
        return None
    return np.array([r0 * ei_ff - r1 * bi_fc + r2 * bf_ec,
                     -r0 * bi_fc + r1 * (a * i - c * c) - r2 * (a * f - b * c),
                     r0 * bf_ec - r1 * (a * f - c * b) + r2 * (a * e - b * b)]) / det
