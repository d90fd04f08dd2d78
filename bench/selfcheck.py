"""The build checks itself: the finished model rendered at its own enrollment frames, scored.

Issue 16, part 1. ``facewire model build`` runs it after the build (``facewire.cli``), on
the model before it is saved, and stores the result in the model (``models.manifest``'s
optional ``self_check``), so that ``model info`` shows it too.

Scoring (``score_frames``). At most ``MAX_FRAMES`` (40) of the build's frames with a face,
evenly spread over its range (``pick_frames``; a photo: the photo, one frame), go through
``bench quality``'s own machinery: the real sender pipeline encodes them
(``bench.encoding.encode_frames``), the packets are decoded, and the receiver's renderer
draws each from the sender's camera (``bench.rendering.render_scores``): face SSIM in the
face box, and the project's tracker on the rendering against the real frame (render NME,
``bench.render_nme``). No x264 reference is made. The frames are spread over the range, so
they are not one stream: the pipeline is reset before each (``independent``), and each is
encoded as the first frame of a stream (a fresh detection, no filter or heuristic state);
the fresh detection the pipeline ran is the real frame's track for the render NME. So the
self-check judges the model at its own frames, not the stream's filters.

    self_check_ssim        mean face SSIM (grey) over the frames rendered
    self_check_render_nme  mean render NME, 68 points, % of the outer-eye distance
    self_check_frames      frames scored (rendered, and the face found on both pictures)

Cost: per frame, two detections (the pipeline's, which is also the real frame's fresh
track, and the rendering's), one face descriptor (the pipeline's tracker takes only the
model's person, ``sender.identity``: 90-250 ms on the shared machine, so a clip with
several people is scored on the model's person) and one rendering; once, the pipeline's
set-up (the tracker's dlib models, the sampler's template grids, about 2 s of it) and the
renderer. On lp_d3 frames 0:300 (three alternating pairs of builds on the shared 2-core
machine, others' jobs running): the build took 15.2, 12.8 and 11.1 s without the
self-check, 20.2, 16.5 and 14.1 s with it; the self-check, decoding included, 6.2, 4.3 and
3.8 s: 34-41 % of the build. ``--no-self-check`` skips it.

Diagnosis (``evidence`` and ``diagnose``). A score is poor when the render NME is over
``POOR_RENDER_NME`` (3 %), the SSIM under ``POOR_SSIM`` (0.65), or the tracker finds no face
on more than ``POOR_FACE_MISSING`` (10 %) of the renderings. Measured on the shared clips
(models from their first 40 %, docs/DESIGN.md §9): the clips' own scores are SSIM
0.70-0.92 and render NME 1.5-3.2 %; two pass 3 %: hamilton_short (3.15 %; its face is lost
in three quarters of its build frames, its head turns fast) and, just, openface_multi_face
(3.02 % on 40 frames, 2.97 % on 60; the front man of three laughs and moves the most of the
clips after hamilton_short); lp_d0's model scored on another person's frames
(lp_d18) gives 4.6 %, and a model whose texture is shifted by an eighth of its width
15-37 %. Render NME is the sharper measure: SSIM on the grey face stays near 0.7 even for
a flat grey texture (whose rendering the tracker does not take for a face at all), so its
threshold only catches the grossest failures. ``model build`` then warns and names the
likely cause, from what the build saw (``Evidence``):

- motion: the head's speed in the fit's poses between posed frames ``MOTION_SPAN_S``
  (0.2 s) apart (90th percentile of the rotation's angular speed, deg/s, and of the
  translation's speed, mm/s), over ``MOTION_DEG_S`` (60) or ``MOTION_MM_S`` (150): on the
  shared clips 6-43 deg/s and 16-93 mm/s but for openface_multi_face (22, 193) and
  hamilton_short (103, 481). Not between
  consecutive frames: the fit's poses are per frame, unfiltered, and their jitter (about a
  degree a frame) alone reads as 30-70 deg/s at 25-30 Hz on still talking heads
  (hdtf_katiehill, lp_d14);
- occlusion: the share of the range's frames without a face or a pose over
  ``LOST_FRACTION`` (20 %; 0 on every shared clip but hamilton_short's 75 %), or the tracked
  points far from the fitted model (the median over posed frames of the mean distance of
  the 68 tracked points from the fitted neutral landmarks posed in that frame, % of the
  outer-eye distance; expression moves them too) over ``LANDMARK_ERROR_PCT`` (6 %; the
  clips: 1.6-4.4 %);
- too few frames: fewer than ``MIN_FACE_FRAMES`` (30: a second at 30 Hz) frames with a face;
- too little pose spread: the posed frames' yaw spans less than ``MIN_YAW_RANGE_DEG`` (5
  deg; lp_d0 and lp_d18 span 2 deg and still score well: alone it rarely explains a poor
  score).

Each cause's measure is divided by its threshold (inverted for the minimums); the causes
past 1 are named, worst first. When none is, the warning says that the build's evidence
names no cause, and which measure came nearest.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.bench.encoding import decode_run, encode_frames
from facewire.bench.render_nme import summary as render_summary
from facewire.bench.rendering import render_scores
from facewire.models.geometry import Intrinsics, Pose, project
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import VideoFrame, read_frames, video_info
from facewire.models.landmarks import outer_eye_distance
from facewire.models.manifest import SelfCheck
from facewire.models.modelfile import PersonModel
from facewire.protocol.packet import Flag
from facewire.protocol.rate import stream_rate
from facewire.sender.pipeline import SenderPipeline, sender_camera, wire_camera
from facewire.sender.tracker import LandmarkTracker

MAX_FRAMES = 40
POOR_SSIM = 0.65
POOR_RENDER_NME = 3.0  # percent of the outer-eye distance
POOR_FACE_MISSING = 0.1  # share of the scored frames whose rendering shows no face
MOTION_DEG_S = 60.0
MOTION_MM_S = 150.0
MOTION_SPAN_S = 0.2  # the head's speed is measured between frames this far apart
LOST_FRACTION = 0.2
LANDMARK_ERROR_PCT = 6.0
MIN_FACE_FRAMES = 30
MIN_YAW_RANGE_DEG = 5.0
CAUSES = ("motion", "occlusion", "too few frames", "too little pose spread")


@dataclass(frozen=True)
class Evidence:
    """What the build saw that can explain a poor self-check (module docstring).

    Attributes:
        frames: frames in the build's range.
        face_frames: frames with a face.
        posed_frames: frames with a pose of the fit.
        speed_deg_s: 90th percentile of the head's angular speed, deg/s, between posed
            frames ``MOTION_SPAN_S`` apart (None: no such pair).
        speed_mm_s: 90th percentile of the head's speed, mm/s (None likewise).
        landmark_error_pct: median over posed frames of the tracked points' mean distance
            from the posed fitted landmarks, % of the outer-eye distance (None: no pose).
        yaw_range_deg: the posed frames' yaw span, degrees.
        photo: the build was from one photo.
    """

    frames: int
    face_frames: int
    posed_frames: int
    speed_deg_s: float | None
    speed_mm_s: float | None
    landmark_error_pct: float | None
    yaw_range_deg: float
    photo: bool = False

    def ratios(self) -> dict[str, float]:
        """Each cause's measure over its threshold (module docstring): past 1, named."""
        lost = 1.0 - self.posed_frames / self.frames if self.frames else 1.0
        motion = max((self.speed_deg_s or 0.0) / MOTION_DEG_S,
                     (self.speed_mm_s or 0.0) / MOTION_MM_S)
        occlusion = max(lost / LOST_FRACTION,
                        (self.landmark_error_pct or 0.0) / LANDMARK_ERROR_PCT)
        few = MIN_FACE_FRAMES / max(self.face_frames, 1)
        spread = MIN_YAW_RANGE_DEG / max(self.yaw_range_deg, 1e-3)
        return {"motion": round(motion, 3), "occlusion": round(occlusion, 3),
                "too few frames": round(few, 3), "too little pose spread": round(spread, 3)}

    def as_dict(self) -> dict[str, Any]:
        return {"frames": self.frames, "face_frames": self.face_frames,
                "posed_frames": self.posed_frames,
                "speed_deg_s": _round(self.speed_deg_s), "speed_mm_s": _round(self.speed_mm_s),
                "landmark_error_pct": _round(self.landmark_error_pct),
                "yaw_range_deg": round(self.yaw_range_deg, 2), "photo": self.photo}


