"""Fitting the generic head to one person from the 68 tracked points of a video.

Input: per frame, the tracker's 68 image points (pixels, origin top-left, y down) or None,
and the camera intrinsics. Output (``Fit``): the person's neutral mesh (the generic head warped
so its landmark vertices sit on the person's neutral 3D landmarks), those landmarks, a head
pose per frame, the neutral frame, the frames to texture from, and how depth was obtained.

Frames and poses are ``models.geometry``'s: model space in mm (y up, z toward the camera),
GL camera poses ``X_cam = R X + t`` (``Pose``), head at ``t_z < 0``; the OpenCV solvers work
in OpenCV's camera frame, converted by ``S = diag(1, -1, -1)``. Yaw and pitch are
``Pose.yaw_deg`` and ``Pose.pitch_deg`` (``models.infra.raster.orbit_pose`` with camera yaw
``a`` gives face yaw ``-a``).

1. Scale. One camera cannot observe absolute size: a head twice as large twice as far away
   gives the same image. We fix it by assuming the person's outer eye corners (36, 45) are as
   far apart as the generic head's (91 mm); every length and every translation is in that
   unit.

2. Pose per frame: ``cv2.solvePnP`` (SQPnP, then Levenberg-Marquardt refinement) of the
   current 3D landmark estimate against the image points, on ``POSE_POINTS`` (brows, nose,
   the four eye corners): not the jaw contour 0-16, whose image points are silhouette points
   that slide over the 3D surface as the head turns, and not the lids or lips, which move with
   blinks and speech. A pose is rejected (None) when the solver fails, puts the head behind
   the camera, or leaves a median reprojection error above ``MAX_POSE_ERROR`` of the image
   eye distance.

3. Neutral frame (``choose_neutral``): among posed frames, the smallest sum of squared,
   scaled penalties (``_neutral_costs``): |yaw| / 10 deg; pitch away from the video's median
   pitch / 10 deg (the person's natural head carriage, not the generic head's, is level);
   eyes less open than 85 % of the video's 90th-percentile eye aspect ratio (per 0.1);
   inner-lip gap / 4 % of the eye distance; mouth width away from the video's median / 5 %;
   expression residual (RMS reprojection error of the non-contour points after pose) above
   the video's median, per 50 % of that median. The build may restrict the choice to given
   frames (``neutral_among``: its clean texture views, ``sender.enroll.evidence``); the
   medians and percentiles stay the whole video's. At least ``MIN_FACE_FRAMES`` frames with a
   face are required (else ``FitError``): fewer give no meaningful percentiles and medians.

4. Depth. If the posed frames' yaw spans at least ``SFM_MIN_YAW_RANGE_DEG`` (20 deg), depth
   comes from rigid structure from motion: a point at depth error dz moves by dz sin(yaw)
   across the image, so over 20 deg a 5 mm error shows as 1.7 mm, about 2 px on a face whose
   eyes are 100 px apart, which a few dozen frames of 1-2 px tracker noise resolve; over a
   narrower range the data cannot beat the generic head. Up to ``SFM_FRAMES`` frames spread
   evenly in yaw (in each yaw bin the one with the least expression) are bundle-adjusted
   (``scipy.optimize.least_squares``, soft-L1 loss at 2 px, sparse Jacobian) over the shape of
   ``SFM_POINTS`` (all but the jaw contour and the inner lips) and the per-frame poses:

       sum_f,i rho(|pi(R_f X_i + t_f) - p_fi|^2 / sigma_px^2)
         + sum_i |X_i - G_i|^2 / sigma_prior^2 + (|X_36 - X_45| - d_G)^2 / sigma_eye^2,

   with the generic landmarks ``G`` as the weak prior (sigma_prior 10 mm; it also fixes the
   gauge: the shape's position and orientation), sigma_px 1 px, and the eye distance held at
   the generic head's (sigma_eye 0.01 mm). The result is rigidly aligned to ``G``;
   ``depth_change_mm`` is the RMS of ``z - G_z`` over ``SFM_POINTS`` (0.0 with generic
   depth). The jaw contour keeps the generic depth either way.

5. The person's neutral landmarks. The neutral frame is posed against the shape of step 4;
   each image point is back-projected along its camera ray to the plane ``z = z_i`` of model
   space (its depth from step 4), so x and y are the person's own (left-right asymmetry kept)
   and reproject onto the neutral frame's points. The jaw contour gets the generic depth
   (its x and y are the frontal silhouette's). Then the landmarks are scaled about their
   centroid so the eye distance is exactly the generic head's. The inner lips (60-67) are not
   back-projected: they are the edges of the mesh's 2 mm lip slit, and closed lips put the
   tracker's upper and lower points on top of each other (or crossed), which would close or
   invert the slit; they follow the morph, and ``landmarks3d[60:68]`` reports where they land.

6. Warp. A global similarity first: scale ``s`` and translation ``t`` fitted by least squares
   from the generic landmarks 0-59 to the targets (no rotation: step 4 already put the
   targets in the generic frame), applied to every vertex. Then a ``VolumeMorph``
   (multiquadric, ``lam = WARP_LAM`` = 1e-4, so the centres land within about 0.01 mm)
   carries the residual ``target - (s G + t)`` at the centres: the landmark vertices 0-59, the
   13 phantoms and ``N_ANCHORS`` anchors on the scalp, the back of the head, the ears and the
   neck (at least ``ANCHOR_CLEARANCE_MM`` from every landmark and phantom, spread by
   farthest-point sampling). Anchors, and the phantoms of the forehead, temples and crown, have
   zero residual, so the skull moves by the similarity only (without anchors the multiquadric
   moves it by about 2 mm; with 40 anchors still up to 1.2 mm between them, 50 mm from the
   face). The field is therefore also faded out with the distance ``r`` from the nearest moving
   centre (landmark or jaw phantom): multiplied by a smoothstep that is 1 for ``r`` up to
   30 mm and 0 beyond 60 mm (``FALLOFF_MM``), so everything further from the face than that
   moves by the similarity exactly. The phantoms that ring the jaw (``JAW_PHANTOMS``:
   cheekbones, jaw angles, jaw, under the chin) take the mean residual of their two nearest contour
   landmarks: they mark the face's edge, which in a fit is the person's jaw line itself (on
   lp_d0.mp4 the contour moves 20-27 mm from the generic one; with those phantoms held, the
   cheek folded over between contour point 0 and the cheekbone phantom 7 mm away). Eyeball
   vertices are not bent: each eyeball moves by the similarity plus the mean residual of its
   eye's six landmarks.

7. Flips. A non-eyeball triangle whose normal turns by more than 90 deg (dot with the
   generic normal < 0) is a fold. If any appears, the whole residual is halved, up to
   ``MAX_DAMPING_STEPS`` times, until none does; ``landmarks3d`` then reports the damped
   mesh's landmark vertices (``Fit`` does not carry the factor). None of the 12 shared
   videos needed it (first 300 frames each).

8. Final poses: every frame with points is posed again (step 2) against the fitted mesh's
   landmark vertices, which is what the texture projection needs.

Size: this module is over 600 lines because this docstring states the method of all eight
steps (about 100 lines), which the code follows step by step with helpers of its own (only
step 3's frame costs, ``frame_costs``, also serve another module: ``sender.enroll.evidence``).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import TypeVar

import cv2
import numpy as np
import scipy.sparse
from scipy.optimize import least_squares

from facewire.models.geometry import (
    Intrinsics,
    Pose,
    project,
    rotation_matrices,
    rotation_matrix,
    rotation_vector,
)
from facewire.models.landmarks import N_LANDMARKS, PHANTOM_NAMES, eye_aspect_ratio
from facewire.models.mesh import Mesh, Tag
from facewire.models.morph import VolumeMorph
from facewire.protocol.errors import FacewireError

MIN_FACE_FRAMES = 10
POSE_POINTS = np.array([*range(17, 36), 36, 39, 42, 45])
CONTOUR = np.arange(0, 17)
INNER_LIP = np.arange(60, 68)
SFM_POINTS = np.arange(17, 60)
WARP_CENTRES = np.arange(0, 60)
MAX_POSE_ERROR = 0.15  # median reprojection error / image eye distance beyond which pose fails
SFM_MIN_YAW_RANGE_DEG = 20.0
SFM_FRAMES = 30
SFM_SIGMA_PX = 1.0
SFM_SIGMA_PRIOR_MM = 10.0
SFM_SIGMA_EYE_MM = 0.01
SFM_LOSS_SCALE = 2.0  # soft-L1 knee, in units of SFM_SIGMA_PX
SIDE_VIEW_MIN_SEPARATION_DEG = 15.0
SIDE_VIEWS_PER_SIDE = 2
N_ANCHORS = 40
ANCHOR_CLEARANCE_MM = 30.0
WARP_LAM = 1e-4
FALLOFF_MM = (30.0, 60.0)
MAX_DAMPING_STEPS = 6
# Phantoms on the jaw side of the ring follow the jaw contour (step 6), the rest stay put.
JAW_PHANTOMS = np.array([i for i, name in enumerate(PHANTOM_NAMES)
                         if name.split("_")[0] in ("cheekbone", "jaw", "under")])


class FitError(FacewireError, ValueError):
    """The frames do not allow a fit; the message says what is wrong."""


@dataclass(frozen=True)
class Fit:
    """The generic head fitted to one person (fields as in the module docstring).

    Attributes:
        mesh: the person's neutral mesh (generic topology, uv, tags, landmarks, phantoms), mm.
        landmarks3d: (68, 3) float64 the neutral 3D landmarks (the mesh's landmark vertices).
        poses: per input frame, the pose of ``mesh`` in that frame, or None.
        neutral: index of the neutral frame in the input.
        views: frames to texture from: the neutral frame, then up to 4 side views.
        depth: ``"structure-from-motion"`` or ``"generic"``.
        depth_change_mm: RMS depth change of the SfM landmarks from the generic head, mm.
        yaw_range_deg: (min, max) yaw over the posed frames, degrees.
    """

    mesh: Mesh
    landmarks3d: np.ndarray
    poses: tuple[Pose | None, ...]
    neutral: int
    views: tuple[int, ...]
    depth: str
    depth_change_mm: float
    yaw_range_deg: tuple[float, float]


def fit_person(
    points: Sequence[np.ndarray | None],
    camera: Intrinsics,
    head: Mesh | None = None,
    progress: Callable[[int], None] | None = None,
    neutral_among: Collection[int] | None = None,
) -> Fit:
    """Fit the generic head to the person seen in a video (method in the module docstring).

    Args:
        points: per frame, (68, 2) float image points (pixels, origin top-left), or None when
            the frame has no face.
        camera: the camera's intrinsics (``models.geometry.intrinsics_guess`` when unknown).
        head: the generic head; ``models.head.generic_head()`` when None.
        progress: called with the percentage done (int, 0-100) after each stage.
        neutral_among: frames the neutral frame may be chosen from (the build's clean
            views, ``sender.enroll.evidence``); any posed frame when None or when none of
            them is posed.

    Returns:
        The ``Fit``.

    Raises:
        FitError: no face in any frame, too few frames with a face, or too few posed frames.
        ValueError: not an ``Intrinsics``, or a malformed points array (naming the frame).
    """
    if not isinstance(camera, Intrinsics):
        raise ValueError(f"camera: expected a models.geometry.Intrinsics, got "
                         f"{type(camera).__name__}")
    frames = [_check_frame(i, p) for i, p in enumerate(points)]
    faces = [i for i, p in enumerate(frames) if p is not None]
    if not faces:
        raise FitError("no face in any frame")
    if len(faces) < MIN_FACE_FRAMES:
        raise FitError(f"only {len(faces)} frames with a face; need at least {MIN_FACE_FRAMES}")
    if head is None:
        from facewire.models.head import generic_head

        head = generic_head()
    report = progress or (lambda _: None)
    generic = head.vertices[head.landmarks].astype(np.float64)
    eye_mm = float(np.linalg.norm(generic[36] - generic[45]))

    poses = _pose_all(frames, generic, camera)
    posed = [i for i in faces if poses[i] is not None]
    if len(posed) < MIN_FACE_FRAMES:
        raise FitError(f"only {len(posed)} frames with a head pose; need at least "
                       f"{MIN_FACE_FRAMES}")
    report(20)

    shape, poses, depth, depth_change = _depth(frames, posed, poses, generic, camera, eye_mm)
    report(50)

    among = None if neutral_among is None else set(neutral_among)
    neutral = choose_neutral(frames, poses, shape, camera, among)
    targets = _neutral_landmarks(_present(frames, neutral), _present(poses, neutral), shape,
                                 head, camera, eye_mm)
    report(60)

    mesh = warp_head(head, targets)
    report(90)

    fit = _final_fit(frames, faces, mesh, neutral, camera, depth, depth_change)
    report(100)
    return fit


def _depth(frames: Sequence[np.ndarray | None], posed: Sequence[int],
           poses: list[Pose | None], generic: np.ndarray, camera: Intrinsics,
           eye_mm: float) -> tuple[np.ndarray, list[Pose | None], str, float]:
    """Step 4: the (68, 3) landmark shape, its frames' poses, the depth's kind and
    ``depth_change_mm``: by structure from motion (and posed again against its result) when
    the posed frames' yaw spans ``SFM_MIN_YAW_RANGE_DEG``, else the generic head's."""
    yaws = np.array([_present(poses, i).yaw_deg for i in posed])
    if yaws.max() - yaws.min() < SFM_MIN_YAW_RANGE_DEG:
        return generic.copy(), poses, "generic", 0.0
    costs = _neutral_costs(frames, poses, posed, generic, camera)
    chosen = _spread_by_yaw(posed, yaws, costs["expression"], SFM_FRAMES)
    estimate = _structure_from_motion([_present(frames, i) for i in chosen],
                                      [_present(poses, i) for i in chosen], generic, camera,
                                      eye_mm)
    shape = generic.copy()
    shape[SFM_POINTS] = estimate
    depth_change = float(np.sqrt(np.mean((estimate[:, 2] - generic[SFM_POINTS, 2]) ** 2)))
    return shape, _pose_all(frames, shape, camera), "structure-from-motion", depth_change


def _final_fit(frames: Sequence[np.ndarray | None], faces: Sequence[int], mesh: Mesh,
               neutral: int, camera: Intrinsics, depth: str, depth_change: float) -> Fit:
    """Step 8: every frame posed against the fitted mesh's landmarks, the views chosen."""
    landmarks3d = mesh.vertices[mesh.landmarks].astype(np.float64)
    poses = _pose_all(frames, landmarks3d, camera)
    if poses[neutral] is None:
        raise FitError(f"frame {neutral}: no head pose against the fitted mesh")
    posed = [i for i in faces if poses[i] is not None]
    costs = _neutral_costs(frames, poses, posed, landmarks3d, camera)
    angles = np.array([(p.yaw_deg, p.pitch_deg) for p in (_present(poses, i) for i in posed)])
    views = _choose_views(neutral, posed, angles[:, 0], costs["expression"])
    return Fit(mesh=mesh, landmarks3d=landmarks3d, poses=tuple(poses), neutral=neutral,
               views=views, depth=depth, depth_change_mm=depth_change,
               yaw_range_deg=(float(angles[:, 0].min()), float(angles[:, 0].max())))


def choose_neutral(points: Sequence[np.ndarray | None], poses: Sequence[Pose | None],
                   shape: np.ndarray, camera: Intrinsics,
                   among: Collection[int] | None = None) -> int:
    """The most neutral frame: frontal, eyes open, mouth closed and relaxed, least expression.

    Args:
        points: per frame, (68, 2) image points or None.
        poses: per frame, the pose of ``shape`` or None.
        shape: (68, 3) float64 3D landmarks the poses refer to, mm.
        camera: the camera's intrinsics.
        among: only these frames may be chosen (all when None or when none is posed); the
            costs' medians and percentiles are still the whole video's.

    Returns:
        Index of the frame with the lowest neutral cost (module docstring, step 3).

    Raises:
        FitError: no frame has both points and a pose.
    """
    posed = [i for i, (p, q) in enumerate(zip(points, poses)) if p is not None and q is not None]
    if not posed:
        raise FitError("no frame with a face and a head pose")
    costs = _neutral_costs(points, poses, posed, shape, camera)["total"]
    if among is not None and any(i in among for i in posed):
        costs = np.where([i in among for i in posed], costs, np.inf)
    return posed[int(np.argmin(costs))]


def warp_head(head: Mesh, targets: np.ndarray) -> Mesh:
    """The generic head warped so landmark vertices 0-59 land on ``targets`` (steps 6-7).

    Args:
        head: the generic head.
        targets: (68, 3) float64 target landmarks, mm, in the head's frame; rows 60-67 (inner
            lips) are ignored.

    Returns:
        A mesh with the head's topology, uv, tags, landmarks and phantoms and moved vertices.
    """
    targets = np.asarray(targets, dtype=np.float64)
    if targets.shape != (N_LANDMARKS, 3) or not np.isfinite(targets).all():
        raise ValueError(f"targets: expected finite (68, 3), got shape {targets.shape}")
    v = head.vertices.astype(np.float64)
    source = v[head.landmarks[WARP_CENTRES]]
    aim = targets[WARP_CENTRES]
    scale, shift = _scale_shift(source, aim)
    moved = scale * v + shift

    eyeball = {tag: np.unique(head.triangles[head.tags == tag]) for tag in
               (Tag.RIGHT_EYEBALL, Tag.LEFT_EYEBALL)}
    rigid = np.zeros(len(v), dtype=bool)
    for ids in eyeball.values():
        rigid[ids] = True
    bent = np.flatnonzero(~rigid)
    anchors = _anchors(head)
    centres = np.vstack([source, v[head.phantoms], v[anchors]])
    residual = np.zeros_like(centres)
    residual[: len(source)] = aim - (scale * source + shift)
    contour = v[head.landmarks[CONTOUR]]
    for j in JAW_PHANTOMS:
        nearest = np.argsort(np.linalg.norm(contour - v[head.phantoms[j]], axis=1))[:2]
        residual[len(source) + j] = residual[CONTOUR[nearest]].mean(axis=0)

    morph = VolumeMorph(centres.astype(np.float32), v[bent].astype(np.float32), lam=WARP_LAM)
    moving = np.vstack([source, v[head.phantoms[JAW_PHANTOMS]]])
    reach = np.array([np.linalg.norm(moving - p, axis=1).min() for p in v[bent]])
    near, far = FALLOFF_MM
    x = np.clip((far - reach) / (far - near), 0.0, 1.0)
    falloff = x * x * (3.0 - 2.0 * x)  # smoothstep: 1 within `near`, 0 beyond `far`
    field = falloff[:, None] * morph.weights.astype(np.float64)
    keep = head.tags != Tag.RIGHT_EYEBALL
    keep &= head.tags != Tag.LEFT_EYEBALL
    before = _face_normals(v, head.triangles[keep])
    eye_sets = ((Tag.RIGHT_EYEBALL, np.arange(36, 42)), (Tag.LEFT_EYEBALL, np.arange(42, 48)))
    factor = 1.0
    for _ in range(MAX_DAMPING_STEPS + 1):
        out = moved.copy()
        d = factor * residual
        out[bent] += field @ d
        for tag, eye in eye_sets:
            out[eyeball[tag]] += d[eye].mean(axis=0)  # WARP_CENTRES starts at landmark 0
        after = _face_normals(out, head.triangles[keep])
        if not np.any((before * after).sum(axis=1) < 0):
            break
        factor *= 0.5
    return Mesh(vertices=out.astype(np.float32), triangles=head.triangles, uv=head.uv,
                tags=head.tags, landmarks=head.landmarks, phantoms=head.phantoms)


def flipped_triangles(before: Mesh, after: Mesh, tag: Tag | None = Tag.SKIN) -> np.ndarray:
    """Indices of triangles (of ``tag``, or all when None) whose normal turned by > 90 deg.

    Args:
        before, after: two meshes with the same triangles.
        tag: which triangles to check.

    Returns:
        (K,) int64 triangle indices.
    """
    if before.triangles.shape != after.triangles.shape:
        raise ValueError("before, after: different triangle arrays")
    sel = np.arange(len(before.triangles)) if tag is None else np.flatnonzero(before.tags == tag)
    a = _face_normals(before.vertices.astype(np.float64), before.triangles[sel])
    b = _face_normals(after.vertices.astype(np.float64), after.triangles[sel])
    return sel[(a * b).sum(axis=1) < 0]


# ----------------------------------------------------------------------------------------


def _check_frame(i: int, p: np.ndarray | None) -> np.ndarray | None:
    """Validate frame ``i``'s points; (68, 2) float64 or None."""
    if p is None:
        return None
    a = np.asarray(p)
    if a.shape != (N_LANDMARKS, 2) or a.dtype.kind not in "fiu":
        raise ValueError(f"points[{i}]: expected a (68, 2) numeric array, got shape {a.shape}, "
                         f"dtype {a.dtype}")
    if not np.isfinite(a).all():
        raise ValueError(f"points[{i}]: contains NaN or infinity")
    return a.astype(np.float64)


_T = TypeVar("_T")


def _present(items: Sequence[_T | None], i: int) -> _T:
    """``items[i]`` of a frame known to have it (points, or a pose: ``posed``)."""
    item = items[i]
    assert item is not None, f"frame {i}: expected a value"
    return item


def _solve_pose(shape: np.ndarray, image: np.ndarray, camera: Intrinsics) -> Pose | None:
    """PnP of ``shape`` (68, 3) against ``image`` (68, 2) on POSE_POINTS; None on failure."""
    obj = np.ascontiguousarray(shape[POSE_POINTS])
    img = np.ascontiguousarray(image[POSE_POINTS])
    k = camera.matrix()
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec, tvec)
    except cv2.error:
        return None
    if not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        return None
    r_cv, t_cv = rotation_matrix(rvec.ravel()), tvec.ravel()
    if (obj @ r_cv.T + t_cv)[:, 2].min() <= 0:
        return None
    pose = Pose.from_opencv(r_cv, t_cv)
    eye_px = float(np.linalg.norm(image[36] - image[45]))
    error = np.linalg.norm(project(obj, pose, camera) - img, axis=1)
    if eye_px <= 0 or np.median(error) > MAX_POSE_ERROR * eye_px:
        return None
    return pose


