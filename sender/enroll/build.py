"""Enrollment: build a person's model (``.fwm``) from a short video of that person.

The steps, in order (``build_model``):

1. Track: the person is chosen among the faces of the range (``sender.enroll.person``:
   the one most present, or ``person``: an index in the first frame or a reference photo),
   then their 68 points are tracked in every frame of the range (``sender.tracker`` given
   the person: nobody else's face is taken); frames without their face are kept as
   ``None``. Their descriptors (``sender.identity``) at up to ``STORED_DESCRIPTORS`` face
   frames spread over the range go into the model (``PersonModel.descriptors``), so that
   the appearance step, the self-check and every sender follow that person only.
2. Fit: choose the neutral frame, among the sharp frames (``sender.enroll.registration``:
   a motion-blurred neutral frame doubles every edge of the texture and rest layers; of a
   guided recording, among the neutral prompt's sharp frames: ``sender.enroll.routine``),
   estimate the head pose in every frame and the person's 3D landmarks, and warp the
   generic head onto them (``sender.enroll.fit``). The camera is unknown, so its
   intrinsics are a guess (``models.geometry.intrinsics_guess``).
3. Texture: score the frames and choose up to nine clean views, spread in time, the neutral
   frame first (``sender.enroll.evidence``: the landmarks' fit against the fitted model,
   blur, pose and expression; frames whose landmarks do not line up are not candidates),
   decode them again, project them onto the fitted mesh's UV layout within the person's
   silhouette in each (``sender.enroll.silhouette``: not the room behind), register them onto
   their consensus (``sender.enroll.align``) and fuse them robustly
   per texel (``sender.enroll.fusion.fuse_views``: a weighted median's consensus, views
   departing from it or not lining up with it locally take no part there, misaligned
   views none at all) at
   ``TEXTURE_SIZE``, and fill every texel no view saw, so no black gap or seam shows from any
   angle. When the neutral frame was an outlier over a part of the face (occluded there),
   the fit is run again with the neutral frame taken among the clean views, and the views
   are fused again on its mesh. ``BuildResult.evidence`` says which views were used, which
   were dropped, where each was occluded and, per part, how much of the texture shows a
   feature twice (``sender.enroll.registration``). A photo has one view.
4. Appearance (``sender.enroll.layers.enroll_regions``, unless ``appearance=False``): the
   texture regions' layers and classification templates, from the same frames. It runs the
   sender's own pipeline (pose, lift, filters) and sampler on the video, so that the
   templates are what the sender will sample at run time; a frame whose mouth or an eye is
   occluded (``sender.enroll.evidence``, 4) gives that region no layer, and the model
   records per region the frames used and rejected, and why (``PersonModel.region_frames``,
   ``sender.enroll.usage``). With them, the coverage
   (``sender.enroll.coverage``): which expression states (eyes closed, gaze, brows, mouth
   open or wide, teeth) the layers' frames show; the model stores it
   (``PersonModel.coverage``) and ``model build`` says what the rendering does for each
   state it lacks. A model without regions covers none: only the neutral. With
   the layers, the mouth cavity's texture becomes its interior (``sender.enroll.interior``:
   the person's own where an open-mouth frame saw it, else a dark made-up one with teeth),
   never the lips or skin that the base texture's hole filling put there.
5. Save the model (``models.modelfile``), with the frames it was built from (the
   video's name, size and sha256, and the range [first, last + 1) of the frames tracked:
   ``info.source``, which ``bench quality`` checks; of a guided recording, the frames of
   the video file it recorded, or none for a camera: ``Guide.origin_range``), and a
   preview PNG beside it: the model
   rendered from the front and from three-quarter view, beside the neutral frame cropped to
   the face, so a user can see at a glance whether the model is that person; below, one row
   per region with, under its name, the frames its layers used and those rejected per
   reason (and a bar of the same in proportion), then its layers in order (as drawn over
   the neutral texture: layer times its opacity and alpha ramp); last, the coverage
   (``sender.enroll.coverage``): which expression states the layers show, and which they
   do not. When the clip showed more than one person, a last row shows a frame of the clip
   with every face boxed, the person's in green, the others numbered as ``--person N``
   counts them in the first frame.

One photo (``build_photo``; ``build_model`` sends a path with a ``PHOTO_SUFFIXES`` suffix
there). The photo is the clip: ``STILL_FRAMES`` copies of it, frames 0 .. 9, go through
steps 1-3 and 5 (the fit needs 10 face frames). Each copy takes the points the tracker
detects on the first: its follower, fed the same image again, moved points by up to 27 px
on the demo's portrait, so the copies would disagree and the fit would take whichever
looked most neutral. One view gives the generic head's depth, and the generic head is
wider than most faces: its sides, seen at grazing angles near the face's outline, project
onto the ear, hair or background beside the cheek, a few pixels stretched over a wide band
of texels, which a head turned by 20 degrees shows as a pale smear on the cheek where a
tracker takes it for the jaw line. So the photo's texture keeps only the texels inside the
jaw contour or above it, a margin in from its edge (``photo_face_texels``: dlib's contour
runs over the ear and the hair beside the jaw), and fills the rest from the nearest face
texels as it fills unseen ones (``fill_holes``). Step 4 is
skipped: one expression gives no states to choose, so the model has no regions, only the
neutral; a receiver draws the neutral texture on the morphed mesh whatever the packet's Q
(its mouth cavity keeps the base texture's filling: giving it the made-up interior moved
the demo's received yaw off the script, r 0.83 against 0.85, for a reason not found).
The demo's performer (``facewire.performer``) builds its portrait's model this way.

The self-check (``check``, a hook: ``sender.enroll`` may not render with the receiver or
score with the benchmarks, so ``facewire model build`` passes ``bench.selfcheck``'s). After
step 4 and before step 5, ``check(model, fit, indices, points)`` gets the finished model,
the fit, the frame indices tracked and their points; it returns the model's ``SelfCheck``
record (saved with the model) and the report's keys (``BuildResult.self_check``).

Failures a user can cause (an unreadable video or photo, no face, too few face frames)
raise ``BuildError`` naming the file.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.models.draworder import region_areas, triangle_groups
from facewire.models.framing import (
    FIELD_EYE_DISTANCES,
    FIELD_RAISE,
    FOV_DEG,
    THREE_QUARTER_YAW_DEG,
    framing_pose,
    head_field,
)
from facewire.models.geometry import Intrinsics, intrinsics_guess
from facewire.models.head import generic_head
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.raster import Camera as ViewCamera
from facewire.models.infra.raster import MeshRenderer
from facewire.models.infra.video import (
    VideoFrame,
    decoded_once,
    frames_in_range,
    range_text,
    read_frames,
    video_info,
)
from facewire.models.landmarks import outer_eye_distance
from facewire.models.manifest import ModelInfo, RegionFrames, SelfCheck, SourceRange
from facewire.models.mesh import Mesh
from facewire.models.modelfile import Area, PersonModel, Region, model_summary, save_model
from facewire.models.texelgrid import texel_rect
from facewire.protocol.errors import FacewireError
from facewire.sender.clean import sharpness
from facewire.sender.enroll.confidence import texture_confidence
from facewire.sender.enroll.coverage import MEASURES, Coverage, measure_coverage
from facewire.sender.enroll.evidence import (
    clean_views,
    frame_scores,
    occluded_parts,
    part_masks,
    texture_views,
)
from facewire.sender.enroll.fit import Fit, FitError, fit_person
from facewire.sender.enroll.fusion import Fusion, fuse_views
from facewire.sender.enroll.layers import enroll_regions
from facewire.sender.enroll.occluders import OccluderScan, Occlusion
from facewire.sender.enroll.person import (
    Chosen,
    choose_person,
    photo_descriptor,
    sample_faces,
    sample_indices,
)
from facewire.sender.enroll.registration import sharp_frames
from facewire.sender.enroll.routine import Guide
from facewire.sender.enroll.silhouette import SilhouetteFinder
from facewire.sender.enroll.texture import UVSurface, fill_holes, uv_surface
from facewire.sender.enroll.usage import LABELS as USAGE_LABELS
from facewire.sender.enroll.usage import ordered as usage_order
from facewire.sender.enroll.usage import region_frames_summary
from facewire.sender.identity import MATCH_DISTANCE, Person, face_descriptor
from facewire.sender.tracker import LandmarkTracker

TEXTURE_SIZE = (1024, 2048)  # rows, columns: twice the paper's 512 x 1024
PREVIEW_HEIGHT = 480
PHOTO_FACE_MARGIN = 0.04  # a photo's texture: texels this far (of the face's width) inside
PREVIEW_YAWS = (0.0, THREE_QUARTER_YAW_DEG)  # degrees: front and three-quarter
PREVIEW_BACKGROUND = (40, 40, 40)
PREVIEW_SAMPLES = 4  # multisampling of the preview's renders
CREATOR = "facewire 0.1.0"
REGION_ROW_HEIGHT = 96  # preview rows of region layers, px
REGION_LABEL_WIDTH = 190
# the preview's bar of how a region spent the frames (sender.enroll.usage), BGR per kind
USAGE_COLOURS = {"used": (110, 230, 110), "clean": (70, 110, 70), "no_face": (110, 110, 110),
                 "occluded": (70, 70, 235), "lid_closed": (230, 160, 80),
                 "no_cue": (170, 170, 170)}
COVERAGE_ROW_HEIGHT = 60  # the preview's last row: the states covered and not seen
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".webp")  # what ``model build`` takes as a photo
STILL_FRAMES = 10  # a photo is fitted as this many copies: sender.enroll.fit needs 10 face frames
STILL_RATE_HZ = 30.0
STORED_DESCRIPTORS = 8  # the person's descriptors a model stores (sender.identity)
PERSON_ROW_HEIGHT = 240  # the preview's row showing whom the model is of

SelfCheckHook = Callable[[PersonModel, Fit, Sequence[int], Sequence[np.ndarray | None]],
                         tuple[SelfCheck, dict[str, Any]]]


class BuildError(FacewireError, ValueError):
    """The video or photo cannot give a model; the message names the file and says why."""


@dataclass(frozen=True)
class BuildResult:
    """What ``build_model`` made and measured.

    Attributes:
        model: the saved model (with its sha256 and file size).
        path: the ``.fwm`` file.
        preview: the preview PNG beside it.
        fit: the geometry fit (poses, neutral frame, depth mode).
        frames: video frame indices tracked, in order.
        face_frames: how many of them had a face.
        seconds: wall time of the whole build.
        appearance: the appearance step's report per region ({} when it was not run).
        coverage: the states the layers show (``sender.enroll.coverage``; none without
            regions).
        self_check: the self-check hook's report keys ({} when it was not run).
        person: whom the model is of (``sender.enroll.person.Chosen``); None when no
            sampled frame showed a face (the largest face tracked was taken).
        evidence: the base texture's views (video indices, the neutral first), those
            dropped as misaligned, per part of the face those that were occluded there, and
            the first neutral frame when it was occluded and taken again
            (``sender.enroll.evidence``), and per part the doubled-feature measure of the
            texture (``sender.enroll.registration``, 3).
        occluders: the frames a hand covered (video indices) and per part of the face how
            many frames covered it (``sender.enroll.occluders``); None for a photo's build.
    """

    model: PersonModel
    path: Path
    preview: Path
    fit: Fit
    frames: tuple[int, ...]
    face_frames: int
    seconds: float
    appearance: dict[str, Any]
    coverage: Coverage
    self_check: dict[str, Any]
    person: Chosen | None
    evidence: dict[str, Any] | None = None
    occluders: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        """The ``--json`` object: the model keys of docs/DESIGN.md §7, then how the build went."""
        return {**model_summary(self.model), "path": str(self.path),
                "preview": str(self.preview), "frames": len(self.frames),
                "face_frames": self.face_frames,
                "neutral_frame": self.model.info.neutral_frame, "depth": self.fit.depth,
                "depth_change_mm": round(self.fit.depth_change_mm, 3),
                "texture_views": list(self.model.info.frames_used),
                "source": None if self.model.info.source is None
                else self.model.info.source.as_dict(),
                "texture_evidence": self.evidence,
                "occluded_enrollment_frames": len((self.occluders or {}).get("frames", ())),
                "occluders": self.occluders,
                "person": None if self.person is None else self.person.summary(),
                "appearance": self.appearance,
                "region_frames": region_frames_summary(self.model),
                **self.coverage.summary(),
                **self.self_check, "seconds": round(self.seconds, 2)}


def preview_path(model_path: str | os.PathLike[str]) -> Path:
    """Where the preview of ``MODEL.fwm`` goes: ``MODEL.preview.png`` beside it."""
    path = Path(model_path)
    return path.with_name(path.stem + ".preview.png")


def is_photo(path: str | os.PathLike[str]) -> bool:
    """Whether ``model build`` takes ``path`` as a photo (``PHOTO_SUFFIXES``, any case)."""
    return Path(path).suffix.lower() in PHOTO_SUFFIXES


def build_model(video: str | os.PathLike[str], out: str | os.PathLike[str],
                frames: slice = slice(0, None), name: str | None = None,
                progress: Progress = no_progress,
                appearance: bool = True, check: SelfCheckHook | None = None,
                guide: Guide | None = None,
                person: int | str | os.PathLike[str] | None = None) -> BuildResult:
    """Build a person's model from a video, or from one photo, and save it with its preview.

    Args:
        video: the enrollment video: the person (the one most present, unless ``person``
            says whom), some seconds of neutral face and expressions, ideally some head
            turns (for depth and side texture).
            A photo (``is_photo``) goes to ``build_photo``.
        out: the ``.fwm`` file to write; the preview goes to ``preview_path(out)``.
        frames: the frame range to use (``models.infra.video.frame_range``); a photo takes
            only the whole range.
        name: the person's name; the video's file name without extension by default.
        progress: wraps an iterable to show progress: ``progress(items, label, total)``.
        appearance: run the appearance step (module docstring, 4); False builds geometry and
            the neutral texture only, a model without regions.
        check: the self-check hook (module docstring), or None: no self-check.
        guide: a guided recording's prompted frames (``sender.enroll.routine``, frame
            indices of ``video``): the neutral frame is chosen among the neutral prompt's
            frames, each region's states among its prompts' frames.
        person: whom to build the model of, among several people (``--person``): an index
            of the faces in the range's first frame, left to right, or a reference photo's
            path; None: the one most present (``sender.enroll.person``).

    Raises:
        BuildError: no readable frames, no face, or too few face frames (names the video).
        PersonError: the person asked for is not found (names the input).
        EnrollError: the appearance step found fewer than 2 frames with a head pose.
        VideoError: the video cannot be opened or decoded.
    """
    video = Path(video)
    if is_photo(video):
        if frames != slice(0, None):
            raise BuildError(f"{video}: a photo has one frame; --frames is for videos")
        return build_photo(video, out, name, progress, check, person)
    info = video_info(video)
    with decoded_once(video):  # tracking, texture, appearance and self-check share frames
        return _build(video.name, lambda s: read_frames(video, s), info.width, info.height,
                      frames_in_range(frames, info.frames), out, frames, name or video.stem,
                      progress, video if appearance else None, str(video), video,
                      check=check, guide=guide, person=person)


def build_photo(photo: str | os.PathLike[str] | np.ndarray, out: str | os.PathLike[str],
                name: str | None = None, progress: Progress = no_progress,
                check: SelfCheckHook | None = None,
                person: int | str | os.PathLike[str] | None = None) -> BuildResult:
    """Build a model from one photo: the neutral only (module docstring, "One photo").

    Args:
        photo: an image file OpenCV reads (``PHOTO_SUFFIXES``), or an (H, W, 3) uint8 BGR
            image (the demo's portrait).
        out: the ``.fwm`` file to write; the preview goes beside it.
        name: the person's name; the file name without extension (or "portrait") by default.
        progress: wraps an iterable to show progress.
        check: the self-check hook (module docstring), or None.
        person: as ``build_model``'s (the photo's largest face by default).

    Raises:
        BuildError: the file is not a readable image, or no face or no usable fit in it (the
            message names the file).
    """
    if isinstance(photo, np.ndarray):
        image, where, source = photo, "the photo", ""
        name = name or "portrait"
    else:
        path = Path(photo)
        if not path.is_file():
            raise BuildError(f"{path}: no such photo")
        read = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if read is None:
            raise BuildError(f"{path}: not an image OpenCV can read")
        image = np.asarray(read)
        where, source = str(path), path.name
        name = name or path.stem
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8 or min(
            image.shape[:2]) < 16:
        raise BuildError(f"{where}: expected a colour image of at least 16 x 16 pixels, got "
                         f"shape {image.shape}")
    still = [VideoFrame(k, k / STILL_RATE_HZ, image) for k in range(STILL_FRAMES)]

    def copies(frames: slice) -> Iterator[VideoFrame]:
        return iter(still[frames])

    return _build(source, copies, image.shape[1], image.shape[0], STILL_FRAMES, out,
                  slice(0, None), name, progress, None, where,
                  None if isinstance(photo, np.ndarray) else Path(photo), photo=True,
                  check=check, person=person)


def _build(source: str, read: Callable[[slice], Iterable[VideoFrame]], width: int,
           height: int, total: int | None, out: str | os.PathLike[str], frames: slice,
           name: str, progress: Progress, video: Path | None, where: str,
           source_file: Path | None, photo: bool = False,
           check: SelfCheckHook | None = None, guide: Guide | None = None,
           person: int | str | os.PathLike[str] | None = None) -> BuildResult:
    """The build (module docstring, steps 1-5) from a frame source: ``read(frames)`` yields
    the frames of a range; ``video`` is the file the appearance step reads (None: no
    appearance step); ``where`` names the input in errors; ``source_file`` is the file the
    model says it was built from (``info.source``; None for an image given in memory);
    ``guide`` the prompted frames of a guided recording; ``person`` as ``build_model``'s."""
    start = time.perf_counter()
    tracker = LandmarkTracker()
    who = _choose(read, frames, total, tracker, where, photo, person)
    tracker = LandmarkTracker(person=None if who is None else Person(who.descriptors))
    indices, points, blur, face_frames, occlusions = _track(read, frames, total, progress,
                                                            where, photo, tracker)
    camera = intrinsics_guess(width, height)
    sharp = sharp_frames(blur, [p is not None for p in points])
    if guide is not None:
        calm = [k for k, i in enumerate(indices) if i in guide.neutral]
        sharp = [k for k in calm if k in sharp] or calm
    unoccluded = [k for k in sharp if not occlusions[k].occluded]
    fit = _fit(points, camera, where, unoccluded or sharp)
    fit, chosen, images, texture, evidence, confidence = _base_texture(
        read, indices, points, blur, fit, camera, where, photo,
        {k for k, o in enumerate(occlusions) if o.occluded})
    occluders = _occluders_report(indices, occlusions)

    used, neutral = tuple(sorted(indices[k] for k in chosen)), indices[fit.neutral]
    if photo:  # the copies are one frame: frame 0
        used, neutral, indices, face_frames = (0,), 0, [0], 1
    made_from = None if source_file is None else SourceRange.of_file(
        source_file, indices[0], indices[-1] + 1)
    if guide is not None:  # the recording is temporary: name what was recorded
        source, made_from = guide.origin, guide.origin_range
    model = PersonModel(
        mesh=fit.mesh, texture=texture, confidence=confidence,
        camera=camera, descriptors=who.descriptors if photo and who is not None  # one image
        else _descriptors(read, indices, points, who),
        info=ModelInfo(name=name, source_video=source, frames_used=used,
                       neutral_frame=neutral, creator=CREATOR, source=made_from))
    report: dict[str, Any] = {}
    coverage = measure_coverage({}, np.zeros(len(MEASURES)))
    if video is not None:
        covered = {indices[k]: o.parts for k, o in enumerate(occlusions) if o.parts}
        regions, report, coverage, usage, texture = enroll_regions(model, video, frames,
                                                                   progress, guide, covered)
        model = at_rest(replace(model, texture=texture, regions=regions,
                                region_frames=usage))
    model = replace(model, coverage=coverage.states)
    checked: dict[str, Any] = {}
    if check is not None:
        record, checked = check(model, fit, indices, points)
        model = replace(model, self_check=record)
    out = Path(out)
    model = replace(model, sha256=save_model(model, out), file_bytes=out.stat().st_size)
    preview = preview_path(out)
    neutral_image = images[min(images)] if photo else images[indices[fit.neutral]]
    _write_png(preview, render_preview(model, neutral_image, points[fit.neutral],
                                       _person_view(read, who)))
    return BuildResult(model, out, preview, fit, tuple(indices), face_frames,
                       time.perf_counter() - start, report, coverage, checked, who,
                       evidence, occluders)