def pick_frames(indices: Sequence[int], count: int = MAX_FRAMES) -> list[int]:
    """At most ``count`` of ``indices``, evenly spread, in order (all when fewer)."""
    if len(indices) <= count:
        return list(indices)
    return [indices[int(round(i))] for i in np.linspace(0, len(indices) - 1, count)]


def read_picked(video: str | os.PathLike[str], picked: Sequence[int]) -> list[VideoFrame]:
    """The frames of ``video`` whose indices are in ``picked`` (one decoding pass)."""
    if not picked:
        return []
    wanted = set(picked)
    return [f for f in read_frames(video, slice(min(picked), max(picked) + 1))
            if f.index in wanted]


def score_frames(model: PersonModel, frames: Sequence[VideoFrame], rate_hz: float,
                 progress: Progress = no_progress) -> dict[str, Any]:
    """Render the model at ``frames`` and score it (module docstring, "Scoring").

    Args:
        model: the person model (in memory: it need not be saved).
        frames: the frames to score, each encoded on its own.
        rate_hz: the video's rate (the stream rate the pipeline announces).
        progress: wraps an iterable to show progress.

    Returns:
        ``self_check_ssim``, ``self_check_render_nme`` (and ``_mouth``, ``_eyes``,
        ``_brows``), ``self_check_frames``, ``self_check_face_missing`` (frames whose
        rendering showed the tracker no face), ``self_check_frames_picked``,
        ``self_check_seconds``; the means are None when no frame was measured.
    """
    start = time.perf_counter()
    out: dict[str, Any] = {"self_check_frames_picked": len(frames)}
    if not frames:
        return {**out, "self_check_ssim": None, "self_check_render_nme": None,
                "self_check_frames": 0, "self_check_face_missing": 0,
                "self_check_seconds": 0.0}
    height, width = frames[0].image.shape[:2]
    pipeline = SenderPipeline(model, sender_camera(width, height), rate_hz=stream_rate(rate_hz),
                              learn=False)  # the model as built, on its own frames
    camera = wire_camera(pipeline.camera)
    run = encode_frames(pipeline, frames, progress, len(frames), independent=True)
    decoded = decode_run(run.packets, run.indices)
    flags = decoded["flags"].astype(np.int64)
    posed = ((flags & Flag.FACE_PRESENT) != 0) & ((flags & Flag.TRACKING_LOST) == 0)
    # the fresh detections take any face (the pipeline's tracker holds the model's person);
    # trackers of a thread share its detector and the predictor, so this one costs nothing
    scores = render_scores(model, camera, decoded, run.tracked, posed, run.images, progress,
                           LandmarkTracker(), truths=run.tracked)
    nme = render_summary("self_check_render", scores.seen)
    ssim = scores.ssim[np.isfinite(scores.ssim)]
    out.update({
        "self_check_ssim": round(float(ssim.mean()), 4) if ssim.size else None,
        "self_check_render_nme": nme["self_check_render_nme_mean"],
        **{f"self_check_render_nme_{part}": nme[f"self_check_render_nme_{part}"]
           for part in ("mouth", "eyes", "brows")},
        "self_check_frames": nme["self_check_render_nme_frames"],
        "self_check_face_missing": scores.seen.missing,
        "self_check_seconds": round(time.perf_counter() - start, 2)})
    return out