def _pose_all(frames: Sequence[np.ndarray | None], shape: np.ndarray,
              camera: Intrinsics) -> list[Pose | None]:
    return [None if p is None else _solve_pose(shape, p, camera) for p in frames]


def _neutral_costs(frames: Sequence[np.ndarray | None], poses: Sequence[Pose | None],
                   posed: Sequence[int], shape: np.ndarray,
                   camera: Intrinsics) -> dict[str, np.ndarray]:
    """Per posed frame: ``total`` and ``expression`` (total without the pose terms) costs."""
    pts = np.stack([_present(frames, i) for i in posed])
    eye = np.linalg.norm(pts[:, 36] - pts[:, 45], axis=1)
    ear = np.array([eye_aspect_ratio(p).mean() for p in pts])
    gap = np.linalg.norm(pts[:, [61, 62, 63]] - pts[:, [67, 66, 65]], axis=2).mean(axis=1) / eye
    width = np.linalg.norm(pts[:, 48] - pts[:, 54], axis=1) / eye
    stable = np.arange(17, 68)
    resid = np.array([
        np.sqrt(np.mean(np.sum((project(shape[stable], _present(poses, i), camera)
                                - _present(frames, i)[stable]) ** 2, axis=1)))
        for i in posed]) / eye
    angles = np.array([(p.yaw_deg, p.pitch_deg) for p in (_present(poses, i) for i in posed)])
    ear_ref = np.percentile(ear, 90)
    expression = (
        (np.maximum(0.0, 0.85 - ear / max(ear_ref, 1e-9)) / 0.1) ** 2
        + (gap / 0.04) ** 2
        + ((width / np.median(width) - 1.0) / 0.05) ** 2
        + (np.maximum(0.0, resid / np.median(resid) - 1.0) / 0.5) ** 2
    )
    pose_cost = (angles[:, 0] / 10.0) ** 2 + ((angles[:, 1] - np.median(angles[:, 1])) / 10.0) ** 2
    return {"total": expression + pose_cost, "expression": expression,
            "residual": resid / max(float(np.median(resid)), 1e-12)}