def _choose(read: Callable[[slice], Iterable[VideoFrame]], frames: slice, total: int | None,
            tracker: LandmarkTracker, where: str, photo: bool,
            person: int | str | os.PathLike[str] | None) -> Chosen | None:
    """Step 1's choice of the person (``sender.enroll.person``) among the faces of
    ``SAMPLES`` frames spread over the range (a photo: its one image); None when no sampled
    frame shows a face and no ``person`` was asked for (the tracking then takes the largest
    face of any frame, or says there is none)."""
    first = frames.start or 0
    count = 1 if photo or not total else total  # frames of unknown count: the first only
    wanted = sample_indices(list(range(first, first + count)))
    sampled = sample_faces(read(slice(first, wanted[-1] + 1)), wanted, tracker)
    if not sampled:
        raise BuildError(f"{where}: no frames in range {range_text(frames)}")
    if person is None and not any(sampled):
        return None
    reference: int | np.ndarray | None = None
    name = ""
    if isinstance(person, int):
        reference = person
    elif person is not None:
        name = os.fspath(person)
        reference = photo_descriptor(person, tracker)
    return choose_person(sampled, reference, where, name)


def _descriptors(read: Callable[[slice], Iterable[VideoFrame]], indices: list[int],
                 points: list[np.ndarray | None], chosen: Chosen | None) -> np.ndarray:
    """(D, 128) float32: the person's descriptors at up to ``STORED_DESCRIPTORS`` tracked
    face frames spread over the range (those within ``MATCH_DISTANCE`` of the chosen faces'
    mean, all without a choice), or the chosen faces' own when none is."""
    faces = [k for k, p in enumerate(points) if p is not None]
    picks = sorted({faces[int(round(i))] for i in np.linspace(
        0, len(faces) - 1, min(STORED_DESCRIPTORS, len(faces)))})
    images = _decode(read, {indices[k] for k in picks})
    seed = None if chosen is None else Person(chosen.descriptors)
    found = []
    for k in picks:
        p = points[k]
        assert p is not None
        d = face_descriptor(images[indices[k]], p)
        if seed is None or seed.distance_of(d) < MATCH_DISTANCE:
            found.append(d)
    if not found:
        assert chosen is not None
        return chosen.descriptors[:STORED_DESCRIPTORS]
    return np.stack(found)