def evidence(poses: Sequence[Pose | None], indices: Sequence[int],
             points: Sequence[np.ndarray | None], landmarks3d: np.ndarray,
             camera: Intrinsics, rate_hz: float, yaw_range_deg: tuple[float, float],
             photo: bool = False) -> Evidence:
    """The build's evidence (module docstring, "Diagnosis").

    Args:
        poses: the fit's pose per tracked frame, or None.
        indices: the video frame index of each tracked frame.
        points: the tracker's (68, 2) points per tracked frame, or None.
        landmarks3d: (68, 3) the fitted neutral landmarks, mm.
        camera: the enrollment camera the poses are in.
        rate_hz: the video's frame rate.
        yaw_range_deg: the fit's (min, max) yaw over posed frames.
        photo: one photo (its copies): no motion, no spread to judge.
    """
    if photo:
        return Evidence(1, int(points[0] is not None), int(poses[0] is not None), None, None,
                        _landmark_error(poses[:1], points[:1], landmarks3d, camera), 0.0, True)
    turns, moves = [], []
    step = max(1, round(MOTION_SPAN_S * rate_hz))  # frames apart
    posed = {i: p for i, p in zip(indices, poses) if p is not None}
    for i, a in posed.items():
        b = posed.get(i + step)
        if b is None:
            continue
        dt = step / rate_hz
        relative = b.rotation @ a.rotation.T
        angle = math.degrees(math.acos(float(np.clip((np.trace(relative) - 1) / 2, -1, 1))))
        turns.append(angle / dt)
        moves.append(float(np.linalg.norm(b.translation - a.translation)) / dt)
    return Evidence(
        frames=len(indices), face_frames=sum(p is not None for p in points),
        posed_frames=sum(p is not None for p in poses),
        speed_deg_s=float(np.percentile(turns, 90)) if turns else None,
        speed_mm_s=float(np.percentile(moves, 90)) if moves else None,
        landmark_error_pct=_landmark_error(poses, points, landmarks3d, camera),
        yaw_range_deg=float(yaw_range_deg[1] - yaw_range_deg[0]))