def frame_costs(points: Sequence[np.ndarray | None], poses: Sequence[Pose | None],
                posed: Sequence[int], shape: np.ndarray,
                camera: Intrinsics) -> dict[str, np.ndarray]:
    """Per frame of ``posed``: the neutral cost (step 3) as ``total``, without its pose terms
    as ``expression``, and the landmarks' RMS residual against ``shape`` over the stable
    points 17-67 under the frame's pose, over the median of those frames, as ``residual``.

    Args:
        points: per frame, (68, 2) image points or None.
        poses: per frame, the pose of ``shape`` or None.
        posed: frames with both, at least one.
        shape: (68, 3) float64 3D landmarks the poses refer to, mm.
        camera: the camera's intrinsics.
    """
    return _neutral_costs(points, poses, posed, shape, camera)


def _spread_by_yaw(posed: Sequence[int], yaws: np.ndarray, expression: np.ndarray,
                   count: int) -> list[int]:
    """Up to ``count`` frames, one per equal yaw bin: the least expressive in each bin."""
    edges = np.linspace(yaws.min(), yaws.max(), count + 1)
    bins = np.clip(np.searchsorted(edges, yaws, side="right") - 1, 0, count - 1)
    chosen = []
    for b in range(count):
        members = np.flatnonzero(bins == b)
        if members.size:
            chosen.append(posed[int(members[np.argmin(expression[members])])])
    return chosen


