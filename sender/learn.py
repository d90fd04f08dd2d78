"""The sender's learning: an appearance the model does not hold, noticed and captured as a
model update (``models.update.ModelUpdate``) during the session.

Noticing. Each frame the classifier gives every region its best score phi, the weighted L1
distance of the winning sample from the nearest template (``sender.classify``). How far a
face the templates describe lies from them depends on the region (a flat forehead scores
lower than an eye); the templates themselves say how far apart the region's states are.
So each region's bound is taken at session start from the model it holds:

    s_r = median over templates j of min over b != j of phi_b(T_j)    (the states' spacing)
    novel when phi > max(``MIN_NOVEL_PHI``, ``NOVEL_FACTOR`` s_r)

(with one template, the bound is ``MIN_NOVEL_PHI``). Derived, not stored: the model file
holds what it needs (the templates), older models work as they are, and ``model info``
has nothing new to show. Measured on lp_d18 (a tuning clip) with a model built on its frames
0:60, where the mouth never opens: on the enrolled frames phi was at most 47 (mouth),
61 (eyeballs), 36 (eyelids), 17 (forehead) and 16 (brow furrow), on the later closed-mouth
frames at most 90 (mouth), 74 (eyeballs); on the open mouth 100-174; a blink gives the eye
regions 100-170 for its few frames. The spacings: 15-24 (forehead), 8-13 (brow furrow),
29-61 (eyelids, eyeballs, mouth).

Candidates. A region is held as a candidate while its phi stays over the bound on
consecutive frames; a frame counts toward the capture only when it is clean evidence:
a pose was fitted and the face was not just lost or re-acquired (flags), the head within
``MAX_YAW_DEG`` of frontal, the face box sharp (``sender.clean.sharpness`` at least
``SHARP_RATIO`` times the median over the session's reference frames, one every
``SHARPNESS_EVERY`` frames) and, for the mouth and the eye regions, its part not occluded
(``sender.clean.ring_occluded`` against the base texture). A frame under the bound ends the
run. ``HOLD_FRAMES`` consecutive novel frames with ``CAPTURE_FRAMES`` clean ones among them
(a blink lasts 3-6 frames at 30 Hz: it never gets there) make a capture, unless the region
learned within ``COOLDOWN_S``, or the traffic's budget is spent (nothing is held
meanwhile): the learning keeps the transport's own token bucket (``protocol.shaper.BUCKET``:
700 B/s, 17000 B deep), each update spending its bytes times ``WIRE_FACTOR`` (the chunk
messages' fields), and issues an update (a state or a texture patch, ``sender.heal``) only
while the bucket is not in debt: a first burst as deep as the wire's, then no faster, on
average, than the wire may carry them (the transport paces each chunk within the budget over
any second). While the healing's last look found tiles to patch, or it has not looked
since the model last changed (``Healer.wanting``), no capture is made unless the last
update was a patch: the texture heals first (a hand baked into it is what the viewer sees),
and then patches and states take turns (a healing that keeps finding tiles does not starve
the learning).

Capture. From the last ``CAPTURE_FRAMES`` clean frames of the run: each frame's layer
images, one per area of the region, read the way enrollment reads them (``sender.texels``:
the texels' surface points on the morphed, posed mesh, projected and read bilinearly;
exposure matched to the base texture at the border, the skin regions' broad shading
matched), fused texel by texel by the median; the template is the median of their centre
samples. The mouth's layer keeps what the camera saw in the cavity (enrollment paints the
interior of frames that do not see into it; a mouth wide enough to be novel does). Then,
per area, only what changed is kept: a texel whose difference from the update's reference
(the state the new one sits just before, ``models.update.references``: the bytes carry the
difference from it), the largest over the colour channels, smoothed by a Gaussian of
``CHANGE_SIGMA`` texels, exceeds ``CHANGE_LEVELS`` grey levels is changed, the changed
area is grown by ``CHANGE_GROW`` texels, and every other texel takes the reference's
value: the skin around an opened mouth stays as it was, and its texels cost nothing on the
wire. The changed texels' difference from the reference is then kept at the frame's own
resolution, not the texture's: averaged over blocks of b x b texels, b the texels one frame
pixel spans (1 .. ``MAX_BLOCK``; the median distance in pixels between neighbouring texels'
projections, inverted and floored), and rounded to ``DIFF_STEP`` (4) grey levels, at most
2 levels off. The texture is finer than a face in a camera frame (lp_d18's 480 x 480
frames: 0.43-0.48 px between neighbouring mouth texels, so blocks of 2), so the blocks show
nothing the camera saw, and the bytes (the difference, zlib-compressed) stop paying for
interpolated noise; a coarser rounding instead (steps of 8 levels, no blocks) showed contour
bands in the smooth inside of the mouth. lp_d18's open mouth, learned on a model of its
closed mouth, changes 93 % of the mouth's texels (the whole cavity): its difference took
36.0 kB exact, 21.7 kB rounded to 2 levels, 10.5 kB in blocks of 2 rounded to 2, 6.8-7.0
kB in blocks of 2 rounded to 4; the whole update 37.3 kB exact, 8.2 kB as made. At the
wire's 32 kbit/s over a second, 8.2 kB take 2.1 s, so the first update can
reach the receivers within 3 s of the expression (37 kB took 9.3 s).

Placing it. Q must stay a scalar along the region's axis, so the new state goes where its
landmark cue (``sender.cues.region_cues``: mouth opening, eye closure, brow raise, ...)
belongs among the existing states': the session keeps, per state, the mean cue of the frames
that state matched (rounded Q, phi under the bound, one frame in ``CUE_EVERY``), the rest
state starting from the neutral face's own cue (the model's landmark vertices seen from the
front, zero residuals: the neutral; the gaze has no such cue). The new state is inserted
before the first state whose mean cue is larger, or after all of them; states never matched
do not count. A region holds at most ``models.update.MAX_LEARNED_LAYERS`` states; a full one
replaces its least used state (the fewest frames with that rounded Q this session), never the
rest state. An eyelid's state placed at or before its rest state (an eye open wider) is
transparent, as enrollment makes the open states (``models.regions``).

In the background (``background``, the live ``send``): a capture costs 170-220 ms on
lp_d18's mouth (against 12 ms for a frame), two thirds of it finding the region's texels on
the mesh the first time. So a worker thread finds every region's texels and every part's
ring at session start, and fuses each capture's held frames; the frame that finds a fusion
done places it and issues the update, so the frames in between are sent on time, and no
other capture starts meanwhile; the held frames' occlusion (a few ms each, once the rings
are found) is judged on the worker too. Without it (an ``encode``, the tests) all
of it runs on the frame that made the capture due, so that a log's updates do not depend on
the machine's speed.

The update is applied to the learner's own model at once (``models.update.apply_update``),
and the sender's classifier takes the new templates (``sender.pipeline``): the next frame
is classified with them, and the next packets' Q refer to the new model version.

Cost (CPU time, lp_d18's 216 frames of 480 x 480, a model of its closed mouth, one update):
noticing is a comparison per region and the states' statistics, the cues on one frame in
``CUE_EVERY`` and the sharpness on one in ``SHARPNESS_EVERY``: 0.05 ms median per frame,
0.16-0.19 ms mean over the frames without a capture (novel frames hold a copy of the frame,
its sharpness and its cues). A capture took 170-220 ms, two thirds of it building the
region's texels on the mesh once per session (the mouth's area and the ring around it,
``sender.texels.area_surface`` and the surface points, some 70 ms each); the rest (reading
five frames' layers and rings, the medians, the update's bytes) some 70 ms. Over those 216
frames that is 0.9-1.1 ms a frame on average, over the 0.5 ms target; the traffic budget
spaces 8-kB updates some 15 s apart once its first 17 kB are spent, so over a minute with
one or two captures it is 0.3-0.4 ms. ``facewire bench speed`` reports ``learn_ms`` (median) and
``learn_ms_per_frame`` (mean, captures included).
"""

