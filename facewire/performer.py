"""The scripted performer of ``facewire demo``: a still portrait turned into a moving face.

The demo needs a video of someone making faces and has neither a camera nor a file, so it
makes one from a public-domain portrait that matplotlib ships (``grace_hopper.jpg``, the
U.S. Navy's official photograph of Rear Admiral Grace Hopper; ``portrait``).

How a frame is made (``Performer.frame``), and what in it is synthetic
---------------------------------------------------------------------
1. A *bootstrap model* of the portrait: ``sender.enroll.build.build_photo``, the build of
   ``facewire model build PHOTO`` (geometry and neutral texture, no regions; one view, so
   the depth is the generic head's). The only edit: the mouth cavity's texels
   (``Tag.MOUTH_INTERIOR`` triangles in UV) are painted a dark red (``MOUTH_COLOUR``): the
   photo's closed mouth shows no inside, and a filled skin tone there would make an open
   mouth look closed to the tracker.
2. Head pose. The neutral pose is the fit's pose of the still. A scripted turn (yaw) and nod
   (pitch), degrees, rotates the head about ``PIVOT`` (a point behind and below the face,
   near where the neck turns it): ``X_cam = R0 (P (X - c) + c) + t0``, with P = R_y(yaw)
   R_x(-pitch) and c the pivot. Positive yaw turns the nose toward the image's right,
   positive pitch lifts the chin (``sender.enroll.fit``'s convention).
3. Expression. The performer stands in for a real face, so it moves more than the packet
   carries: an RBF volume morph (``models.morph.VolumeMorph``, as the rig's) centred on all
   68 landmark vertices, the phantoms and the rig's anchors, with the landmarks moved by
   ``face_displacements``: brows up (``BROW_MM``), and the mouth opened by dropping the chin
   ``CHIN_MM`` with the jaw line in proportion (``JAW_SHARE``), the lower lip with it, the
   upper lip a little up and the corners in and down (``LIP_MM``, ``CORNER_*``); the jaw's
   phantoms follow the chin as the rig's do (``Rig.follow``), the skull's stay. The inner
   lips part along their whole width, so the cavity shows (the rig moves 9 points, of the
   lips only the middles and the corners), and the receiver shows the open mouth through
   its morph and the mouth region's appearance layers, as the paper intends. The eyeballs
   stay rigid. The real renderer (``models.infra.raster.MeshRenderer``) draws the morphed mesh.
4. Compositing over the portrait. Only the face is taken from the render: the polygon of the
   projected jaw contour (0-16) and the brows raised by ``FOREHEAD`` times their height
   over the eyes, feathered (``FEATHER_PX``). Around it the portrait itself (hat, hair,
   ears) is moved by the 2D affine map that best takes the head's outline (the projected
   jaw contour and phantoms, least median of squares) from the neutral pose to this frame's
   pose, faded into the still portrait (neck, shoulders, flag) by an elliptic head mask
   that ends at the chin: a 2D approximation that keeps the hair next to the face's edge
   (the face's outline, not its centre, is what the hair must follow); at 20 degrees of
   yaw the hat shifts and shears rather than turning in depth.
5. Blinks are a 2D lid warp (``close_eyes``), since the rig has no lid: in each eye's
   columns the skin between the brow and the upper lid is stretched down over the eyeball
   until the lid meets the lower lid, tinted toward the skin under the eye (``LID_SKIN``:
   the stretched skin is often in shadow), and the lid edge is darkened (lashes). The
   tracker sees a closing eye; nothing 3D moves.

The script
----------
A performance is a list of ``Cue`` (start, length, channel, peak) on five channels: ``yaw``
and ``pitch`` (degrees), ``brows``, ``mouth`` and ``blink`` (0 .. 1 of the full movement).
Each cue is a smooth bump: smoothstep up over its first third, held, smoothstep down over
its last third; a channel is the sum of its cues. ``SCRIPT`` is the demo's: its first
``ENROLL_S`` seconds show each movement once between still, frontal stretches (the model is
built from them: enrollment must see brows up, mouth open, a blink and a head turn, and the
neutral frame must be a still one), the rest mixes them, with expressions during head
turns and nods.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from facewire.models.geometry import Intrinsics, Pose
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.raster import Camera, MeshRenderer
from facewire.models.mesh import Mesh, Tag
from facewire.models.modelfile import PersonModel
from facewire.models.morph import VolumeMorph
from facewire.models.rig import Rig
from facewire.protocol.errors import FacewireError
from facewire.receiver.output import VideoWriter
from facewire.sender.enroll.build import BuildError, BuildResult, build_photo

PORTRAIT = "grace_hopper.jpg"  # matplotlib's sample data: public domain (U.S. Navy photo)
RATE_HZ = 30.0
CHANNELS = ("yaw", "pitch", "brows", "mouth", "blink")
MOUTH_COLOUR = (58, 16, 20)  # RGB of the painted mouth cavity
PIVOT = (0.0, -40.0, -80.0)  # mm from the landmarks' centroid: the head turns about this
BROW_MM = 7.0  # brows up, at the middle of each brow
BROW_SHARE = {17: 0.55, 18: 0.85, 19: 1.0, 20: 1.0, 21: 0.9,
              22: 0.9, 23: 1.0, 24: 1.0, 25: 0.85, 26: 0.55}
CHIN_MM = 16.0  # mouth open: the chin drops this far, the jaw line in proportion
JAW_SHARE = {3: 0.15, 4: 0.35, 5: 0.6, 6: 0.8, 7: 0.95, 8: 1.0,
             9: 0.95, 10: 0.8, 11: 0.6, 12: 0.35, 13: 0.15}
LIP_MM = {49: 1.5, 50: 2.5, 51: 3.0, 52: 2.5, 53: 1.5, 61: 2.5, 62: 3.0, 63: 2.5,  # up
          55: -9.0, 56: -13.0, 57: -14.0, 58: -13.0, 59: -9.0,  # down
          65: -12.0, 66: -13.0, 67: -12.0}
CORNER_IN_MM = 3.0  # mouth corners (48, 54 and inner 60, 64) drawn in and down
CORNER_DOWN_MM = 3.0
FOREHEAD = 1.0  # the face mask reaches this many brow-over-eye heights above the brows
FEATHER_PX = 3
HEAD_MASK_SCALE = 1.6  # the head mask's ellipse, in half-extents of the projected phantoms
LID_BAND = 0.6  # the lid skin stretched over the eye: this fraction of the lid-to-brow height
LID_SKIN = 0.6  # a closed lid is tinted this far toward the skin under the eye


@dataclass(frozen=True)
class Cue:
    """One movement of the script: ``channel`` rises to ``peak`` and returns to 0.

    Attributes:
        start_s: when it starts, seconds from the first frame.
        length_s: how long it lasts, seconds (> 0).
        channel: one of ``CHANNELS``.
        peak: the value at the top: degrees for yaw and pitch, 0 .. 1 for the others.
    """

    start_s: float
    length_s: float
    channel: str
    peak: float

    def __post_init__(self) -> None:
        if self.channel not in CHANNELS:
            raise ValueError(f"cue channel: expected one of {', '.join(CHANNELS)}, "
                             f"got {self.channel!r}")
        if not (np.isfinite(self.start_s) and np.isfinite(self.length_s)
                and self.length_s > 0 and np.isfinite(self.peak)):
            raise ValueError(f"cue {self.channel} at {self.start_s} s: start, length (> 0) "
                             f"and peak must be finite numbers")


ENROLL_S = 4.0
LENGTH_S = 11.0
SCRIPT: tuple[Cue, ...] = (
    # Enrollment: still and frontal, then each movement once, then still again. The brows
    # go up while the head is turned, so that model building never takes a frame with
    # raised brows for the neutral one (it prefers frontal frames with the eyes open, and
    # raised brows make the tracker see the eyes wider open).
    Cue(0.5, 1.5, "yaw", 15.0),
    Cue(0.95, 0.6, "brows", 1.0),
    Cue(2.0, 0.9, "mouth", 1.0),
    Cue(2.95, 0.36, "blink", 1.0),
    # The performance.
    Cue(4.2, 1.8, "yaw", 20.0),
    Cue(4.5, 1.0, "brows", 1.0),
    Cue(5.2, 0.33, "blink", 1.0),
    Cue(5.8, 1.0, "mouth", 1.0),
    Cue(6.3, 1.8, "yaw", -20.0),
    Cue(7.0, 0.9, "mouth", 0.8),
    Cue(7.6, 0.33, "blink", 1.0),
    Cue(8.1, 1.2, "pitch", 15.0),
    Cue(8.3, 0.9, "brows", 1.0),
    Cue(9.3, 1.1, "pitch", -12.0),
    Cue(9.5, 0.8, "mouth", 0.9),
    Cue(10.35, 0.33, "blink", 1.0),
)


class PerformerError(FacewireError, ValueError):
    """The portrait cannot be performed (no face in it); the message says why."""


def portrait() -> np.ndarray:
    """The demo's portrait from matplotlib's sample data.

    Returns:
        (600, 512, 3) uint8 BGR image.

    Raises:
        PerformerError: matplotlib's sample data is missing or unreadable.
    """
    import matplotlib.cbook

    try:
        path = matplotlib.cbook.get_sample_data(PORTRAIT, asfileobj=False)
    except (OSError, ValueError) as exc:
        raise PerformerError(f"matplotlib's sample portrait {PORTRAIT} is missing ({exc}); "
                             f"reinstall matplotlib, or run the demo with --source VIDEO") \
            from None
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise PerformerError(f"{path}: cannot read matplotlib's sample portrait")
    return image


def bump(t: np.ndarray, cue: Cue) -> np.ndarray:
    """A cue's value at times ``t`` (s): smoothstep up over the first third of the cue, held,
    smoothstep down over the last third; 0 outside it.

    Args:
        t: (F,) times, seconds.
        cue: the cue.

    Returns:
        (F,) float64.
    """
    x = (np.asarray(t, np.float64) - cue.start_s) / cue.length_s  # 0 .. 1 over the cue
    up = np.clip(3.0 * x, 0.0, 1.0)
    down = np.clip(3.0 * (1.0 - x), 0.0, 1.0)
    ramp = np.minimum(up, down)
    return cue.peak * ramp * ramp * (3.0 - 2.0 * ramp)


def script_values(script: tuple[Cue, ...], times: np.ndarray) -> np.ndarray:
    """Every channel of a script at times ``t``.

    Args:
        script: the cues.
        times: (F,) seconds.

    Returns:
        (F, 5) float64, columns in ``CHANNELS`` order.
    """
    times = np.asarray(times, np.float64)
    out = np.zeros((len(times), len(CHANNELS)))
    for cue in script:
        out[:, CHANNELS.index(cue.channel)] += bump(times, cue)
    return out


def face_displacements(brows: float, mouth: float) -> np.ndarray:
    """The performer's expression at its 68 landmarks (module docstring, 3).

    Args:
        brows: 0 (rest) .. 1 (raised by ``BROW_MM``).
        mouth: 0 (closed) .. 1 (open: chin down ``CHIN_MM``).

    Returns:
        (68, 3) float64 model-space displacements, mm, iBUG order.
    """
    d = np.zeros((68, 3))
    for point, share in BROW_SHARE.items():
        d[point, 1] = BROW_MM * share * brows
    for point, dy in LIP_MM.items():
        d[point, 1] = dy * mouth
    for point, share in JAW_SHARE.items():
        d[point, 1] = -CHIN_MM * share * mouth
    for right, left in ((48, 54), (60, 64)):  # corners: the person's right is model -x
        d[right] = (CORNER_IN_MM * mouth, -CORNER_DOWN_MM * mouth, 0.0)
        d[left] = (-CORNER_IN_MM * mouth, -CORNER_DOWN_MM * mouth, 0.0)
    return d


def head_turn(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """(3, 3) float64 P = R_y(yaw) R_x(-pitch), model space (module docstring, 2)."""
    y, p = np.radians(yaw_deg), np.radians(-pitch_deg)
    turn = np.array([[np.cos(y), 0.0, np.sin(y)], [0.0, 1.0, 0.0], [-np.sin(y), 0.0, np.cos(y)]])
    nod = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(p), -np.sin(p)], [0.0, np.sin(p), np.cos(p)]])
    return turn @ nod


def paint_mouth(model: PersonModel, colour: tuple[int, int, int] = MOUTH_COLOUR
                ) -> np.ndarray:
    """The model's texture with the mouth cavity's texels painted (module docstring, 1).

    Returns:
        (H, W, 3) uint8 RGB, a copy.
    """
    texture = model.texture.copy()
    h, w = texture.shape[:2]
    mesh = model.mesh
    cavity = mesh.triangles[mesh.tags == Tag.MOUTH_INTERIOR]
    corners = mesh.uv[cavity].astype(np.float64) * (w, -h) + (0.0, h)  # (K, 3, 2) px, rows down
    polygons = [np.rint(c * 8).astype(np.int32) for c in corners]  # 3 fractional bits
    cv2.fillPoly(texture, polygons, colour, lineType=cv2.LINE_8, shift=3)
    return texture


def close_eyes(image: np.ndarray, points: np.ndarray, closure: float) -> np.ndarray:
    """Close both eyes of a face by a 2D lid warp (module docstring, 5).

    Args:
        image: (H, W, 3) uint8 frame (any channel order).
        points: (68, 2) the face's landmarks in it, px (iBUG order).
        closure: 0 (open, the image is returned as is) .. 1 (the lid meets the lower lid).

    Returns:
        (H, W, 3) uint8, a new image (or ``image`` itself at closure 0).
    """
    if closure <= 1e-3:
        return image
    out = image.copy()
    for corners, upper, lower, brow in (((36, 39), (37, 38), (41, 40), (18, 19, 20)),
                                        ((42, 45), (43, 44), (47, 46), (23, 24, 25))):
        _close_eye(out, image, points, corners, upper, lower, brow, min(closure, 1.0))
    return out


def _close_eye(out: np.ndarray, image: np.ndarray, points: np.ndarray,
               corners: tuple[int, int], upper: tuple[int, int], lower: tuple[int, int],
               brow: tuple[int, int, int], closure: float) -> None:
    """Warp one eye of ``image`` into ``out``: per column x between the eye corners, the lid
    edge y_u(x) moves to y_e = y_u + closure (y_l - y_u); rows [y_top, y_e] sample the rows
    [y_top, y_u] (the lid skin, stretched), rows below y_e are left as they are."""
    a, b = points[corners[0]], points[corners[1]]
    xs_u = [a[0], *points[list(upper), 0], b[0]]
    ys_u = [a[1], *points[list(upper), 1], b[1]]
    xs_l = [a[0], *points[list(lower), 0], b[0]]
    ys_l = [a[1], *points[list(lower), 1], b[1]]
    x0, x1 = int(np.floor(a[0])), int(np.ceil(b[0]))
    brow_y = float(points[list(brow), 1].mean())
    band = LID_BAND * max(float(np.mean(ys_u)) - brow_y, 2.0)
    y0 = int(np.floor(min(ys_u) - band)) - 1
    y1 = int(np.ceil(max(ys_l))) + 2
    h, w = image.shape[:2]
    x0, x1, y0, y1 = max(x0, 0), min(x1, w - 1), max(y0, 0), min(y1, h - 1)
    if x1 <= x0 or y1 <= y0:
        return
    x = np.arange(x0, x1 + 1, dtype=np.float64)
    y_u = np.interp(x, xs_u, ys_u)
    y_l = np.maximum(np.interp(x, xs_l, ys_l), y_u)
    y_e = y_u + closure * (y_l - y_u)
    y_top = y_u - band
    rows = np.arange(y0, y1 + 1, dtype=np.float64)[:, None]
    scale = (y_u - y_top) / np.maximum(y_e - y_top, 1e-6)
    stretched = y_top + (rows - y_top) * scale
    inside = (rows >= y_top) & (rows <= y_e)
    map_y = np.where(inside, stretched, rows).astype(np.float32)
    map_x = np.broadcast_to(x[None, :], map_y.shape).astype(np.float32)
    patch = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
    # The lid's skin: the colour under the eye (the stretched band is often in shadow).
    below = image[min(int(max(ys_l)) + 2, h - 1):min(int(max(ys_l)) + 2 + int(band) + 2, h),
                  x0:x1 + 1]
    if below.size:
        skin = np.median(below.reshape(-1, 3), axis=0).astype(np.float32)
        rise = np.clip((rows - y_top) / np.maximum(y_u - y_top, 1e-6), 0.0, 1.0)
        taper = np.sqrt((y_l - y_u) / max(float((y_l - y_u).max()), 1e-6))
        weight = LID_SKIN * closure * rise * rise * (3.0 - 2.0 * rise) * taper \
            * (rows <= y_e - 1.0)
        weight = weight[..., None]
        patch = patch * (1.0 - weight) + skin * weight
    lash = np.exp(-0.5 * ((rows - y_e) / 1.0) ** 2) * closure * 0.6  # a dark line at the edge
    patch *= 1.0 - lash[..., None]
    out[y0:y1 + 1, x0:x1 + 1] = np.clip(patch, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class PerformanceResult:
    """What ``perform`` wrote.

    Attributes:
        path: the performer video (H.264 ``.mp4``).
        frames: how many frames.
        rate_hz: its frame rate.
        values: (frames, 5) float64 the script's channels at each frame (``CHANNELS``).
        seconds: wall time, bootstrap model included.
    """

    path: Path
    frames: int
    rate_hz: float
    values: np.ndarray
    seconds: float


class Performer:
    """Renders performer frames of one portrait (module docstring).

    Args:
        image: (H, W, 3) uint8 BGR still portrait with one face.
        bootstrap: the bootstrap model's build from that still (``Performer.bootstrap``).

    Usage: ``with Performer(image, build) as p: bgr = p.frame(values_row)``.
    """

    def __init__(self, image: np.ndarray, bootstrap: BuildResult) -> None:
        fit = bootstrap.fit
        pose = fit.poses[fit.neutral]
        if pose is None:
            raise PerformerError("the portrait's neutral frame has no head pose")
        self.image = image
        self.height, self.width = image.shape[:2]
        model = bootstrap.model
        self.mesh: Mesh = model.mesh
        rig = Rig(model.mesh)
        vertices = model.mesh.vertices
        centres = np.concatenate([model.mesh.landmarks, model.mesh.phantoms, rig.anchors])
        weights = VolumeMorph(vertices[centres], vertices).weights.copy()
        weights[rig.eyeball_vertices] = 0.0
        self._weights = weights  # (N, M): vertices move by weights @ (M, 3) displacements
        self._follow = rig.follow  # (13,) the phantoms' share of the chin's move
        self._neutral = vertices.astype(np.float32)
        self.pose: Pose = pose
        c = model.camera
        self._intrinsics = Intrinsics(c.fx, c.fy, c.cx, c.cy, self.width, self.height)
        landmarks = model.mesh.vertices[model.mesh.landmarks].astype(np.float64)
        self.pivot = landmarks.mean(axis=0) + np.asarray(PIVOT)
        self._head_points = np.concatenate([model.mesh.landmarks[:17], model.mesh.phantoms])
        rest = self.camera(0.0, 0.0).project(model.mesh.vertices[self._head_points])
        self._rest_points = rest.astype(np.float32)
        self._head_mask = _head_mask(rest, float(rest[8, 1]), self.width, self.height)
        rows, cols = np.nonzero(self._head_mask > 1e-3)
        self._head_box = (int(cols.min()), int(rows.min()), int(cols.max()) + 1,
                          int(rows.max()) + 1)  # x0, y0, x1, y1: where the mask is not 0
        self._renderer = MeshRenderer(self.width, self.height, samples=0)
        self._renderer.set_mesh(len(self.mesh.vertices), self.mesh.triangles, self.mesh.uv)
        self._renderer.set_texture(paint_mouth(model))

    @staticmethod
    def bootstrap(image: np.ndarray, folder: str | os.PathLike[str],
                  progress: Progress = no_progress) -> BuildResult:
        """Build the bootstrap model of a still (module docstring, 1) in ``folder``: the
        one-photo build of ``facewire model build PHOTO`` (``sender.enroll.build.build_photo``).

        Raises:
            PerformerError: no face, or no usable fit, in the image.
        """
        try:
            return build_photo(image, Path(folder) / "still.fwm", name="portrait",
                               progress=progress)
        except BuildError as exc:
            raise PerformerError(f"the portrait cannot be modelled: {exc}") from None

    def camera(self, yaw_deg: float, pitch_deg: float) -> Camera:
        """The camera seeing the head turned by (yaw, pitch) about the pivot."""
        turn = head_turn(yaw_deg, pitch_deg)
        r0, t0 = self.pose.rotation, self.pose.translation
        return Camera(self._intrinsics,
                      Pose(r0 @ turn, r0 @ (self.pivot - turn @ self.pivot) + t0))

    def frame(self, values: np.ndarray) -> np.ndarray:
        """One performer frame.

        Args:
            values: (5,) the channels at this frame, ``CHANNELS`` order.

        Returns:
            (H, W, 3) uint8 BGR frame.
        """
        yaw, pitch, brows, mouth, blink = (float(v) for v in values)
        camera = self.camera(yaw, pitch)
        vertices = self.morph(brows, mouth)
        face = self._renderer.render(vertices, camera)[..., ::-1]
        points = camera.project(vertices[self.mesh.landmarks])
        head = camera.project(self.mesh.vertices[self._head_points]).astype(np.float32)
        background = self.image
        affine, _ = cv2.estimateAffine2D(self._rest_points, head, method=cv2.LMEDS)
        if affine is not None:
            x0, y0, x1, y1 = self._head_box
            affine[:, 2] -= (x0, y0)  # into the box's own pixels
            moved = cv2.warpAffine(self.image, affine, (x1 - x0, y1 - y0),
                                   flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
            background = self.image.copy()
            background[y0:y1, x0:x1] = _blend(moved, self.image[y0:y1, x0:x1],
                                              self._head_mask[y0:y1, x0:x1])
        out = _blend(face, background, _face_mask(points, self.width, self.height))
        return close_eyes(out, points, blink)

    def morph(self, brows: float, mouth: float) -> np.ndarray:
        """(N, 3) float32 the mesh's vertices under an expression (module docstring, 3)."""
        d = face_displacements(brows, mouth)
        centres = np.zeros((self._weights.shape[1], 3), np.float32)
        centres[:68] = d
        centres[68:68 + len(self._follow)] = self._follow[:, None] * d[8]
        return self._neutral + self._weights @ centres

    def release(self) -> None:
        """Free the renderer's context."""
        self._renderer.release()

    def __enter__(self) -> Performer:
        return self

    def __exit__(self, *_: object) -> None:
        self.release()