def _person_view(read: Callable[[slice], Iterable[VideoFrame]], chosen: Chosen | None
                 ) -> tuple[np.ndarray, int, Chosen] | None:
    """The frame the preview's person row shows (module docstring, 5), its index and the
    choice, or None when the clip showed one person: of the sampled frames that show the
    person, the one with the most faces (the earliest of those)."""
    if chosen is None or chosen.people < 2:
        return None
    counts: dict[int, int] = {}
    for face, _ in chosen.faces:
        counts[face.frame] = counts.get(face.frame, 0) + 1
    frame = min({f.frame for f, mine in chosen.faces if mine},
                key=lambda i: (-counts[i], i))
    return _decode(read, {frame})[frame], frame, chosen


def _track(read: Callable[[slice], Iterable[VideoFrame]], frames: slice, total: int | None,
           progress: Progress, where: str, photo: bool, tracker: LandmarkTracker
           ) -> tuple[list[int], list[np.ndarray | None], list[float], int, list[Occlusion]]:
    """Step 1: each frame's index, the person's 68 points (None: no face), sharpness and
    occluders (``sender.enroll.occluders``; none looked for in a photo's copies), and how
    many frames show their face; ``BuildError`` when none do."""
    scan = None if photo else OccluderScan()
    indices: list[int] = []
    points: list[np.ndarray | None] = []
    blur: list[float] = []
    for frame in progress(read(frames), "tracking", total):
        indices.append(frame.index)
        if photo and points:  # the same image: the detection's points, not the follower's
            points.append(points[0])
            blur.append(blur[0])
            continue
        found = tracker.track(frame.image).points
        points.append(found)
        blur.append(0.0 if found is None else sharpness(frame.image, found))
        if scan is not None:
            scan.see(frame.image, found)
    occlusions = [Occlusion()] * len(indices) if scan is None else scan.verdicts()
    if not indices:
        raise BuildError(f"{where}: no frames in range {range_text(frames)}")
    face_frames = sum(p is not None for p in points)
    if face_frames == 0:
        raise BuildError(f"{where}: no face found in the photo" if photo else
                         f"{where}: no face found in frames {indices[0]}..{indices[-1]}")
    return indices, points, blur, face_frames, occlusions