from __future__ import annotations

import dataclasses
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from facewire.models.fields import TEMPLATE_SIZE
from facewire.models.geometry import Intrinsics
from facewire.models.modelfile import PersonModel
from facewire.models.patch import TexturePatch, encode_patch
from facewire.models.regions import REGION_NAMES, spec
from facewire.models.rig import Rig
from facewire.models.update import (
    MAX_LEARNED_LAYERS,
    ModelUpdate,
    Update,
    apply_update,
    encode_update,
    references,
)
from facewire.protocol.packet import Flag
from facewire.protocol.shaper import BUCKET
from facewire.sender.classify import FrameClassification, RegionClassifiers
from facewire.sender.clean import (
    REGION_PARTS,
    SHARP_RATIO,
    ring_mask,
    ring_occluded,
    sharpness,
)
from facewire.sender.cues import region_cues
from facewire.sender.heal import LOOK_EVERY, Healer
from facewire.sender.texels import AreaTexels, area_surface, state_layers, welded_normals

NOVEL_FACTOR = 2.5  # phi over this many times the region's template spacing is unseen ...
MIN_NOVEL_PHI = 60.0  # ... and over this (normalised coefficient units)
HOLD_FRAMES = 8  # consecutive novel frames before a capture
CAPTURE_FRAMES = 5  # clean frames fused into the new state
MAX_YAW_DEG = 25.0  # a candidate frame's head within this of frontal
SHARPNESS_EVERY = 15  # frames between the session's sharpness reference samples
CUE_EVERY = 5  # frames between the states' cue statistics samples
SHARPNESS_WINDOW = 40  # reference samples kept
COOLDOWN_S = 3.0  # a region learns again at the earliest this long after its last update
WIRE_FACTOR = 1.3  # an update's bytes on the wire per byte (290 B of fields per 1 KiB chunk)
CHANGE_LEVELS = 12.0  # grey levels a texel must change by (smoothed) to be part of a state ...
CHANGE_SIGMA = 1.5  # ... the difference's Gaussian, texels ...
CHANGE_GROW = 2  # ... and the changed area grown by this many texels
DIFF_STEP = 4  # a changed texel's difference from the reference, in steps of this (grey levels)
MAX_BLOCK = 4  # texels a side of the blocks a changed difference is averaged over, at most
_BAD_FLAGS = Flag.TRACKING_LOST | Flag.REACQUIRED