def perform(out: str | os.PathLike[str], script: tuple[Cue, ...] = SCRIPT,
            length_s: float = LENGTH_S, rate_hz: float = RATE_HZ,
            image: np.ndarray | None = None,
            progress: Progress = no_progress) -> PerformanceResult:
    """Write the performer video of a script.

    Args:
        out: the ``.mp4`` to write (replaced).
        script: the cues.
        length_s: the video's length, seconds (> 0).
        rate_hz: its frame rate.
        image: (H, W, 3) uint8 BGR still portrait; ``portrait()`` by default.
        progress: wraps an iterable to show progress.

    Returns:
        What was written, with the script's channel values per frame.

    Raises:
        PerformerError: no usable face in the portrait, or a bad length or rate.
    """
    start = time.perf_counter()
    if not (np.isfinite(length_s) and length_s > 0 and np.isfinite(rate_hz) and rate_hz > 0):
        raise PerformerError(f"length_s and rate_hz: expected positive numbers, got "
                             f"{length_s!r}, {rate_hz!r}")
    if image is None:
        image = portrait()
    if image.shape[0] % 2 or image.shape[1] % 2:  # H.264 4:2:0 wants an even size
        image = image[:image.shape[0] // 2 * 2, :image.shape[1] // 2 * 2]
    count = int(round(length_s * rate_hz))
    values = script_values(script, np.arange(count) / rate_hz)
    with tempfile.TemporaryDirectory(prefix="facewire-portrait-") as folder:
        build = Performer.bootstrap(image, folder, progress)
    out = Path(out)
    with Performer(image, build) as performer, \
            VideoWriter(out, performer.width, performer.height, rate_hz) as writer:
        for k in progress(range(count), "performing", count):
            writer.write(np.ascontiguousarray(performer.frame(values[k])[..., ::-1]))
    return PerformanceResult(out, count, rate_hz, values, time.perf_counter() - start)


def _face_mask(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) float32 0 .. 1: the face polygon (module docstring, 4), feathered inward."""
    jaw = points[0:17]
    brows = points[26:16:-1].copy()  # 26 .. 17: left to right across the top
    eyes = points[36:48, 1].mean()
    lift = FOREHEAD * max(eyes - float(brows[:, 1].mean()), 1.0)
    brows[:, 1] -= lift
    polygon = np.rint(np.concatenate([jaw, brows]) * 8).astype(np.int32)
    mask: np.ndarray = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, [polygon], 255, lineType=cv2.LINE_AA, shift=3)
    mask = cv2.erode(mask, np.ones((3, 3), np.uint8), iterations=FEATHER_PX // 2)
    size = 2 * FEATHER_PX + 1
    return cv2.GaussianBlur(mask.astype(np.float32) / 255.0, (size, size), 0)


def _head_mask(points: np.ndarray, chin_y: float, width: int, height: int) -> np.ndarray:
    """(H, W) float32 0 .. 1: an ellipse around the head's projected points, ``HEAD_MASK_SCALE``
    times their half-extent, raised by a fifth of its height (hat and hair), faded out toward
    the chin (row ``chin_y``; the neck and shoulders below stay), feathered."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = (lo + hi) / 2
    axes = HEAD_MASK_SCALE * (hi - lo) / 2
    centre[1] -= 0.2 * axes[1]
    mask: np.ndarray = np.zeros((height, width), np.float32)
    cv2.ellipse(mask, (int(centre[0]), int(centre[1])), (int(axes[0]), int(axes[1])), 0.0,
                0.0, 360.0, 1.0, -1)
    size = int(0.25 * axes[0]) * 2 + 1
    mask = cv2.GaussianBlur(mask, (size, size), 0)
    fade = 0.15 * (hi[1] - lo[1])
    rows = np.arange(height, dtype=np.float32)
    mask *= np.clip((chin_y - rows) / fade, 0.0, 1.0)[:, None]
    return mask


def _blend(top: np.ndarray, bottom: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: ``top * alpha + bottom * (1 - alpha)``, alpha (H, W) float32."""
    return cv2.blendLinear(top, bottom, alpha, 1.0 - alpha)