def _occluders_report(indices: list[int], occlusions: list[Occlusion]) -> dict[str, Any]:
    """What the build reports of the occluders found (``sender.enroll.occluders``): the
    occluded frames (video indices) and per part of the face how many frames covered it."""
    parts: dict[str, int] = {}
    for o in occlusions:
        for part in o.parts:
            parts[part] = parts.get(part, 0) + 1
    return {"frames": [i for i, o in zip(indices, occlusions) if o.occluded],
            "parts": dict(sorted(parts.items()))}


def _fit(points: list[np.ndarray | None], camera: Intrinsics, where: str,
         neutral_among: list[int] | None = None) -> Fit:
    """Step 2: ``fit_person`` on the generic head, its ``FitError`` a ``BuildError``."""
    try:
        return fit_person(points, camera, head=generic_head(), neutral_among=neutral_among)
    except FitError as exc:
        raise BuildError(f"{where}: {exc}") from None


def _base_texture(read: Callable[[slice], Iterable[VideoFrame]], indices: list[int],
                  points: list[np.ndarray | None], blur: list[float], fit: Fit,
                  camera: Intrinsics, where: str, photo: bool, handed: set[int]
                  ) -> tuple[Fit, tuple[int, ...], dict[int, np.ndarray], np.ndarray,
                             dict[str, Any], np.ndarray]:
    """Step 3: the fit (fitted again when the neutral frame was occluded), the views fused
    (positions in ``indices``; none of the ``handed`` ones, a hand on the face, while
    others are candidates),
    the decoded images by frame index, the filled base texture, the evidence the build
    reports and the texture's confidence map (``sender.enroll.confidence``)."""
    surface = uv_surface(fit.mesh, TEXTURE_SIZE)
    scores = frame_scores(points, fit, camera, blur)
    scores = {f: c for f, c in scores.items() if f not in handed} or scores
    chosen, primary = ((fit.neutral,), 1) if photo else texture_views(fit, scores)
    images = _decode(read, {indices[k] for k in chosen})
    # a photo's texture keeps only the face inside its contour (photo_face_texels, below):
    # nothing of the room, so no segmentation model is loaded for it
    with nullcontext() if photo else SilhouetteFinder() as finder:
        fusion, occluded = _fuse(fit, chosen, primary, images, points, indices, camera,
                                 surface, finder)
        clean = clean_views(fusion, occluded)
        first_neutral = None
        if not clean[0] and clean.any():  # the neutral was occluded: take it from the clean
            first_neutral = indices[fit.neutral]
            fit = _fit(points, camera, where, [k for k, ok in zip(chosen, clean) if ok])
            surface = uv_surface(fit.mesh, TEXTURE_SIZE)
            chosen = (fit.neutral, *(k for k in chosen if k != fit.neutral))
            primary = 1
            images.update(_decode(read, {indices[k] for k in chosen} - set(images)))
            fusion, occluded = _fuse(fit, chosen, primary, images, points, indices, camera,
                                     surface, finder)
    valid = fusion.weight > 0
    if photo:
        pose = fit.poses[fit.neutral]
        face = points[fit.neutral]
        assert pose is not None and face is not None  # the neutral frame is a posed face frame
        image = images[indices[fit.neutral]]
        valid &= photo_face_texels(surface, ViewCamera(camera, pose), face, image.shape[:2])
    texture = fill_holes(fusion.texture, valid)
    evidence = {"views": [indices[k] for k in chosen],
                "misaligned": [indices[k] for k, ok in zip(chosen, fusion.aligned) if not ok],
                "occluded": {part: [indices[k] for k, bad in zip(chosen, flags) if bad]
                             for part, flags in occluded.items()},
                "neutral_occluded": first_neutral,
                "doubled": {part: round(fusion.doubled_fraction(mask), 3)
                            for part, mask in part_masks(fit.mesh, surface.size).items()}}
    confidence = texture_confidence(fusion, np.array([blur[k] for k in chosen]),
                                    np.array([k in handed for k in chosen]), occluded,
                                    part_masks(fit.mesh, surface.size))
    return fit, chosen, images, texture, evidence, confidence