@dataclass(eq=False)
class _Held:
    """One candidate frame of a region (clean but for occlusion, judged when needed)."""

    image: np.ndarray  # (H, W, 3) uint8 BGR
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    residuals: np.ndarray  # (9, 3)
    sample: np.ndarray  # (16, 16) float32 the region's centre sample
    cue: float
    occluded: bool | None = None


@dataclass(frozen=True, eq=False)
class _Fused:
    """A capture's fused state: one (h, w, 3) uint8 layer per area, the (16, 16) template,
    the median cue and the texels a frame pixel spans (``_block``)."""

    layers: tuple[np.ndarray, ...]
    template: np.ndarray
    cue: float
    block: int


class Learner:
    """Notices unseen appearance and captures it as model updates (module docstring).

    Args:
        model: the person model the session starts from (loaded from its file: its
            ``sha256`` names the base of every update).
        camera: the sender camera's intrinsics.
        rig: the model's rig.
        classifiers: the sender's classifier of the model's regions (packet order).

    Attributes:
        model: the model as learned so far (version ``serial``).
        serial: the last update's serial, 0 before any.
        updates: the updates issued, in order.
    """

    def __init__(self, model: PersonModel, camera: Intrinsics, rig: Rig,
                 classifiers: RegionClassifiers, background: bool = False,
                 heal: bool = True) -> None:
        if not can_learn(model):
            raise ValueError("model: learning needs the model's file identity (sha256) and "
                             "the regions of models.regions.REGIONS, in that order")
        self.model = model
        self.camera = camera
        self.rig = rig
        self.serial = 0
        self.updates: list[Update] = []
        self.update_bytes: dict[int, bytes] = {}  # serial -> the update's bytes
        self.base_sha256 = model.sha256
        self.names = REGION_NAMES
        self.bound = np.array([_bound(c.cross) for c in classifiers.regions])
        count = len(self.names)
        self._run = np.zeros(count, np.int64)
        self._held: list[deque[_Held]] = [deque(maxlen=HOLD_FRAMES) for _ in range(count)]
        k = [r.templates.shape[0] for r in model.regions[:count]]
        self._cue_sum = [np.zeros(n) for n in k]
        self._cue_count = [np.zeros(n, np.int64) for n in k]
        self._used = [np.zeros(n, np.int64) for n in k]
        neutral = region_cues(np.zeros((count, TEMPLATE_SIZE, TEMPLATE_SIZE), np.float32),
                              model.mesh.vertices[model.mesh.landmarks][:, :2],
                              np.zeros((9, 3)))
        for r, region in enumerate(model.regions[:count]):  # the rest state: the neutral face
            if np.isfinite(neutral[r]):
                self._cue_sum[r][round(region.rest)] += neutral[r]
                self._cue_count[r][round(region.rest)] += 1
        self._learned_at = np.full(count, -np.inf)
        self._budget = _Budget()
        self._frames = 0
        self._sharp: deque[float] = deque(maxlen=SHARPNESS_WINDOW)
        self._normals: np.ndarray | None = None
        self._areas: dict[str, list[AreaTexels]] = {}
        self._rings: dict[str, tuple[AreaTexels, np.ndarray]] = {}
        self._worker = ThreadPoolExecutor(1, "learn") if background else None
        self._pending: tuple[int, Future[_Fused | None]] | None = None
        self.healer = Healer(model, camera, rig) if heal else None
        self._healing: Future[TexturePatch | None] | None = None
        # the worker's search for every region's texels, at session start (None: inline)
        self.prepared = None if self._worker is None else self._worker.submit(self._prepare)

    def observe(self, image: np.ndarray, points: np.ndarray, rotation: np.ndarray,
                translation: np.ndarray, residuals: np.ndarray, samples: np.ndarray,
                result: FrameClassification, flags: Flag, time_s: float) -> Update | None:
        """One classified frame: notice, hold, and when a capture is due, capture.

        Args:
            image: (H, W, 3) uint8 BGR frame.
            points: (68, 2) its tracked points, px.
            rotation: (3, 3) the sent pose's rotation; translation: (3,) mm.
            residuals: (9, 3) the sent residuals, mm.
            samples: (R, 5, 16, 16) float32 the regions' samples that were classified.
            result: their classification (Q before the eye gate, and the scores).
            flags: the frame's packet flags.
            time_s: the frame's time, s.

        Returns:
            The update issued on this frame (already applied to ``model``): a region's new
            state or a texture patch (``sender.heal``), or None. In the background, the
            capture a frame makes due is issued by a later frame.
        """
        self._frames += 1
        issued: Update | None = None
        if self._pending is not None and self._pending[1].done():
            r, fused = self._pending[0], self._pending[1].result()
            self._pending = None
            issued = None if fused is None else self._issue(r, fused, time_s)
        if self._frames % SHARPNESS_EVERY == 1:
            self._sharp.append(sharpness(image, points))
        if self.healer is not None and issued is None:
            issued = self._heal(image, points, rotation, translation, residuals, result,
                                flags, time_s)
        novel = result.score > self.bound
        state = np.rint(result.q).astype(np.int64)
        for i in np.flatnonzero(~novel):
            self._run[i] = 0
            self._held[i].clear()
        for j in range(len(self.names)):
            self._used[j][state[j]] += 1
        cues = None
        if novel.any() or self._frames % CUE_EVERY == 1:
            cues = region_cues(samples[:, 0], points, residuals)
        if cues is not None and self._frames % CUE_EVERY == 1:
            for i in np.flatnonzero(~novel & np.isfinite(cues)):
                self._cue_sum[i][state[i]] += cues[i]
                self._cue_count[i][state[i]] += 1
        if issued is not None or self._pending is not None or not novel.any() \
                or not self._budget.allows(time_s):  # learning, nothing new, or no budget
            return issued
        assert cues is not None
        clean = not (flags & _BAD_FLAGS) and _yaw_deg(rotation) <= MAX_YAW_DEG
        if clean and self._sharp:
            clean = sharpness(image, points) >= SHARP_RATIO * float(np.median(self._sharp))
        copy = None
        for i in np.flatnonzero(novel):
            self._run[i] += 1
            if clean and np.isfinite(cues[i]):
                copy = image.copy() if copy is None else copy
                self._held[i].append(_Held(copy, rotation.copy(), translation.copy(),
                                           residuals.copy(), samples[i, 0].copy(),
                                           float(cues[i])))
        due = [int(i) for i in np.flatnonzero(novel) if self._run[i] >= HOLD_FRAMES
               and len(self._held[i]) >= CAPTURE_FRAMES
               and time_s - self._learned_at[i] >= COOLDOWN_S]
        patched_last = bool(self.updates) and isinstance(self.updates[-1], TexturePatch)
        if not due or (self.healer is not None and self.healer.wanting and not patched_last):
            return None  # nothing due, or the texture heals first (the two take turns)
        r = max(due, key=lambda i: result.score[i] / self.bound[i])  # the most unlike
        if self.prepared is not None and not self.prepared.done():
            return None  # the worker is still finding the texels on the mesh
        held = list(self._held[r])
        if self._worker is not None:  # judged and fused on the worker, issued on a later frame
            self._pending = (r, self._worker.submit(self._capture, r, held))
            return None
        fused = self._capture(r, held)
        return None if fused is None else self._issue(r, fused, time_s)

    def _heal(self, image: np.ndarray, points: np.ndarray, rotation: np.ndarray,
              translation: np.ndarray, residuals: np.ndarray, result: FrameClassification,
              flags: Flag, time_s: float) -> TexturePatch | None:
        """The healing's part of a frame (``sender.heal``): a clean frame read now and
        then, a patch looked for after a read while the budget allows one (on the worker
        in the background) and issued."""
        healer = self.healer
        assert healer is not None
        clean = not (flags & _BAD_FLAGS) and _yaw_deg(rotation) <= MAX_YAW_DEG
        if healer.due(clean) and (not self._sharp or sharpness(image, points)
                                  >= SHARP_RATIO * float(np.median(self._sharp))):
            healer.read(image, points, rotation, translation, residuals, result.q)
        made = None
        if self._healing is not None:
            if not self._healing.done():
                return None
            made, self._healing = self._healing.result(), None
        elif healer.fresh >= LOOK_EVERY and self._budget.allows(time_s) \
                and self._pending is None:
            healer.fresh = 0
            reads = healer.held()
            if self._worker is not None:
                self._healing = self._worker.submit(healer.patch, reads, self.base_sha256, 1)
                return None
            made = healer.patch(reads, self.base_sha256, 1)
        if made is None or not self._budget.allows(time_s):
            return None
        patch = dataclasses.replace(made, serial=self.serial + 1)
        data = self.update_bytes[patch.serial] = encode_patch(patch)
        self._budget.spend(time_s, len(data))
        self.model = apply_update(self.model, patch)
        self.serial = patch.serial
        self.updates.append(patch)
        healer.take(self.model)
        return patch

    def _capture(self, r: int, held: list[_Held]) -> _Fused | None:
        """Region r's new state from the last ``CAPTURE_FRAMES`` of its held frames whose
        part is not occluded (each frame judged once), oldest first; None when there are not
        that many (the region's run goes on)."""
        chosen: list[_Held] = []
        for frame in reversed(held):
            if frame.occluded is None:
                frame.occluded = self._occluded(r, frame)
            if not frame.occluded:
                chosen.append(frame)
            if len(chosen) == CAPTURE_FRAMES:
                return self._fuse(r, chosen[::-1])
        return None

    def _prepare(self) -> None:
        """Find every region's texels and every part's ring on the mesh (the first capture
        of a region would otherwise do it)."""
        for r, name in enumerate(self.names):
            self._texels(r)
            part = REGION_PARTS.get(name)
            if part is not None:
                self._ring(part)

    def _occluded(self, r: int, held: _Held) -> bool:
        """Whether region r's part of the face is occluded (``sender.clean``)."""
        part = REGION_PARTS.get(self.names[r])
        if part is None:
            return False
        area, ring = self._ring(part)
        colour, seen, _, _ = area.read(self.camera, held.image, held.rotation, held.translation,
                                       held.residuals)
        return ring_occluded(colour, seen, self.model.texture[area.slices], ring)

    def _ring(self, part: str) -> tuple[AreaTexels, np.ndarray]:
        """A part's ring (``sender.clean.ring_mask``) as texels, found once."""
        if part not in self._rings:
            rect, ring = ring_mask(self.model.mesh, part, self.model.texture.shape[:2])
            self._rings[part] = (self._area(rect), ring)
        return self._rings[part]

    def _texels(self, r: int) -> list[AreaTexels]:
        """Region r's areas (the rectangles its layers cover) as texels, found once."""
        name = self.names[r]
        if name not in self._areas:
            region = self.model.regions[r]
            self._areas[name] = [self._area(rect) for rect in
                                 (region.uv_rect, *(a.uv_rect for a in region.areas))]
        return self._areas[name]

    def _area(self, rect: tuple[float, float, float, float]) -> AreaTexels:
        """An area's texels on the model's surface, found on the CPU (``sender.texels``)."""
        if self._normals is None:
            self._normals = welded_normals(self.model.mesh)
        shape = self.model.texture.shape[:2]
        triangles, normals = area_surface(self.model.mesh, rect, shape, self._normals)
        return AreaTexels(self.model.mesh, self.rig, rect, shape, triangles, normals)

    def _fuse(self, r: int, held: list[_Held]) -> _Fused:
        """Region r's new state from its held frames (module docstring, capture): the costly
        part, which reads only what no update changes (the mesh, the base texture)."""
        name = self.names[r]
        areas = self._texels(r)
        base = [self.model.texture[a.slices] for a in areas]
        reads = [[a.read(self.camera, h.image, h.rotation, h.translation, h.residuals)
                  for a in areas] for h in held]
        per_frame = [state_layers(name, [read[:2] for read in frame], base) for frame in reads]
        block = _block(*reads[-1][0][1:])
        layers = tuple(np.median(np.stack(stack), axis=0).round().astype(np.uint8)
                       for stack in zip(*per_frame, strict=True))
        template = np.median(np.stack([h.sample for h in held]), axis=0).astype(np.float32)
        return _Fused(layers, template, float(np.median([h.cue for h in held])), block)

    def _issue(self, r: int, fused: _Fused, time_s: float) -> ModelUpdate:
        """Region r's fused state placed, made the next update, applied and encoded (module
        docstring, placing it)."""
        self._run[r] = 0
        self._held[r].clear()
        name, layers, template, cue = self.names[r], fused.layers, fused.template, fused.cue
        region = self.model.regions[r]
        k = region.templates.shape[0]
        rest = round(region.rest)
        replaces = None
        if k >= MAX_LEARNED_LAYERS:
            used = self._used[r].astype(np.float64)
            used[rest] = np.inf
            replaces = int(np.argmin(used))
        kept = [j for j in range(k) if j != replaces]
        position = len(kept)
        for n, j in enumerate(kept):
            if self._cue_count[r][j] and self._cue_sum[r][j] / self._cue_count[r][j] > cue:
                position = n
                break
        rest_kept = rest - (replaces is not None and replaces < rest)
        opacity = 0.0 if spec(name).transparent_open and position <= rest_kept else 1.0
        update = ModelUpdate(base_sha256=self.base_sha256, serial=self.serial + 1,
                             region=name, position=position, replaces=replaces,
                             layers=layers, template=template, opacity=opacity)
        update = dataclasses.replace(update, layers=tuple(
            _changed_only(layer, reference, fused.block)
            for layer, reference in zip(layers, references(self.model, update), strict=True)))
        data = self.update_bytes[update.serial] = encode_update(update, self.model)
        self._learned_at[r] = time_s
        self._budget.spend(time_s, len(data))
        self.model = apply_update(self.model, update)
        self.serial = update.serial
        self.updates.append(update)
        if self.healer is not None:
            self.healer.take(self.model)
        for stats, value in ((self._cue_sum, cue), (self._cue_count, 1), (self._used, 0)):
            stats[r] = np.insert(stats[r][kept], position, value)
        return update