def _landmark_error(poses: Sequence[Pose | None], points: Sequence[np.ndarray | None],
                    landmarks3d: np.ndarray, camera: Intrinsics) -> float | None:
    errors = []
    for pose, seen in zip(poses, points):
        if pose is None or seen is None:
            continue
        drawn = project(landmarks3d, pose, camera)
        errors.append(float(np.linalg.norm(drawn - seen, axis=1).mean()
                            / outer_eye_distance(seen)))
    return float(np.median(errors)) * 100 if errors else None


@dataclass(frozen=True)
class Diagnosis:
    """A self-check's verdict: ``poor``, the causes named (``CAUSES``, worst first) and the
    report's lines (none when not poor)."""

    poor: bool
    causes: tuple[str, ...]
    lines: tuple[str, ...]


def diagnose(scores: dict[str, Any], seen: Evidence) -> Diagnosis:
    """Whether the scores are poor, and the likely cause (module docstring)."""
    ssim, nme = scores["self_check_ssim"], scores["self_check_render_nme"]
    missing = scores.get("self_check_face_missing", 0)
    tried = missing + scores.get("self_check_frames", 0)
    reasons = []
    if tried and missing / tried > POOR_FACE_MISSING:
        reasons.append(f"the tracker found no face on {missing} of {tried} renderings")
    if ssim is None or nme is None:
        reasons.append("no frame could be scored (no rendered face was found)")
    else:
        if ssim < POOR_SSIM:
            reasons.append(f"face SSIM {ssim:.3f} < {POOR_SSIM:g}")
        if nme > POOR_RENDER_NME:
            reasons.append(f"render NME {nme:.2f} % > {POOR_RENDER_NME:g} %")
    if not reasons:
        return Diagnosis(False, (), ())
    ratios = seen.ratios()
    if seen.photo:  # one frame: no motion, no spread, no frame count to blame
        ratios = {"occlusion": ratios["occlusion"]}
    ranked = sorted(ratios, key=lambda c: -ratios[c])
    causes = tuple(c for c in ranked if ratios[c] > 1.0)
    lines = [f"WARNING: the model renders its own enrollment frames poorly ({'; '.join(reasons)})"]
    if causes:
        lines.append("likely cause: " + ", ".join(causes))
        lines += [f"  {c}: {_detail(c, seen)}" for c in causes]
    else:
        nearest = ranked[0]
        lines.append(f"likely cause: none of motion, occlusion, frame count or pose spread is "
                     f"past its threshold; nearest: {nearest}")
        lines.append(f"  {nearest}: {_detail(nearest, seen)}")
        causes = (nearest,)
    return Diagnosis(True, causes, tuple(lines))