def photo_face_texels(surface: UVSurface, camera: ViewCamera, points: np.ndarray,
                      shape: tuple[int, int]) -> np.ndarray:
    """The texels a photo shows as the face or above it (module docstring, "One photo").

    A texel is kept when its surface point projects inside the jaw contour (points 0 .. 16)
    or above it, ``PHOTO_FACE_MARGIN`` of the contour's width (point 0 to 16) in from its
    edge: the polygon of the contour closed by the two lines from points 0 and 16 along the
    face's up direction (chin, point 8, to the brows' mean), eroded by that margin, so the
    forehead, the hair and a hat on top stay.

    Args:
        surface: the texels' surface points (``uv_surface``).
        camera: the photo's camera (intrinsics and the fitted head pose).
        points: (68, 2) the photo's landmarks, px.
        shape: (H, W) the photo's size.

    Returns:
        (H_t, W_t) bool over the texture: covered texels inside that region.
    """
    height, width = shape
    up = points[17:27].mean(axis=0) - points[8]
    up /= max(float(np.linalg.norm(up)), 1e-6)
    reach = float(height + width) * up
    polygon = np.concatenate([points[0:17], [points[16] + reach, points[0] + reach]])
    region: np.ndarray = np.zeros((height, width), np.uint8)
    cv2.fillPoly(region, [np.rint(polygon * 8).astype(np.int32)], 1, lineType=cv2.LINE_8,
                 shift=3)
    margin = int(round(PHOTO_FACE_MARGIN * float(np.linalg.norm(points[16] - points[0]))))
    region = cv2.erode(region, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8))
    covered = surface.covered
    xy = np.rint(camera.project(surface.positions[covered].astype(np.float64))).astype(int)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < width) & (xy[:, 1] >= 0) & (xy[:, 1] < height)
    kept = np.zeros(len(xy), bool)
    kept[inside] = region[xy[inside, 1], xy[inside, 0]] > 0
    out = np.zeros(surface.size, bool)
    out[covered] = kept
    return out