class _Budget:
    """The update traffic's token bucket as the learning keeps it (module docstring)."""

    def __init__(self) -> None:
        self.rate, self.depth = BUCKET
        self.tokens = self.depth
        self.time: float | None = None

    def _refill(self, time_s: float) -> None:
        if self.time is not None:
            self.tokens = min(self.depth, self.tokens + self.rate * max(time_s - self.time, 0))
        self.time = time_s

    def allows(self, time_s: float) -> bool:
        """Whether an update may be issued at ``time_s`` (the bucket is not in debt)."""
        self._refill(time_s)
        return self.tokens > 0

    def spend(self, time_s: float, size: int) -> None:
        """An update of ``size`` bytes issued at ``time_s``."""
        self._refill(time_s)
        self.tokens -= WIRE_FACTOR * size


def _block(seen: np.ndarray, x: np.ndarray, y: np.ndarray) -> int:
    """The texels per frame pixel of an area's read (``AreaTexels.read``'s seen, x, y), as
    the side of a block of texels that one pixel spans: 1 .. ``MAX_BLOCK``."""
    step = np.hypot(np.diff(x, axis=1), np.diff(y, axis=1))[seen[:, 1:] & seen[:, :-1]]
    if step.size == 0:
        return 1
    return int(np.clip(np.floor(1.0 / max(float(np.median(step)), 1e-6)), 1, MAX_BLOCK))