def _structure_from_motion(frames: list[np.ndarray], poses: list[Pose], generic: np.ndarray,
                           camera: Intrinsics, eye_mm: float) -> np.ndarray:
    """Rigid bundle adjustment (step 4); returns (len(SFM_POINTS), 3) aligned to ``generic``."""
    prior = generic[SFM_POINTS]
    k, f = len(SFM_POINTS), len(frames)
    obs = np.stack([p[SFM_POINTS] for p in frames])  # (F, K, 2)
    i36 = int(np.flatnonzero(SFM_POINTS == 36)[0])
    i45 = int(np.flatnonzero(SFM_POINTS == 45)[0])
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    start = [prior.ravel()]
    for pose in poses:
        r_cv, t_cv = pose.to_opencv()
        start.append(rotation_vector(r_cv))
        start.append(t_cv)
    x0 = np.concatenate(start)

    def residuals(x: np.ndarray) -> np.ndarray:
        shape = x[: 3 * k].reshape(k, 3)
        ext = x[3 * k:].reshape(f, 6)
        cam = shape @ rotation_matrices(ext[:, :3]).transpose(0, 2, 1) + ext[:, None, 3:]
        z = np.maximum(cam[..., 2], 1e-6)
        uv = np.stack([cx + fx * cam[..., 0] / z, cy + fy * cam[..., 1] / z], axis=-1)
        eye = np.linalg.norm(shape[i36] - shape[i45])
        return np.concatenate([((uv - obs) / SFM_SIGMA_PX).ravel(),
                               ((shape - prior) / SFM_SIGMA_PRIOR_MM).ravel(),
                               [(eye - eye_mm) / SFM_SIGMA_EYE_MM]])

    sparsity = scipy.sparse.lil_matrix((2 * f * k + 3 * k + 1, 3 * k + 6 * f), dtype=np.int8)
    for j in range(f):
        for i in range(k):
            rows = slice(2 * (j * k + i), 2 * (j * k + i) + 2)
            sparsity[rows, 3 * i: 3 * i + 3] = 1
            sparsity[rows, 3 * k + 6 * j: 3 * k + 6 * j + 6] = 1
    for i in range(k):
        for c in range(3):
            sparsity[2 * f * k + 3 * i + c, 3 * i + c] = 1
    sparsity[-1, 3 * i36: 3 * i36 + 3] = 1
    sparsity[-1, 3 * i45: 3 * i45 + 3] = 1
    solution = least_squares(residuals, x0, jac_sparsity=sparsity.tocsr(), loss="soft_l1",
                             f_scale=SFM_LOSS_SCALE, x_scale="jac", ftol=1e-4, max_nfev=60,
                             method="trf", tr_solver="lsmr")
    shape = solution.x[: 3 * k].reshape(k, 3)
    rotation, shift = _rigid(shape, prior)
    return shape @ rotation.T + shift