def _decode(read: Callable[[slice], Iterable[VideoFrame]], wanted: set[int]
            ) -> dict[int, np.ndarray]:
    """The images of the frames ``wanted`` (video indices), decoded again."""
    if not wanted:
        return {}
    return {frame.index: frame.image for frame in read(slice(min(wanted), max(wanted) + 1))
            if frame.index in wanted}


def _fuse(fit: Fit, chosen: tuple[int, ...], primary: int, images: dict[int, np.ndarray],
          points: list[np.ndarray | None], indices: list[int], camera: Intrinsics,
          surface: UVSurface, finder: SilhouetteFinder | None
          ) -> tuple[Fusion, dict[str, np.ndarray]]:
    """The chosen views fused onto the fitted mesh (the first ``primary`` of them make the
    texture where none is an outlier), each within the person's silhouette
    (``sender.enroll.silhouette``; the whole view without a ``finder``), and per part which
    were occluded (``sender.enroll.evidence``, 3)."""
    views, silhouettes = [], []
    for k in chosen:
        pose, face = fit.poses[k], points[k]
        assert pose is not None and face is not None  # the views are among the posed frames
        image = images[indices[k]]
        views.append((image, ViewCamera(camera, pose)))
        if finder is not None:
            silhouettes.append(finder.find(image, face))
    parts = part_masks(fit.mesh, surface.size)
    fusion = fuse_views(fit.mesh, surface, views, primary=primary,
                        features=np.logical_or.reduce(list(parts.values())),
                        silhouettes=silhouettes if finder is not None else None)
    return fusion, occluded_parts(fusion, parts)


def at_rest(model: PersonModel) -> PersonModel:
    """The model with each region's rest layer painted into the base texture.

    First, in region order, the texels under each region become ``B (1 - a) + L a`` with L
    its layer at its (integer) rest state and ``a = opacity * mask / 255``. Then each
    region's rest layer becomes the finished texture under it (regions may overlap: the
    eyelids and eyeballs share the eyeball's texels). A receiver blends a region over the
    base as ``B + a (L_Q - B)``, so at rest it draws the base texture itself: a face at rest
    renders exactly as the model's preview, and the base texture carries the person's eyes
    and mouth as the enrollment camera saw them at rest (the neutral view alone sees the
    eyeball and the mouth's interior badly, through the lids and lips, with the occlusion
    test of ``sender.enroll.texture``).

    Args:
        model: a model whose regions' ``rest`` are layer indices.

    Returns:
        A new model (texture and regions replaced).
    """
    texture = model.texture.astype(np.float32)
    for region in model.regions:
        j = int(round(region.rest))
        for part in region.parts():
            alpha = region.opacity[j] * part.mask[..., None].astype(np.float32) / 255.0
            under = texture[texel_rect(part.uv_rect, texture.shape[:2])[1]]
            under[:] = np.clip(np.rint(under * (1.0 - alpha) + part.layers[j] * alpha), 0, 255)
    texture = texture.astype(np.uint8)

    def resting(part: Area, j: int) -> np.ndarray:
        layers = part.layers.copy()
        layers[j] = texture[texel_rect(part.uv_rect, texture.shape[:2])[1]]
        return layers

    regions = []
    for region in model.regions:
        j = int(round(region.rest))
        areas = tuple(replace(a, layers=resting(a, j)) for a in region.areas)
        regions.append(replace(region, layers=resting(region.parts()[0], j), rest=float(j),
                               areas=areas))
    return replace(model, texture=texture, regions=tuple(regions))


