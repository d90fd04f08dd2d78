"""Appearance enrollment: a person's region layers and classification templates from video.

``facewire model build`` (``sender.enroll.build.build_model``) first fits the geometry and
the neutral texture, then calls ``enroll_regions`` on the same frames. The templates must be
what the sender will sample at run time, so enrollment runs the sender itself: the real
``SenderPipeline`` (tracker, pose, lift, filters) on the model being built and the real
``AppearanceSampler``. That is also why it lives in ``sender``: ``models`` may not import
the sender's pose and lift.

1. Observe. Every frame of the range goes through the pipeline; each frame with a pose
   gives its pose, residuals, the (centre-offset) sample of every region, five cues, the
   parts of the face occluded in it (``sender.enroll.evidence``, 4, and the hands found by
   ``sender.enroll.occluders``: a region whose part is occluded in a frame takes nothing
   from it, its cue there is dropped) and the
   coverage's measures (``sender.enroll.coverage.state_measures``: once the states are
   chosen, ``coverage.measure_coverage`` judges which expression states their frames show).
2. Cues (``sender.cues.region_cues``, landmark-derived; at run time only the classifier
   decides Q): brow raise, brows drawn together, eye closure, gaze (frames with the lid
   open only: aspect ratio over 0.8 of the median), mouth opening.

3. States. A region of k states spans its cue from a *rest* level to an *extreme* level, at
   k evenly spaced cue levels: eyelids from the 10th percentile (wide open: a typical open
   eye then lies a little way into the range, and a wide-open one is no stranger to the
   templates than a half-closed one) to the 99th (closed: blinks are brief, so the extreme
   is rare); forehead and brow furrow from the median to the 98th percentile; mouth from
   the 5th to the 98th percentile; gaze from the 5th to the 95th percentile. The level
   nearest to the neutral frame's own cue is the region's *rest* state and takes the
   neutral frame itself (``sender.enroll.build`` chose it, and paints the rest layers into the
   base texture) unless that frame is unusable for the region (its cue undefined: its
   part occluded there); then the rest state is chosen like the others. Every other level
   takes the frame whose cue is nearest to it (ties broken toward a frontal head: cost
   |cue - level| / span + 0.002 |yaw deg|; for an eyelid, also toward an eye looking
   ahead: + 0.002 ``GAZE_COST`` |gaze - its median| / gaze span, so that its templates do
   not tie the lid's state to a gaze), among the usable frames, each at most once per
   region while any is left (with fewer usable frames than states, some serve twice). A
   region with no usable frame takes none: its states are all the neutral frame's, with
   opacity 0, so it draws the base texture; ``sender.enroll.usage`` counts the frames each
   region used and rejected. A region whose span is below ``MIN_SPAN`` (the video
   does not show that expression) still gets its k states, and the report says it is weak.
   A guided recording (``sender.enroll.routine.Guide``) narrows both steps for each region:
   the levels are the percentiles over its prompts' frames and the neutral prompt's, and
   every state but the rest one takes a frame of its prompts (another frame only when its
   prompts' frames with a cue run out; the report's ``prompted`` says whether they did).
4. Layers. Each state's frame is projected onto the region's UV rectangle (and onto each
   of its further areas, the eyelids' lid skin, the same way): every texel's
   surface point (``sender.texels``: its triangle and barycentric weights, from
   ``sender.enroll.texture.uv_surface``
   of the neutral mesh) is moved by that frame's morph, posed, projected and read from the
   frame bilinearly, with no occlusion test (a closed mouth paints its lips into the hidden
   mouth interior, which is what the sender's camera sees there; step 7 puts the interior
   back). Texels off the image or facing away keep the neutral texture, and so do an eye
   region's texels under glare (``sender.enroll.glare``: a lens's or the cornea's
   reflection, bright and grey, is no eyelid or gaze state). Each layer is
   then scaled per colour channel by g = sum(base) / sum(layer) over the border ramp
   (clipped to [0.5, 2]), so an exposure change between frames leaves no step at the
   border. The skin regions' layers
   (``SHADED``: forehead, brow furrow) then take the base texture's broad shading: each is
   multiplied by the smooth field f = (G*(B w) / G*w + 1) / (G*(g L w) / G*w + 1), clipped
   to ``SHADING_LIMITS``, G a Gaussian of sigma ``SHADING_SIGMA`` times the area's shorter
   side (some 19 texels), B the base, g L the scaled layer, w 1 on the texels read. A
   wrinkle, finer than G, stays; a frame's own light on the skin (a highlight, the shadow of
   hair), broader than G, goes, and the rendered layer shows no lighter box (on lp_d14 the
   brow furrow's was plain between the brows). The ramp is that of the region's last
   area: its only one, or for an eyelid the lid skin, the same skin in every state (the
   eyeball's border under an open lid is eyeball, and matching a closed lid to it darkened
   the closed states). The mask is the region's
   ``ramp_mask``; the eyelids' open states, those up to the rest state, have opacity 0: an
   open lid shows the gaze layers under it (an opaque rest state painted the neutral
   frame's gaze over every open eye).
5. Templates: each state's frame's centre sample, 16 x 16 raw grey levels.
6. Rest: the rest state's index, ``Region.rest``: what a receiver shows for a face at
   rest or lost. The neutral frame's sample is that state's template, so the classifier
   gives exactly this Q on it.
7. Interior (``sender.enroll.interior``). The mouth cavity's texels (its disc's bounding
   rectangle, the texels on ``MOUTH_INTERIOR`` triangles) are read from each of the mouth
   states' frames as in step 4, with each frame's weight: how far the texel's projection
   lies inside that frame's inner-lip polygon (0 unless the frame's mouth cue is at least
   ``sender.enroll.coverage.OPEN_GAP`` and its mouth is not occluded: by the ring test or a
   hand, ``covered``; 0 too where the texel looks like lit skin,
   ``sender.enroll.interior.skin_like``). Their weighted median
   where seen, the seen colours carried over the rest (or, with too little seen, the
   made-up interior) elsewhere, is the interior; it replaces the base texture's cavity
   (``Enrollment.texture``), and in each mouth layer a texel takes
   w L + (1 - w) I (L the layer, I the interior, w its own frame's weight), so a layer
   keeps its frame's pixels only where that frame saw into the mouth. The templates stay
   the frames' samples (step 5): what the sender's camera sees, lips and all.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from facewire.models.geometry import Intrinsics
from facewire.models.head.uvlayout import MOUTH_UV, MOUTH_UV_RADIUS
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import frames_in_range, range_text, read_frames, video_info
from facewire.models.landmarks import eye_aspect_ratio
from facewire.models.manifest import RegionFrames
from facewire.models.mesh import Mesh, Tag
from facewire.models.modelfile import Area, PersonModel, Region
from facewire.models.regions import REGION_NAMES, REGIONS, RegionSpec, place, ramp_mask
from facewire.models.rig import Rig
from facewire.models.texelgrid import texel_rect
from facewire.protocol.errors import FacewireError
from facewire.protocol.rate import stream_rate
from facewire.sender.appearance import AppearanceSampler
from facewire.sender.clean import REGION_PARTS, ring_mask, ring_occluded
from facewire.sender.cues import EYEBALL_LEFT, EYEBALL_RIGHT, region_cues
from facewire.sender.enroll.align import register_layer
from facewire.sender.enroll.coverage import (
    OPEN_GAP,
    Coverage,
    measure_coverage,
    reference,
    state_measures,
)
from facewire.sender.enroll.glare import glare_free
from facewire.sender.enroll.interior import (
    continued,
    disc_polar,
    fuse_seen,
    interior,
    palette,
    seen_weight,
    skin_like,
    synthetic,
)
from facewire.sender.enroll.routine import Guide
from facewire.sender.enroll.texture import UVSurface, uv_surface
from facewire.sender.enroll.usage import region_frames
from facewire.sender.pipeline import SenderPipeline
from facewire.sender.texels import AreaTexels, state_layers

OPEN_EYE = 0.8  # aspect ratio over this fraction of the median: the lid is open
GAZE_COST = 150.0  # an eyelid state's cost, degrees of yaw, per gaze span off the middle
MIN_SPAN = {"forehead": 1.5, "brow_furrow": 1.0, "eyelid": 0.08, "eyeball": 0.1,
            "mouth": 0.08}  # cue units (module docstring)
_LEVELS = {"forehead": (50, 98), "brow_furrow": (50, 98), "eyelid": (10, 99),
           "eyeball": (5, 95), "mouth": (5, 98)}  # percentiles: rest, extreme
_MOUTH = REGION_NAMES.index("mouth")


class EnrollError(FacewireError, ValueError):
    """The video cannot give appearance states; the message says why."""


@dataclass(frozen=True)
class Observation:
    """One frame of the enrollment video with a pose.

    Attributes:
        index: the video frame index.
        rotation: (3, 3) the sent pose's rotation; translation: (3,) mm.
        residuals: (9, 3) float32 the sent residuals, model space, mm.
        samples: (R, 16, 16) float32 each region's centre sample (``REGIONS`` order).
        cues: (R,) float64 each region's cue (module docstring); NaN when not defined.
        eye_ratio: (2,) the eye aspect ratios (right eye, left eye).
        yaw_deg: the head's yaw, degrees.
        measures: (M,) float64 the frame's ``sender.enroll.coverage.state_measures``.
        lips: (8, 2) float32 the inner-lip landmarks 60..67, px.
        occluded: the parts of the face (``sender.clean.PARTS``) occluded in the
            frame (``sender.clean.ring_occluded``).
    """

    index: int
    rotation: np.ndarray
    translation: np.ndarray
    residuals: np.ndarray
    samples: np.ndarray
    cues: np.ndarray
    eye_ratio: np.ndarray
    yaw_deg: float
    measures: np.ndarray
    lips: np.ndarray
    occluded: frozenset[str] = frozenset()


class Enrollment(NamedTuple):
    """What ``enroll_regions`` made: the regions, per region how they were chosen (the
    report is ``BuildResult.appearance``, ``sender.enroll.build``), which states their
    layers show (``sender.enroll.coverage``), per region the frames used and rejected
    (``sender.enroll.usage``), and the model's base texture with the mouth's interior in
    its cavity (step 7)."""

    regions: tuple[Region, ...]
    report: dict[str, dict[str, Any]]
    coverage: Coverage
    usage: dict[str, RegionFrames]
    texture: np.ndarray


def enroll_regions(model: PersonModel, video: str | os.PathLike[str],
                   frames: slice = slice(0, None), progress: Progress = no_progress,
                   guide: Guide | None = None,
                   covered: Mapping[int, frozenset[str]] | None = None) -> Enrollment:
    """Choose every region's states in a video and extract their layers and templates.

    Args:
        model: the person's geometry model (mesh, neutral texture, enrollment camera);
            its own regions are ignored.
        video: the enrollment video.
        frames: the frame range to use.
        progress: wraps an iterable to show progress.
        guide: a guided recording's prompted frames (``sender.enroll.routine``): each
            region's states chosen among its prompts' frames (module docstring, 3).
        covered: per video frame index, the parts of the face (``sender.clean.PARTS``)
            an occluder covers there (``sender.enroll.occluders``): occluded as when the
            ring test finds them (module docstring, step 1).

    Returns:
        The regions in ``REGIONS`` order, a report per region (the chosen frames, their
        cue values, the span, whether it is weak, the rest state: the neutral frame's,
        and with a guide whether its states came from its prompts' frames), the states
        the layers' frames show, and per region the frames used and rejected.

    Raises:
        EnrollError: fewer than 2 frames with a pose.
        VideoError: the video cannot be decoded.
    """
    video = Path(video)
    texels = _RegionTexels(model, model.camera)
    observations, candidates = _observe(model, model.camera, video, frames, progress, texels,
                                        covered or {})
    if len(observations) < 2:
        raise EnrollError(f"{video}: {len(observations)} frames with a head pose in range "
                          f"{range_text(frames)}; appearance needs at least 2")
    raw = np.array([o.cues for o in observations])
    cues = without_closed_eyes(raw, np.array([o.eye_ratio for o in observations]))
    lid_closed = np.isnan(cues) & ~np.isnan(raw)
    blocked = np.array([[REGION_PARTS.get(r.name, "") in o.occluded for r in REGIONS]
                        for o in observations])
    cues[blocked] = np.nan  # an occluded part gives its regions nothing (step 1)
    yaw = np.array([abs(o.yaw_deg) for o in observations])
    neutral = min(range(len(observations)),
                  key=lambda i: abs(observations[i].index - model.info.neutral_frame))
    chosen: dict[str, list[int]] = {}
    report: dict[str, dict[str, Any]] = {}
    seen = np.array([o.index for o in observations])
    for r, region in enumerate(REGIONS):
        prompted = calm = None
        if guide is not None:
            prompted = np.isin(seen, list(guide.regions.get(region.name, ())))
            calm = np.isin(seen, list(guide.neutral))
        picks, info = _choose_states(region, cues[:, r], yaw + _gaze_cost(region, cues),
                                     neutral, prompted, calm)
        chosen[region.name] = picks
        report[region.name] = {**info, "frames": [observations[i].index for i in picks],
                               "occluded_frames": int(blocked[:, r].sum())}
    usage = region_frames(candidates, blocked, lid_closed, np.isnan(cues),
                          seen.tolist(),
                          [report[r.name]["frames"] for r in REGIONS], REGION_NAMES)
    measures = np.array([o.measures for o in observations])
    coverage = measure_coverage({name: measures[picks] for name, picks in chosen.items()},
                                reference(measures))
    for region in REGIONS:  # no clean frame: every state the neutral's, drawn transparent
        chosen[region.name] = chosen[region.name] or [neutral] * region.layers

    wanted = sorted({i for picks in chosen.values() for i in picks})
    images = {}
    by_index = {observations[i].index: i for i in wanted}
    for frame in progress(read_frames(video, slice(observations[wanted[0]].index,
                                                   observations[wanted[-1]].index + 1)),
                          "layers", None):
        if frame.index in by_index:
            images[by_index[frame.index]] = frame.image
    inside, weights = texels.cavity.interior(
        [(images[i], observations[i]) for i in chosen["mouth"]])
    regions = []
    for r, region in enumerate(REGIONS):
        picks = chosen[region.name]
        rest = report[region.name]["rest"]
        parts = [np.stack(stack) for stack in zip(*(
            texels.layers(region.name, images[i], observations[i], j == rest)
            for j, i in enumerate(picks)))]
        masks = [np.rint(255 * ramp_mask(p.shape[1:3])).astype(np.uint8) for p in parts]
        templates = np.stack([observations[i].samples[r] for i in picks]).astype(np.float32)
        opacity = tuple(0.0 if (region.transparent_open and j <= rest) or not usage[
            region.name].used else 1.0 for j in range(len(picks)))
        placement = texels.placements[region.name]
        areas = tuple(Area(*area) for area in zip(placement.areas, parts[1:], masks[1:]))
        if region.name == "mouth":
            parts[0] = texels.cavity.layers(parts[0], placement.uv_rect, inside, weights)
        regions.append(Region(region.name, placement.uv_rect, placement.template_rect, parts[0],
                              masks[0], templates, opacity, float(rest), areas))
    return Enrollment(tuple(regions), report, coverage, usage,
                      texels.cavity.paint(model.texture, inside))


def _observe(model: PersonModel, camera: Intrinsics, video: Path, frames: slice,
             progress: Progress, texels: _RegionTexels,
             covered: Mapping[int, frozenset[str]]) -> tuple[list[Observation], int]:
    """Run the sender over the frames (module docstring, step 1); the frames with a pose,
    and how many frames were read; a frame's occluded parts are the ring test's and those
    ``covered`` names for it."""
    info = video_info(video)
    pipeline = SenderPipeline(model, camera, rate_hz=stream_rate(info.rate_hz))
    names = tuple(r.name for r in REGIONS)
    sampler = AppearanceSampler(model.mesh, pipeline.rig, camera, names)
    total = frames_in_range(frames, info.frames)
    out, read = [], 0
    for frame in progress(read_frames(video, frames), "appearance", total):
        read += 1
        sent = pipeline.process(frame.image, frame.time)
        if sent.rotation is None or sent.translation is None or sent.points is None:
            continue
        gray = cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
        samples = sampler.sample(gray, sent.rotation, sent.translation, sent.residuals)
        forward = sent.rotation[:, 2]
        cues = region_cues(samples[:, 0], sent.points, sent.residuals)
        measures = state_measures(sent.points, sent.residuals, dict(zip(names, cues)),
                                  frame.image)
        seen = Observation(
            index=frame.index, rotation=sent.rotation, translation=sent.translation,
            residuals=sent.residuals, samples=samples[:, 0].copy(), cues=cues,
            eye_ratio=eye_aspect_ratio(sent.points),
            yaw_deg=float(np.degrees(np.arctan2(forward[0], forward[2]))), measures=measures,
            lips=np.asarray(sent.points[60:68], np.float32))
        out.append(replace(seen, occluded=texels.occluded(frame.image, seen)
                           | covered.get(frame.index, frozenset())))
    return out, read


def without_closed_eyes(cues: np.ndarray, ratios: np.ndarray) -> np.ndarray:
    """The gaze cues blanked (NaN) on frames where that eye's lid is not open.

    Args:
        cues: (F, R) ``region_cues`` of F frames.
        ratios: (F, 2) the frames' eye aspect ratios (right eye, left eye).

    Returns:
        (F, R) a copy; eyeball cues are NaN where the eye's ratio is under ``OPEN_EYE``
        times its median over the frames.
    """
    cues = cues.copy()
    closed = ratios < OPEN_EYE * np.median(ratios, axis=0)
    cues[closed[:, 0], EYEBALL_RIGHT] = np.nan
    cues[closed[:, 1], EYEBALL_LEFT] = np.nan
    return cues


def _gaze_cost(region: RegionSpec, cues: np.ndarray) -> np.ndarray:
    """(F,) an eyelid state's extra cost, in degrees of yaw, for a frame whose eye looks away
    from the middle of the gaze seen: ``GAZE_COST`` times the distance of that eye's gaze cue
    from its median over the span of ``_LEVELS``; 0 for other regions and for frames
    without a gaze cue (lid closed). An eyelid's templates then show the eye looking ahead,
    as it mostly does, and a wide-open eye looking ahead is not read as a lid closing."""
    cost = np.zeros(len(cues))
    if _family(region) != "eyelid":
        return cost
    gaze = cues[:, REGION_NAMES.index(region.name.replace("eyelid", "eyeball"))]
    seen = np.isfinite(gaze)
    if seen.sum() < 2:
        return cost
    low, high = np.percentile(gaze[seen], _LEVELS["eyeball"])
    cost[seen] = GAZE_COST * np.abs(gaze[seen] - np.median(gaze[seen])) / max(high - low, 1e-6)
    return cost


def _family(region: RegionSpec) -> str:
    return region.name.split("_")[0] if region.name.startswith(("eyelid", "eyeball")) \
        else region.name


def _choose_states(region: RegionSpec, cue: np.ndarray, away: np.ndarray, neutral: int,
                   prompted: np.ndarray | None = None, calm: np.ndarray | None = None
                   ) -> tuple[list[int], dict[str, Any]]:
    """The observation index of each state, and the report entry with the rest state
    (module docstring, 3); ``neutral`` is the neutral frame's observation, ``away`` (F,)
    how far each frame is from a frontal head looking ahead, in degrees (|yaw|, plus
    ``_gaze_cost`` for an eyelid); ``prompted`` and ``calm`` (bool per observation) mark a
    guided recording's frames of the region's prompts and of the neutral prompt."""
    family = _family(region)
    usable = np.isfinite(cue)
    if not usable.any():
        return [], {"cue": [], "span": 0.0, "weak": True, "rest": 0}
    pools = [usable]  # where each state's frame is looked for, in turn
    span_of = usable  # the frames whose cue percentiles give the levels
    guided = prompted is not None and bool((usable & prompted).any())
    if guided:
        assert prompted is not None and calm is not None
        pools.insert(0, usable & prompted)
        span_of = usable & (prompted | calm)
    rest_pct, extreme_pct = _LEVELS[family]
    rest, extreme = np.percentile(cue[span_of], rest_pct), np.percentile(cue[span_of],
                                                                       extreme_pct)
    span = float(abs(extreme - rest))
    levels = np.linspace(rest, extreme, region.layers)
    scale = max(span, 1e-6)
    at_rest = cue[neutral] if usable[neutral] else np.median(cue[usable])
    rest_state = int(np.argmin(np.abs(levels - at_rest)))
    picks = [neutral] * region.layers
    taken = [neutral] if usable[neutral] else []
    for j, level in enumerate(levels):
        if j == rest_state and usable[neutral]:
            continue
        near = np.abs(np.nan_to_num(cue) - level) / scale + 0.002 * away
        for pool in pools:
            cost = np.where(pool, near, np.inf)
            cost[taken] = np.inf
            if np.isfinite(cost).any():
                break
        else:  # the usable frames ran out: they serve again
            cost = np.where(usable, near, np.inf)
        picks[j] = int(np.argmin(cost))
        taken.append(picks[j])
    weak = span < MIN_SPAN[family]
    info = {"cue": [round(float(cue[i]), 4) for i in picks], "span": round(span, 4),
            "weak": bool(weak), "rest": rest_state}
    if prompted is not None:
        info["prompted"] = all(prompted[i] for i in picks if i != neutral)
    return picks, info


class _RegionTexels:
    """Every region's texels as surface points of the model (module docstring, step 4)."""

    def __init__(self, model: PersonModel, camera: Intrinsics) -> None:
        self.model = model
        self.camera = camera
        shape = model.texture.shape[:2]
        surface = uv_surface(model.mesh, shape)
        rig = Rig(model.mesh)
        self.placements = {r.name: place(r, shape) for r in REGIONS}
        self.areas: dict[str, list[AreaTexels]] = {}
        for r in REGIONS:
            placement = self.placements[r.name]
            self.areas[r.name] = [_area(model.mesh, rig, surface, rect, shape)
                                  for rect in (placement.uv_rect, *placement.areas)]
        self.cavity = _Cavity(model, camera, surface, rig)
        self.rings: dict[str, tuple[AreaTexels, np.ndarray]] = {}
        for part in sorted(set(REGION_PARTS.values())):
            rect, ring = ring_mask(model.mesh, part, shape)
            self.rings[part] = (_area(model.mesh, rig, surface, rect, shape), ring)

    def occluded(self, image: np.ndarray, seen: Observation) -> frozenset[str]:
        """The parts whose ring departs from the base texture in ``image``
        (``sender.enroll.evidence``, 4)."""
        out = set()
        for part, (area, ring) in self.rings.items():
            colour, ok = _read(area, self.camera, image, seen)[:2]
            if ring_occluded(colour, ok, self.model.texture[area.slices], ring):
                out.add(part)
        return frozenset(out)

    def layers(self, name: str, image: np.ndarray, seen: Observation, rest: bool
               ) -> list[np.ndarray]:
        """(h, w, 3) uint8 RGB per area of the region: its texels read from ``image``, with
        the exposure gain of its last area, registered onto the base texture (module
        docstring, step 4; ``rest``: the rest state's, registered all over)."""
        areas = self.areas[name]
        base = [self.model.texture[a.slices] for a in areas]
        reads = [_read(a, self.camera, image, seen)[:2] for a in areas]
        if name.startswith(("eyelid", "eyeball")):  # a lens's or cornea's glare is no layer
            reads = [(c, glare_free(c, ok, b)) for (c, ok), b in zip(reads, base)]
        layers = state_layers(name, reads, base)
        if name == "mouth":  # behind the lips: its layers show what the base cannot
            return layers
        return [register_layer(layer, b, rest) for layer, b in zip(layers, base)]


class _Cavity:
    """The mouth cavity's texels: its interior from the mouth's frames, painted into its
    layers and the base texture (module docstring, step 7; ``sender.enroll.interior``)."""

    def __init__(self, model: PersonModel, camera: Intrinsics, surface: UVSurface,
                 rig: Rig) -> None:
        shape = model.texture.shape[:2]
        u, v = MOUTH_UV
        disc = (u - MOUTH_UV_RADIUS, v - 2 * MOUTH_UV_RADIUS, u + MOUTH_UV_RADIUS,
                v + 2 * MOUTH_UV_RADIUS)
        self.area = _area(model.mesh, rig, surface, texel_rect(disc, shape)[0], shape)
        rows, cols = self.area.slices
        tri = surface.triangles[rows, cols]
        tags = np.asarray(model.mesh.tags)
        self.inside = (tri >= 0) & (tags[np.maximum(tri, 0)] == Tag.MOUTH_INTERIOR)
        lip, self.skin = palette(model.texture, model.mesh)
        self.synthetic = synthetic(*disc_polar(rows, cols, shape), lip, self.skin)
        self.camera = camera
        self.shape = shape

    def interior(self, frames: list[tuple[np.ndarray, Observation]]
                 ) -> tuple[np.ndarray, list[np.ndarray]]:
        """The interior (h, w, 3) float32 RGB over the cavity's rectangle, and per frame
        (its image and observation) its weights (h, w) float32: how much of each texel it
        saw (0 for a frame whose mouth is not open)."""
        colours, weights = [], []
        for image, seen in frames:
            colour, ok, x, y = _read(self.area, self.camera, image, seen)
            weight = np.zeros(ok.shape, np.float32)
            if seen.cues[_MOUTH] >= OPEN_GAP and REGION_PARTS["mouth"] not in seen.occluded:
                weight = np.where(ok & self.inside & ~skin_like(colour, self.skin),
                                  seen_weight(seen.lips, x, y), 0.0)
            colours.append(colour)
            weights.append(weight.astype(np.float32))
        fused, coverage = fuse_seen(np.stack(colours), np.stack(weights))
        walls = continued(fused, coverage, self.inside)
        made_up = self.synthetic if walls is None else walls
        return interior(made_up, fused, coverage), weights

    def layers(self, layers: np.ndarray, rect: tuple[float, float, float, float],
               inside: np.ndarray, weights: list[np.ndarray]) -> np.ndarray:
        """The mouth's layers (k, h, w, 3) uint8 RGB over ``rect`` with every cavity texel
        its frame did not see (weights, one per layer, over the cavity's rectangle) taking
        the interior ``inside`` instead."""
        rows, cols = self._within(rect)
        cavity = self.inside[rows, cols][..., None]
        out = layers.astype(np.float32)
        for j, weight in enumerate(weights):
            w = weight[rows, cols][..., None]
            blended = w * out[j] + (1.0 - w) * inside[rows, cols]
            out[j] = np.where(cavity, blended, out[j])
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)

    def paint(self, texture: np.ndarray, inside: np.ndarray) -> np.ndarray:
        """The base texture (H, W, 3) uint8 RGB with the interior on the cavity's texels."""
        out = texture.copy()
        block = out[self.area.slices]
        block[self.inside] = np.clip(np.rint(inside[self.inside]), 0, 255).astype(np.uint8)
        return out

    def _within(self, rect: tuple[float, float, float, float]) -> tuple[slice, slice]:
        """The texels of ``rect`` as slices of the cavity's rectangle (``rect`` lies in it)."""
        rows, cols = texel_rect(rect, self.shape)[1]
        top, left = self.area.slices[0].start, self.area.slices[1].start
        return slice(rows.start - top, rows.stop - top), slice(cols.start - left,
                                                              cols.stop - left)


def _area(mesh: Mesh, rig: Rig, surface: UVSurface, rect: tuple[float, float, float, float],
          shape: tuple[int, int]) -> AreaTexels:
    """An area's texels on the model's UV surface (``sender.texels``)."""
    slices = texel_rect(rect, shape)[1]
    return AreaTexels(mesh, rig, rect, shape, surface.triangles[slices], surface.normals[slices])


def _read(area: AreaTexels, camera: Intrinsics, image: np.ndarray, seen: Observation
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``AreaTexels.read`` at an observation's pose and residuals."""
    return area.read(camera, image, seen.rotation, seen.translation, seen.residuals)