def _rigid(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation R and translation t with R source + t ~ target (Kabsch)."""
    a, b = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((target - b).T @ (source - a))
    d = np.sign(np.linalg.det(u @ vt))
    rotation = u @ np.diag([1.0, 1.0, d]) @ vt
    return rotation, b - rotation @ a


def _scale_shift(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray]:
    """Least-squares uniform scale s and translation t with s source + t ~ target."""
    a, b = source.mean(axis=0), target.mean(axis=0)
    scale = float(((source - a) * (target - b)).sum() / ((source - a) ** 2).sum())
    return scale, b - scale * a


def _neutral_landmarks(image: np.ndarray, pose: Pose, shape: np.ndarray, head: Mesh,
                       camera: Intrinsics, eye_mm: float) -> np.ndarray:
    """Step 5: back-project the neutral frame's points to their model depths; (68, 3)."""
    depth = shape[:, 2].copy()
    depth[CONTOUR] = head.vertices[head.landmarks[CONTOUR], 2]
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    rays = np.column_stack([(image[:, 0] - cx) / fx, -(image[:, 1] - cy) / fy,
                            -np.ones(len(image))])  # GL camera frame
    r, t = pose.rotation, pose.translation
    model_rays = rays @ r  # R^T d per row
    origin = -(r.T @ t)  # camera centre in model space
    along = (depth - origin[2]) / model_rays[:, 2]
    out = origin + along[:, None] * model_rays
    out[INNER_LIP] = shape[INNER_LIP]
    centre = out.mean(axis=0)
    out = centre + (out - centre) * (eye_mm / np.linalg.norm(out[36] - out[45]))
    return out


def _anchors(head: Mesh) -> np.ndarray:
    """N_ANCHORS vertex indices on the scalp, back of the head, ears and neck (step 6)."""
    v = head.vertices.astype(np.float64)
    far_tags = np.isin(head.tags, [Tag.SCALP, Tag.EAR])
    candidates = np.zeros(len(v), dtype=bool)
    candidates[np.unique(head.triangles[far_tags])] = True
    skin = np.zeros(len(v), dtype=bool)
    skin[np.unique(head.triangles[head.tags == Tag.SKIN])] = True
    candidates |= skin & ((v[:, 2] < 0.0) | (v[:, 1] < -125.0))
    face = np.vstack([v[head.landmarks], v[head.phantoms]])
    ids = np.flatnonzero(candidates)
    nearest = np.min(np.linalg.norm(v[ids, None, :] - face[None], axis=2), axis=1)
    ids = ids[nearest >= ANCHOR_CLEARANCE_MM]
    pts = v[ids]
    chosen = [int(np.argmax(pts[:, 1]))]  # start at the top of the head
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    for _ in range(N_ANCHORS - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[nxt], axis=1))
    return ids[chosen]