def render_preview(model: PersonModel, neutral_image: np.ndarray | None = None,
                   neutral_points: np.ndarray | None = None,
                   person: tuple[np.ndarray, int, Chosen] | None = None) -> np.ndarray:
    """The model from the front and from three-quarter view, beside the neutral frame.

    Args:
        model: the person model.
        neutral_image: (h, w, 3) uint8 BGR frame the texture's neutral view came from, or None.
        neutral_points: (68, 2) its landmarks (px), to crop the frame to the face like the
            renders; the whole frame when None.
        person: a (h, w, 3) uint8 BGR frame of the clip, its index and the build's choice
            of person, for the last row (module docstring, 5), or None: no such row.

    Returns:
        (PREVIEW_HEIGHT + R * REGION_ROW_HEIGHT [+ COVERAGE_ROW_HEIGHT]
        [+ PERSON_ROW_HEIGHT], W, 3) uint8 BGR
        image: [neutral frame |] front | three-quarter, then a row per region of its R
        regions, then, when the model has its coverage, a row naming the states covered and
        those not seen (module docstring).
    """
    mesh = model.mesh
    size = PREVIEW_HEIGHT
    panels = []
    if neutral_image is not None:
        panels.append(_face_crop(neutral_image, neutral_points, size))
    with MeshRenderer(size, size, samples=PREVIEW_SAMPLES,
                      background=PREVIEW_BACKGROUND) as renderer:
        triangles = triangle_groups(mesh.uv, mesh.triangles, region_areas(model.regions))[0]
        renderer.set_mesh(len(mesh.vertices), triangles, mesh.uv)
        renderer.set_texture(model.texture)
        for camera in preview_cameras(mesh):
            panels.append(renderer.render(mesh.vertices, camera)[..., ::-1])
    top = np.hstack(panels)
    usage = model.region_frames or {}
    rows = [_region_row(model.texture, r, top.shape[1], usage.get(r.name))
            for r in model.regions]
    if model.coverage is not None:
        rows.append(_coverage_row(model.coverage, top.shape[1]))
    if person is not None:
        rows.append(_person_row(*person, top.shape[1]))
    return np.vstack([top, *rows])