def _detail(cause: str, e: Evidence) -> str:
    if cause == "motion":
        return (f"the head turns at {_fmt(e.speed_deg_s)} deg/s (threshold "
                f"{MOTION_DEG_S:g}) and moves at {_fmt(e.speed_mm_s)} mm/s (threshold "
                f"{MOTION_MM_S:g}), 90th percentiles")
    if cause == "occlusion":
        lost = e.frames - e.posed_frames
        return (f"{lost} of {e.frames} frames without a face or pose (threshold "
                f"{LOST_FRACTION * 100:g} %); tracked points {_fmt(e.landmark_error_pct)} % of "
                f"the eye distance from the fitted model (threshold {LANDMARK_ERROR_PCT:g} %)")
    if cause == "too few frames":
        return f"{e.face_frames} frames with a face, fewer than {MIN_FACE_FRAMES}"
    return f"yaw spans {e.yaw_range_deg:.1f} deg, less than {MIN_YAW_RANGE_DEG:g}"


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f}"


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 3)


def stored(scores: dict[str, Any], verdict: Diagnosis) -> SelfCheck:
    """The model's ``self_check`` record of a self-check."""
    return SelfCheck(ssim=scores["self_check_ssim"], render_nme=scores["self_check_render_nme"],
                     frames=scores["self_check_frames"], poor=verdict.poor,
                     causes=verdict.causes)


def video_check(video: str | os.PathLike[str], progress: Progress = no_progress
                ) -> Callable[..., tuple[SelfCheck, dict[str, Any]]]:
    """The self-check of a build from ``video``, as ``sender.enroll.build``'s ``check`` hook:
    ``check(model, fit, indices, points)`` -> the model's record and the report's keys."""
    rate = video_info(video).rate_hz

    def check(model: PersonModel, fit: Any, indices: Sequence[int],
              points: Sequence[np.ndarray | None]) -> tuple[SelfCheck, dict[str, Any]]:
        start = time.perf_counter()
        faces = [i for i, p in zip(indices, points) if p is not None]
        scores = score_frames(model, read_picked(video, pick_frames(faces)), rate, progress)
        seen = evidence(fit.poses, indices, points, fit.landmarks3d, model.camera, rate,
                        fit.yaw_range_deg)
        scores["self_check_seconds"] = round(time.perf_counter() - start, 2)  # with decoding
        return _report(scores, seen)
    return check


def photo_check(photo: str | os.PathLike[str], progress: Progress = no_progress
                ) -> Callable[..., tuple[SelfCheck, dict[str, Any]]]:
    """The self-check of a build from one photo: the photo itself, one frame."""
    def check(model: PersonModel, fit: Any, indices: Sequence[int],
              points: Sequence[np.ndarray | None]) -> tuple[SelfCheck, dict[str, Any]]:
        image = cv2.imread(str(Path(photo)), cv2.IMREAD_COLOR)
        scores = score_frames(model, [VideoFrame(0, 0.0, np.asarray(image))], 30.0, progress)
        seen = evidence(fit.poses, indices, points, fit.landmarks3d, model.camera, 30.0,
                        fit.yaw_range_deg, photo=True)
        return _report(scores, seen)
    return check


def _report(scores: dict[str, Any], seen: Evidence) -> tuple[SelfCheck, dict[str, Any]]:
    verdict = diagnose(scores, seen)
    return stored(scores, verdict), {
        **scores, "self_check_poor": verdict.poor, "self_check_causes": list(verdict.causes),
        "self_check_lines": list(verdict.lines), "self_check_evidence": seen.as_dict(),
        "self_check_cause_ratios": seen.ratios()}