def _face_normals(v: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (v[triangles[:, k]] for k in range(3))
    return np.cross(b - a, c - a)


def _choose_views(neutral: int, posed: Sequence[int], yaws: np.ndarray,
                  expression: np.ndarray) -> tuple[int, ...]:
    """Neutral first, then per side up to SIDE_VIEWS_PER_SIDE frames of largest |yaw|.

    Candidates are the frames with expression cost at most the 75th percentile (falling back
    to all frames of a side when none qualifies); each view is at least
    SIDE_VIEW_MIN_SEPARATION_DEG in yaw from the neutral frame and from the views already taken.
    """
    index = {f: k for k, f in enumerate(posed)}
    taken = [yaws[index[neutral]]]
    views = [neutral]
    calm = expression <= np.percentile(expression, 75)
    for sign in (1.0, -1.0):
        side = sign * yaws > 0
        pool = np.flatnonzero(side & calm)
        if pool.size == 0:
            pool = np.flatnonzero(side)
        for k in pool[np.argsort(-np.abs(yaws[pool]))]:
            if sum(1 for f in views[1:] if np.sign(yaws[index[f]]) == sign) >= \
                    SIDE_VIEWS_PER_SIDE:
                break
            if all(abs(yaws[k] - y) >= SIDE_VIEW_MIN_SEPARATION_DEG for y in taken):
                views.append(posed[k])
                taken.append(yaws[k])
    return tuple(views)