def _person_row(image: np.ndarray, frame: int, chosen: Chosen, width: int) -> np.ndarray:
    """(PERSON_ROW_HEIGHT, width, 3) BGR: frame ``frame`` of the clip (``image``) with its
    sampled faces boxed, the person's in green, those of the range's first frame numbered
    left to right (``--person N``), and the choice in words beside it."""
    row = np.full((PERSON_ROW_HEIGHT, width, 3), 24, np.uint8)
    scale = min((PERSON_ROW_HEIGHT - 8) / image.shape[0], (width / 2) / image.shape[1])
    view = cv2.resize(image, (max(1, int(image.shape[1] * scale)),
                              max(1, int(image.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    numbered = frame == chosen.first[0]
    shown = [(face, mine) for face, mine in chosen.faces if face.frame == frame]
    for n, (face, mine) in enumerate(shown):
        x0, y0, x1, y1 = (int(round(v * scale)) for v in face.box)
        colour = (80, 220, 80) if mine else (170, 170, 170)
        cv2.rectangle(view, (x0, y0), (x1, y1), colour, 2 if mine else 1, cv2.LINE_AA)
        label = " ".join(([str(n)] if numbered else []) + (["person"] if mine else []))
        cv2.putText(view, label, (x0, max(y0 - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    colour, 1, cv2.LINE_AA)
    row[4:4 + view.shape[0], 4:4 + view.shape[1]] = view
    text = chosen.line().removeprefix("person:").strip()
    x, y = view.shape[1] + 16, 24
    for part in text.split("; "):
        cv2.putText(row, part, (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (230, 230, 230), 1,
                    cv2.LINE_AA)
        y += 22
    return row


def _coverage_row(coverage: dict[str, bool], width: int) -> np.ndarray:
    """(COVERAGE_ROW_HEIGHT, width, 3) BGR: the states the layers show, and those they do
    not (``sender.enroll.coverage``)."""
    row = np.full((COVERAGE_ROW_HEIGHT, width, 3), 24, np.uint8)
    seen = [name.replace("_", " ") for name, ok in coverage.items() if ok]
    missing = [name.replace("_", " ") for name, ok in coverage.items() if not ok]
    for y, colour, text in ((22, (140, 220, 140), "covered: " + (", ".join(seen) or
                                                                  "only the neutral")),
                            (48, (120, 160, 240), "not seen: " + (", ".join(missing) or
                                                                   "none"))):
        cv2.putText(row, text, (6, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
    return row


def preview_cameras(mesh: Mesh) -> list[ViewCamera]:
    """The preview's cameras (``PREVIEW_YAWS``), ``PREVIEW_HEIGHT`` px square, framing the
    model as the receiver's virtual views do (``models.framing``) and like the crop of the
    neutral frame (``_face_crop``)."""
    centre, field = head_field(mesh.vertices[mesh.landmarks].astype(np.float64))
    return [ViewCamera.virtual(PREVIEW_HEIGHT, PREVIEW_HEIGHT, framing_pose(yaw, centre, field),
                               fov_y_deg=FOV_DEG) for yaw in PREVIEW_YAWS]


def _region_row(texture: np.ndarray, region: Region, width: int,
                frames: RegionFrames | None = None) -> np.ndarray:
    """(REGION_ROW_HEIGHT, width, 3) BGR: the region's name and how its layers spent the
    enrollment frames (``_usage_label``), then its layers in order, each drawn over the
    neutral texture as the receiver blends it (its areas side by side)."""
    drawn = [_drawn_layers(texture, part, region.opacity) for part in region.parts()]
    height = max(d.shape[1] for d in drawn)
    layers = np.concatenate([_to_height(d, height) for d in drawn], axis=2)
    h, w = layers.shape[1:3]
    row = np.full((REGION_ROW_HEIGHT, width, 3), 24, np.uint8)
    if frames is None:
        cv2.putText(row, region.name, (6, REGION_ROW_HEIGHT // 2 + 5),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (230, 230, 230), 1, cv2.LINE_AA)
    else:
        _usage_label(row, region.name, frames)
    k = len(region.layers)
    room = width - REGION_LABEL_WIDTH - 4 * k
    scale = min((REGION_ROW_HEIGHT - 4) / h, room / (k * w))
    size = (max(1, int(w * scale)), max(1, int(h * scale)))
    x = REGION_LABEL_WIDTH
    for layer in layers:
        tile = cv2.resize(layer[..., ::-1], size, interpolation=cv2.INTER_AREA)
        y = (REGION_ROW_HEIGHT - size[1]) // 2
        row[y:y + size[1], x:x + size[0]] = tile
        x += size[0] + 4
    return row


def _usage_label(row: np.ndarray, name: str, frames: RegionFrames) -> None:
    """Draw into a region row's label area: the name, ``used k / N`` (or ``no clean frame:
    base texture``), the clean frames not chosen, a line per reason of rejection with its
    count (as many as fit), and at the bottom a bar
    ``REGION_LABEL_WIDTH - 12`` px wide split in proportion to the frames used, clean but not
    chosen, and rejected per reason (``USAGE_COLOURS``)."""
    font, small = cv2.FONT_HERSHEY_SIMPLEX, 0.38
    cv2.putText(row, name, (6, 15), font, 0.5, (230, 230, 230), 1, cv2.LINE_AA)
    if frames.used:
        head, colour = f"used {len(frames.used)} / {frames.candidates}", USAGE_COLOURS["used"]
    else:
        head, colour = "no clean frame: base texture", (60, 160, 250)
    lines = [(head, colour), (f"{frames.clean} clean, not chosen", (110, 170, 110))]
    lines += [(f"{count} {USAGE_LABELS.get(reason, reason)}",
               USAGE_COLOURS.get(reason, (200, 200, 200)))
              for reason, count in usage_order(frames.rejected)]
    for y, (text, colour) in zip(range(30, REGION_ROW_HEIGHT - 12, 13), lines):
        cv2.putText(row, text, (6, y), font, small, colour, 1, cv2.LINE_AA)
    parts = [("used", len(frames.used)), ("clean", frames.clean),
             *usage_order(frames.rejected)]
    x, bar = 6.0, (REGION_LABEL_WIDTH - 12) / max(frames.candidates, 1)
    for kind, count in parts:
        x1 = x + count * bar
        if count:
            row[REGION_ROW_HEIGHT - 10:REGION_ROW_HEIGHT - 3, int(round(x)):max(
                int(round(x1)), int(round(x)) + 1)] = USAGE_COLOURS.get(kind, (200, 200, 200))
        x = x1


def _drawn_layers(texture: np.ndarray, part: Area, opacity: tuple[float, ...]) -> np.ndarray:
    """(k, h, w, 3) uint8 RGB: an area's layers over the texture under it, as blended."""
    base = texture[texel_rect(part.uv_rect, texture.shape[:2])[1]].astype(np.float32)
    alpha = np.asarray(opacity, np.float32)[:, None, None, None] \
        * part.mask[None, ..., None].astype(np.float32) / 255.0
    drawn = base[None] * (1.0 - alpha) + part.layers.astype(np.float32) * alpha
    return np.clip(np.rint(drawn), 0, 255).astype(np.uint8)


def _to_height(images: np.ndarray, height: int) -> np.ndarray:
    """(k, h, w, 3) images resized to (k, height, w * height / h, 3)."""
    width = max(1, round(images.shape[2] * height / images.shape[1]))
    return np.stack([cv2.resize(i, (width, height), interpolation=cv2.INTER_AREA)
                     for i in images])


def _face_crop(image: np.ndarray, points: np.ndarray | None, size: int) -> np.ndarray:
    """A square crop of the frame around the face, ``size`` px: the preview's field
    (``models.framing``: ``FIELD_EYE_DISTANCES`` outer-eye distances wide, centred
    ``FIELD_RAISE`` of it above the points' mean)."""
    h, w = image.shape[:2]
    if points is None:
        side, x0, y0 = min(h, w), (w - min(h, w)) // 2, (h - min(h, w)) // 2
    else:
        side = int(FIELD_EYE_DISTANCES * float(outer_eye_distance(points)))
        cx, cy = points.mean(axis=0)
        x0, y0 = int(cx - side / 2), int(cy - side / 2 - FIELD_RAISE * side)
    pad = max(0, -x0, -y0, x0 + side - w, y0 + side - h)
    padded = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_CONSTANT,
                                value=(40, 40, 40))
    crop = padded[y0 + pad:y0 + pad + side, x0 + pad:x0 + pad + side]
    return cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA)


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise BuildError(f"{path}: could not encode the preview")
    path.write_bytes(data.tobytes())

