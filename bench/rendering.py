"""The receiver's side of a measured run: each frame rendered and scored against the real one.

``render_scores`` draws every measured frame (a pose of its own and tracked points) with the
receiver's renderer (``receiver.render.FaceRenderer``) from the sender's camera
(``receiver.views.sender_view``) with the decoded pose, residuals, Q and light, and scores it
against the real frame inside the face box and its mask (``bench.fidelity``): grayscale SSIM
and PSNR, and the render NME of the project's tracker run afresh on both pictures
(``bench.render_nme``; ``FreshTracker`` times it). Each frame is drawn with the model version
its packet's ``serial`` names (``versions``, from a sender that learned during the session:
``bench.encoding``), as a receiver holding the session's model updates draws it.
``bench.quality``'s docstring states the measures ("Appearance fidelity", "What the viewer
sees"); ``bench quality`` and the build's self-check (``bench.selfcheck``) both score
through it.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import NamedTuple

import cv2
import numpy as np

from facewire.bench.fidelity import face_box, face_mask, gray_ssim, psnr
from facewire.bench.render_nme import PARTS, FaceCounts, picture_nme, track_fresh
from facewire.models.infra.progress import Progress
from facewire.models.modelfile import PersonModel
from facewire.models.rig import Rig
from facewire.protocol.control import Camera
from facewire.receiver.render import FaceRenderer
from facewire.receiver.views import sender_view
from facewire.sender.tracker import LandmarkTracker


class RenderScores(NamedTuple):
    """Our rendering of each measured frame against the real frame (``render_scores``).

    Attributes:
        ssim, psnr: (F,) face SSIM and PSNR (dB); NaN where not measured.
        seen: ``FaceCounts``: (F, len(PARTS)) render NME fractions and the frames whose
            rendering showed the tracker no face.
        real_points: frame position -> (68, 2) the real frame's fresh track.
        render_points: frame position -> (68, 2) the fresh track of our rendering of it.
        real_missing: measured frames whose real frame showed the fresh tracker no face.
        boxes, masks: frame position -> the face box and its mask (``bench.fidelity``).
        faces: frame position -> our rendering cropped to the face box (``keep_faces``).
        tracking_s: seconds spent in the fresh tracking.
    """

    ssim: np.ndarray
    psnr: np.ndarray
    seen: FaceCounts
    real_points: dict[int, np.ndarray]
    render_points: dict[int, np.ndarray]
    real_missing: int
    boxes: dict[int, tuple[int, int, int, int]]
    masks: dict[int, np.ndarray]
    faces: dict[int, np.ndarray]
    tracking_s: float


def render_scores(model: PersonModel, camera: Camera, decoded: np.ndarray,
                  tracked: list[np.ndarray | None], posed: np.ndarray,
                  images: list[np.ndarray], progress: Progress, tracker: LandmarkTracker,
                  keep_faces: bool = False,
                  truths: list[np.ndarray | None] | None = None,
                  versions: Mapping[int, PersonModel] | None = None) -> RenderScores:
    """Render every measured frame (a pose of its own and tracked points) with the
    receiver's renderer from the sender's camera and score it against the real frame: face
    SSIM and PSNR in the face box, and the fresh tracker's points on both (``bench.quality``'s
    docstring, "Appearance fidelity" and "What the viewer sees").

    Args:
        model: the person model the packets were made with.
        camera: the sender's camera as the Hello carries it.
        decoded: (F,) ``FRAME_DTYPE`` decoded packets.
        tracked: F sender tracker results, (68, 2) pixels or None.
        posed: (F,) bool, frames with a pose of their own.
        images: F real frames, (H, W, 3) uint8 BGR.
        progress: wraps an iterable to show progress.
        tracker: the tracker for the fresh detections (``bench.render_nme.track_fresh``).
        keep_faces: keep each rendering's face crop (``RenderScores.faces``).
        truths: the real frames' fresh tracks when already made (a pipeline reset before
            every frame detects afresh: ``encode_frames(independent=True)``); else tracked
            here.
        versions: {serial: model version} for the serials the packets name (``Run.versions``;
            the same mesh as ``model``); each frame is drawn with its serial's version.
            None: every frame with ``model``.
    """
    rig = Rig(model.mesh)
    ssim = np.full(len(decoded), np.nan)
    peak = np.full(len(decoded), np.nan)
    boxes: dict[int, tuple[int, int, int, int]] = {}
    masks: dict[int, np.ndarray] = {}
    rendered_faces: dict[int, np.ndarray] = {}
    seen = np.full((len(decoded), len(PARTS)), np.nan)  # render NME per frame and part
    real_points: dict[int, np.ndarray] = {}  # the real frames' fresh tracks
    render_points: dict[int, np.ndarray] = {}  # our renderings' fresh tracks
    missing = {"real": 0, "render": 0}
    fresh = FreshTracker(tracker)
    shown = model
    renderer = FaceRenderer(model, camera.width, camera.height)
    try:
        for k, image in enumerate(progress(images, "rendering", len(images))):
            points = tracked[k]
            if not posed[k] or points is None:
                continue
            record = decoded[k]
            version = model if versions is None else versions[int(record["serial"])]
            if version is not shown:
                renderer.release()
                renderer, shown = FaceRenderer(version, camera.width, camera.height), version
            vertices = rig.morph(rig.from_tangent(record["residuals"]))
            view = sender_view(camera, record["rotation"], record["translation"],
                               camera.width, camera.height)
            rendered = renderer.render(vertices, record["q"], view, record["shade"])[..., ::-1]
            boxes[k] = x0, y0, x1, y1 = face_box(points, camera.width, camera.height)
            masks[k] = mask = face_mask(points, boxes[k])
            real, ours = image[y0:y1, x0:x1], rendered[y0:y1, x0:x1]
            ssim[k] = gray_ssim(real, ours, mask)
            peak[k] = psnr(grey(real)[mask], grey(ours)[mask])
            if keep_faces:
                rendered_faces[k] = ours.copy()
            truth = fresh(image) if truths is None else truths[k]
            if truth is None:
                missing["real"] += 1
                continue
            real_points[k] = truth
            drawn = fresh(rendered)
            if drawn is None:
                missing["render"] += 1
            else:
                render_points[k] = drawn
                seen[k] = picture_nme(truth, drawn)
    finally:
        renderer.release()
    return RenderScores(ssim, peak, FaceCounts(seen, missing["render"]), real_points,
                        render_points, missing["real"], boxes, masks, rendered_faces, fresh.seconds)


class FreshTracker:
    """``track_fresh`` with the tracker given, timed: ``seconds`` spent in it so far."""

    def __init__(self, tracker: LandmarkTracker) -> None:
        self.tracker = tracker
        self.seconds = 0.0

    def __call__(self, image: np.ndarray) -> np.ndarray | None:
        start = time.perf_counter()
        points = track_fresh(self.tracker, image)
        self.seconds += time.perf_counter() - start
        return points


def grey(image: np.ndarray) -> np.ndarray:
    """The BGR image in grey levels."""
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