def _changed_only(layer: np.ndarray, reference: np.ndarray, block: int) -> np.ndarray:
    """(h, w, 3) uint8: where ``layer`` changed from ``reference``, the reference plus their
    difference averaged over ``block`` x ``block`` texels and rounded to ``DIFF_STEP``; the
    reference's texels elsewhere (the module docstring, capture)."""
    ref = reference.astype(np.float32)
    diff = layer.astype(np.float32) - ref
    changed = cv2.GaussianBlur(np.abs(diff).max(axis=2), (0, 0), CHANGE_SIGMA) > CHANGE_LEVELS
    grow = 2 * CHANGE_GROW + 1
    changed = cv2.dilate(changed.astype(np.uint8), np.ones((grow, grow), np.uint8)) > 0
    h, w = changed.shape
    padded = np.pad(diff, ((0, -h % block), (0, -w % block), (0, 0)), mode="edge")
    coarse = padded.reshape(padded.shape[0] // block, block, padded.shape[1] // block, block,
                            3).mean(axis=(1, 3))
    coarse = np.rint(coarse / DIFF_STEP) * DIFF_STEP
    coarse = np.repeat(np.repeat(coarse, block, axis=0), block, axis=1)[:h, :w]
    stepped = np.clip(np.rint(ref + coarse), 0, 255).astype(np.uint8)
    return np.where(changed[..., None], stepped, reference)


def can_learn(model: PersonModel) -> bool:
    """Whether a model can learn: it was loaded from its file (its sha256 names the base of
    the updates) and holds the regions of ``models.regions.REGIONS`` in that order (the
    cues are computed in that order)."""
    return len(model.sha256) == 64 and tuple(r.name for r in model.regions) == REGION_NAMES


def _bound(cross: np.ndarray) -> float:
    """A region's novelty bound from its templates' cross scores (k, k) (module docstring)."""
    k = len(cross)
    if k < 2:
        return MIN_NOVEL_PHI
    others = np.asarray(cross, np.float64) + np.diag(np.full(k, np.inf))
    return max(MIN_NOVEL_PHI, NOVEL_FACTOR * float(np.median(others.min(axis=1))))


def _yaw_deg(rotation: np.ndarray) -> float:
    """|yaw| of a pose, degrees: the model's +z (forward) turned about the camera's y."""
    forward = np.asarray(rotation, np.float64)[:, 2]
    return abs(float(np.degrees(np.arctan2(forward[0], forward[2]))))
