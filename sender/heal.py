"""Healing: the base texture corrected during the session, shipped as texture patches.

The enrollment's texture holds what its few seconds of video showed: a hand its detector
missed, a side of the face never turned to the camera, a flush. During the session the
sender sees the face again and again; where clean views keep disagreeing with what the
model draws, or see clean what the enrollment saw badly (its confidence map,
``sender.enroll.confidence``), it corrects the texture and ships the correction as a
``models.patch.TexturePatch``, a model update of its own kind.

The healing grid. The texture is read at 1 / ``SCALE`` of its resolution (a face spans
fewer pixels in a camera frame than texels in the texture), over the UV box of the face's
landmark vertices grown by ``BOX_GROW`` (up by ``BOX_UP``, for the forehead): cells, each
``SCALE`` x ``SCALE`` texels, read from the frame like a region's layer (``sender.texels``:
the cell's surface point on the morphed, posed mesh, projected, read bilinearly).

A read. One frame in ``EVERY`` is read when it is clean (none for ``HAND_REST`` frames after a
hand was found on the face): a pose fitted and not just lost or
re-acquired, the head within ``MAX_YAW_DEG`` of frontal, the face box sharp (the learner's
test, ``sender.clean.sharpness``). A cell takes part when its normal faces the camera with
cos at least ``FRONTAL_COS``, no other cell of the box lies in front of it
(``sender.texels``' occlusion test: the neck below the chin reads the chin) and it lies
outside the regions that move (``MOVING``: the
eyeballs and eyelids, with the gaze, and the mouth's interior, with the jaw: their states
are the learning's). What the model draws there, E, is the base texture with the
regions composited at the frame's Q (``receiver.render``'s blend, at the grid's
resolution); the read's colour V is scaled per channel to E's exposure (the ratio of their
medians over the cells taking part whose confidence is at least ``TRUSTED``, clipped to
[0.5, 2]), and its difference V - E is kept. The last ``VIEWS`` reads are held, and a
correction is looked for after every ``LOOK_EVERY`` new ones.

A correction. Per cell seen in at least ``MIN_VIEWS`` held reads: the median difference
d (per channel) and the views' spread, the median absolute deviation of their luma
differences. The cell needs healing when the views agree (spread under ``SPREAD_LEVELS``)
and either disagree with the model (|luma d| smoothed by a Gaussian of ``SMOOTH`` cells
over ``DEPART_LEVELS``) or the model hardly saw it (confidence under ``LOW_CONFIDENCE``,
a texel no view saw or only at a grazing angle; on lp_d0's own model, built from clean
frames, 4 % of the cells the healing sees are under 90 of 255) and d is over
``NOISE_LEVELS``. d is smoothed over the seen cells by the same Gaussian
(the views' noise would bloat the patch's PNG by a third). The cells that need it, grown
by ``GROW`` cells and feathered, take their d; a tile of ``TILE`` x ``TILE`` cells is
patched when more than ``TILE_SHARE`` of its seen cells, and at least ``MIN_CELLS``, need
healing (a tile at the box's edge, seen in a few cells, is not patched for a few), the largest
disagreements first, at most ``MAX_TILES`` tiles and ``PATCH_BYTES`` of PNG a patch, none
patched within the last ``REPATCH_READS`` reads (the rest waits for the next, so the first
reaches the viewers soon), the correction's weight blurred by a Gaussian of ``TAPER`` / 3
cells and brought to zero over ``TAPER`` cells inside the chosen tiles' outer edges by a
smoothstep (faded over 3 cells and cut where the cells seen in enough reads ended, a healed
cheek showed its tile's rectangle: docs/DESIGN.md, "Texture patches"), and clipped to
``MAX_CHANGE``. The patch stores the
correction at ``STORE`` x ``STORE`` cells a pixel (scale ``SCALE * STORE`` texels: the
correction is smooth), and chosen tiles side by side in a row as one stored tile (one PNG's
header and one tile's fields, not several: a hand's tiles are mostly neighbours); its PNG
bytes are counted so. Before a patch
is issued, the held frames it is made of are
asked for hands (``sender.enroll.occluders``, MediaPipe's hand tracker: a hand that
moves with the face and agrees with itself would otherwise be painted in); a frame with a
hand on the face is dropped and the correction waits for clean ones. They are asked for the
person's outline too (``sender.enroll.silhouette``, MediaPipe's selfie segmentation): where
the fitted head is wider or taller than the real one, the enrollment left its texels to the
hole filling rather than take the room behind the person, and the reads there see the room
again (clean, agreeing, far from the model: a patch of sky on mediapipe_selfie's crown within
3 s), so a cell whose point lies within ``ROOM_PX`` of a pixel outside the person takes no
part in that read, and the correction is looked for again without it. The hand tracker is made
with the healer (MediaPipe's import and start, 0.8 s on this machine, mostly holding the GIL:
paid before a live stream's first frame, not by a frame mid-stream, whose sender it stalled
past the slots' ``MAX_LAG_S``). A patch is applied at
once to the learner's model; the held reads (differences against the old model) are then
forgotten.

The traffic's budget is the learner's (``sender.learn``: the transport's token bucket), which
patches and learned states share.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from facewire.models.archive import png_bytes
from facewire.models.geometry import Intrinsics
from facewire.models.modelfile import PersonModel
from facewire.models.patch import MAX_TILE_SIDE, TexturePatch, Tile, tile_diff
from facewire.models.rig import Rig
from facewire.models.texelgrid import texel_rect
from facewire.sender.enroll.occluders import OccluderFinder
from facewire.sender.enroll.silhouette import SilhouetteFinder
from facewire.sender.texels import AreaTexels, area_surface, welded_normals

SCALE = 8  # texels per healing cell, a side
TILE = 16  # cells per tile side (128 texels)
STORE = 2  # cells per stored difference pixel, a side (the correction is smooth)
EVERY = 3  # frames between reads
LOOK_EVERY = 2  # new reads before the healing looks for a correction again
HAND_REST = 25  # frames without reads after a hand was found on the face
VIEWS = 5  # reads held
MIN_VIEWS = 3  # reads a cell must be seen in
FRONTAL_COS = 0.6  # a cell's normal towards the camera, at least
TRUSTED = 128  # confidence (of 255) of the cells exposure is matched over
SPREAD_LEVELS = 10.0  # grey levels: the views agree under this spread
DEPART_LEVELS = 20.0  # grey levels: a disagreement with the model that counts
NOISE_LEVELS = 6.0  # grey levels: a low-confidence cell's difference that counts
LOW_CONFIDENCE = 10  # of 255
SMOOTH = 1.0  # cells, the Gaussian of the disagreement and of the correction
GROW = 2  # cells the needing cells are grown by
TAPER = 6  # cells over which the correction fades to zero at the chosen tiles' edges
TILE_SHARE = 0.2  # of a tile's seen cells needing healing, over which it is patched ...
MIN_CELLS = 32  # ... and at least this many (an eighth of a tile)
REPATCH_READS = 15  # reads before a patched tile may be patched again
MAX_TILES = 48  # tiles a patch (a patch holds at most models.patch.MAX_TILES)
PATCH_BYTES = 7400  # a patch's tiles stop at this many bytes of PNG: with its fields, nine
#                     1-KiB chunks at most, which the wire's three a 1.1 s bring in 2.2 s
MAX_CHANGE = 120.0  # grey levels a cell may change by in one patch
BOX_GROW = 0.25  # the landmarks' UV box grown by this of its size on each side ...
BOX_UP = 0.8  # ... and by this upwards (the forehead)
ROOM_PX = 1.5  # a cell this near a pixel outside the person may read it (bilinear: sqrt 2)
MOVING = ("eyeball_right", "eyeball_left", "eyelid_right", "eyelid_left", "mouth")
_LUMA = np.array([0.299, 0.587, 0.114], np.float32)


@dataclass(eq=False)
class _Read:
    """One held read: the frame (to ask for hands and the outline), its points, the cells'
    projections and the differences."""

    image: np.ndarray  # (H, W, 3) uint8 BGR
    points: np.ndarray  # (68, 2)
    x: np.ndarray  # (h, w) float32 px: the cells' points in the frame
    y: np.ndarray
    diff: np.ndarray  # (h, w, 3) float32, NaN where the cell took no part
    hand: bool | None = None  # a hand on the face (None: not asked yet)
    outlined: bool = False  # the cells outside the person taken out


def _median(stack: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The median over axis 0 of ``stack`` (V, ...) ignoring its NaNs, ``count`` (...) the
    values that are not NaN at each place (NaN sorts last): the mean of the sorted values
    (c - 1) // 2 and c // 2; 0 where there are none."""
    ordered = np.sort(stack, axis=0)
    top = stack.shape[0] - 1
    low = np.take_along_axis(ordered, np.clip((count - 1) // 2, 0, top)[None], axis=0)[0]
    high = np.take_along_axis(ordered, np.clip(count // 2, 0, top)[None], axis=0)[0]
    return np.where(count > 0, (low + high) / 2, 0.0)


class Healer:
    """Corrects the base texture from clean views (module docstring).

    Args:
        model: the session's model (loaded from its file).
        camera: the sender camera's intrinsics; rig: the model's rig.

    Attributes:
        reads: reads made; patches: patches made.
    """

    def __init__(self, model: PersonModel, camera: Intrinsics, rig: Rig) -> None:
        self.camera = camera
        height, width = model.texture.shape[:2]
        self.grid = (height // SCALE, width // SCALE)
        uv = model.mesh.uv[model.mesh.landmarks].astype(np.float64)
        low, high = uv.min(axis=0), uv.max(axis=0)
        size = high - low
        rect = (max(0.0, low[0] - BOX_GROW * size[0]), max(0.0, low[1] - BOX_GROW * size[1]),
                min(1.0, high[0] + BOX_GROW * size[0]), min(1.0, high[1] + BOX_UP * size[1]))
        triangles, normals = area_surface(model.mesh, rect, self.grid, welded_normals(model.mesh))
        self.area = AreaTexels(model.mesh, rig, rect, self.grid, triangles, normals)
        self.rows, self.cols = self.area.slices
        self.reads: deque[_Read] = deque(maxlen=VIEWS)
        self.read_count = 0
        self.patches = 0
        self._frames = 0
        self._rest_until = 0  # no read before this frame (a hand was found)
        self.fresh = 0  # reads since the last look for a correction
        self._finder: OccluderFinder | None = OccluderFinder()
        self._outline: SilhouetteFinder | None = SilhouetteFinder()
        self._patched: dict[tuple[int, int], int] = {}  # tile -> the read count it was patched at
        self.take(model)

    def take(self, model: PersonModel) -> None:
        """Hold ``model``'s texture and regions at the grid's resolution (a new version)."""
        self.model = model
        small = cv2.resize(model.texture, self.grid[::-1], interpolation=cv2.INTER_AREA)
        self.base = small[self.rows, self.cols].astype(np.float32)
        confidence = (np.full(model.texture.shape[:2], 255, np.uint8)
                      if model.confidence is None else model.confidence)
        self.confidence = cv2.resize(confidence, self.grid[::-1],
                                     interpolation=cv2.INTER_AREA)[self.rows, self.cols]
        self.parts: list[tuple[int, tuple[slice, slice], np.ndarray, np.ndarray]] = []
        moving = np.zeros(self.base.shape[:2], bool)
        for r, region in enumerate(model.regions):
            for part in region.parts():
                where = self._cells(part.uv_rect)
                if where is None:
                    continue
                (h, w), inner, outer = where
                layers = np.stack([cv2.resize(layer, (w, h), interpolation=cv2.INTER_AREA)
                                   for layer in part.layers]).astype(np.float32)
                mask = cv2.resize(part.mask, (w, h), interpolation=cv2.INTER_AREA)
                alpha = (np.asarray(region.opacity, np.float32)[:, None, None]
                         * mask.astype(np.float32) / 255.0)
                self.parts.append((r, outer, layers[:, *inner], alpha[:, *inner]))
                if region.name in MOVING:
                    moving[outer] |= alpha[:, *inner].max(axis=0) > 0
        self.moving = moving
        self.reads.clear()
        self.wanting = True  # the last correction looked for found tiles (none yet: unknown)

    def _cells(self, rect: tuple[float, float, float, float]
               ) -> tuple[tuple[int, int], tuple[slice, slice], tuple[slice, slice]] | None:
        """An area's cells: the (h, w) of its rectangle on the grid, and where it meets the
        healing box (slices into the area's grid image, slices into the box); None when
        they do not meet."""
        rows, cols = texel_rect(rect, self.grid)[1]
        r0, r1 = max(rows.start, self.rows.start), min(rows.stop, self.rows.stop)
        c0, c1 = max(cols.start, self.cols.start), min(cols.stop, self.cols.stop)
        if r1 <= r0 or c1 <= c0:
            return None
        inner = (slice(r0 - rows.start, r1 - rows.start), slice(c0 - cols.start, c1 - cols.start))
        outer = (slice(r0 - self.rows.start, r1 - self.rows.start),
                 slice(c0 - self.cols.start, c1 - self.cols.start))
        return (rows.stop - rows.start, cols.stop - cols.start), inner, outer

    def expected(self, q: np.ndarray) -> np.ndarray:
        """(h, w, 3) float32: what the model draws on the box at Q ``q`` (R,): the base
        with each region composited (``receiver.render``: B + a (L - B), Q interpolated)."""
        out = self.base.copy()
        for r, where, layers, alpha in self.parts:
            k = len(layers)
            value = float(np.clip(q[r], 0, k - 1)) if r < len(q) else 0.0
            i = min(int(np.floor(value)), k - 1)
            j, t = min(i + 1, k - 1), value - i
            layer = (1 - t) * layers[i] + t * layers[j]
            a = ((1 - t) * alpha[i] + t * alpha[j])[..., None]
            under = out[where]
            out[where] = under + a * (layer - under)
        return out

    def due(self, clean: bool) -> bool:
        """Whether this frame is read (one clean frame in ``EVERY``)."""
        self._frames += 1
        return clean and self._frames % EVERY == 0 and self._frames >= self._rest_until

    def read(self, image: np.ndarray, points: np.ndarray, rotation: np.ndarray,
             translation: np.ndarray, residuals: np.ndarray, q: np.ndarray) -> None:
        """Read one clean frame (module docstring, a read): hold its differences.

        Args:
            image: (H, W, 3) uint8 BGR; points: (68, 2) px.
            rotation: (3, 3); translation: (3,) mm; residuals: (9, 3) mm: the sent pose.
            q: (R,) the frame's Q per region (the classifier's).
        """
        colour, seen, x, y = self.area.read(self.camera, image, rotation, translation,
                                            residuals, occlusion=True)
        facing = (self.area.normals @ np.asarray(rotation, np.float32).T)[..., 2]
        ok = seen & (facing >= FRONTAL_COS) & ~self.moving
        expected = self.expected(q)
        trusted = ok & (self.confidence >= TRUSTED)
        if trusted.sum() < 50:
            return
        gain = np.median(expected[trusted], axis=0) / np.maximum(
            np.median(colour[trusted], axis=0), 1.0)
        diff = colour * np.clip(gain, 0.5, 2.0) - expected
        diff[~ok] = np.nan
        self.reads.append(_Read(image.copy(), np.asarray(points).copy(), x, y, diff))
        self.read_count += 1
        self.fresh += 1

    def correction(self, reads: list[_Read]) -> tuple[np.ndarray, list[tuple[int, int]]] | None:
        """The reads' correction: (h, w, 3) float32 d, feathered to zero outside the cells
        that need healing, and the tiles to patch (their first cells in the box), largest
        disagreement first; None when no tile needs it."""
        if len(reads) < MIN_VIEWS:
            return None
        self.wanting = False
        stack = np.stack([r.diff for r in reads])
        count = np.isfinite(stack[..., 0]).sum(axis=0)
        enough = count >= MIN_VIEWS
        if not enough.any():
            return None
        d = np.where(enough[..., None], _median(stack, count[..., None]), 0.0).astype(np.float32)
        luma = stack @ _LUMA
        spread = _median(np.abs(luma - _median(luma, count)), count)
        agree = enough & (spread < SPREAD_LEVELS)
        depart = cv2.GaussianBlur(np.abs(d @ _LUMA), (0, 0), SMOOTH)
        need = agree & ((depart > DEPART_LEVELS)
                        | ((self.confidence < LOW_CONFIDENCE) & (depart > NOISE_LEVELS)))
        if not need.any():
            return None
        depart = np.where(need, depart, 0.0)
        tiles = []
        h, w = need.shape
        for r in range(0, h, TILE):
            for c in range(0, w, TILE):
                seen = enough[r:r + TILE, c:c + TILE].sum()
                needing = need[r:r + TILE, c:c + TILE].sum()
                recent = self.read_count - self._patched.get((r, c), -REPATCH_READS)
                if needing >= MIN_CELLS and needing > TILE_SHARE * seen \
                        and recent >= REPATCH_READS:
                    tiles.append((float(depart[r:r + TILE, c:c + TILE].sum()), r, c))
        if not tiles:
            return None
        tiles.sort(reverse=True)
        chosen = [(r, c) for _, r, c in tiles[:MAX_TILES]]
        self.wanting = True
        inside = np.zeros(need.shape, np.uint8)
        for r, c in chosen:
            inside[r:r + TILE, c:c + TILE] = 1
        grow = 2 * GROW + 1
        grown = cv2.dilate(need.astype(np.uint8), np.ones((grow, grow), np.uint8))
        weight = np.minimum(cv2.GaussianBlur(grown.astype(np.float32), (0, 0), GROW / 2.0)
                            * 1.5, 1.0)
        # to zero at the chosen tiles' outer edge, so no tile's edge shows
        taper = cv2.distanceTransform(np.pad(inside, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
        ramp = np.clip(taper / TAPER, 0, 1)
        weight = cv2.GaussianBlur(np.where(enough, weight, 0.0).astype(np.float32), (0, 0),
                                  TAPER / 3) * ramp * ramp * (3 - 2 * ramp)
        # smoothed over the seen cells (a normalised Gaussian): the views' noise left out of
        # the patch, whose PNG it would bloat
        cover = cv2.GaussianBlur(enough.astype(np.float32), (0, 0), SMOOTH)
        d = cv2.GaussianBlur(d, (0, 0), SMOOTH) / np.maximum(cover, 1e-3)[..., None]
        d = np.clip(d, -MAX_CHANGE, MAX_CHANGE) * weight[..., None]
        return d, chosen

    def held(self) -> list[_Read]:
        """The held reads no hand was found in."""
        return [r for r in self.reads if not r.hand]

    def _hands(self, reads: list[_Read]) -> bool:
        """Whether any of ``reads``' frames has a hand on the face (each asked once)."""
        assert self._finder is not None, "the healer was closed"
        for r in reads:
            if r.hand is None:
                r.hand = self._finder.find(r.image, r.points).occluded
        if any(r.hand for r in reads):
            self._rest_until = self._frames + HAND_REST
            return True
        return False

    def _room(self, reads: list[_Read]) -> bool:
        """Take out of each of ``reads`` (each asked once) the cells that may read the room
        behind the person (module docstring); whether any cell was taken out."""
        assert self._outline is not None, "the healer was closed"
        taken = False
        for r in reads:
            if r.outlined:
                continue
            r.outlined = True
            person = self._outline.find(r.image, r.points)
            inside = cv2.distanceTransform(person.astype(np.uint8), cv2.DIST_L2,
                                           cv2.DIST_MASK_PRECISE)
            seen = np.isfinite(r.diff[..., 0])  # on the image: their projections are finite
            h, w = person.shape
            col = np.clip(np.rint(r.x[seen]), 0, w - 1).astype(np.intp)
            row = np.clip(np.rint(r.y[seen]), 0, h - 1).astype(np.intp)
            room = np.zeros_like(seen)
            room[seen] = inside[row, col] < ROOM_PX
            if room.any():
                r.diff[room] = np.nan
                taken = True
        return taken

    def patch(self, reads: list[_Read], base_sha256: str, serial: int
              ) -> TexturePatch | None:
        """The patch ``reads`` (``held``) make (module docstring, a correction), asked for
        hands and the person's outline; None when none is due or a hand was found (that
        read is then left out)."""
        found = self.correction(reads)
        if found is None or self._hands(reads):
            return None
        if self._room(reads):
            found = self.correction(reads)
            if found is None:
                return None
        d, where = found
        picked: list[tuple[int, int]] = []
        tiles: list[Tile] = []
        for r, c in where:
            picked.append((r, c))
            tiles = self._tiles(d, picked)
            if sum(len(png_bytes(t.diff)) for t in tiles) >= PATCH_BYTES:
                break
        for r, c in picked:
            self._patched[r, c] = self.read_count
        self.patches += 1
        return TexturePatch(base_sha256, serial, SCALE * STORE, tuple(tiles))

    def _tiles(self, d: np.ndarray, picked: list[tuple[int, int]]) -> list[Tile]:
        """The patch's tiles of correction ``d`` (h, w, 3) over the ``picked`` tiles (their
        first cells in the box): the picked tiles side by side in a row are one tile (fewer
        PNG headers and fields), ``STORE`` cells a stored pixel."""
        span = MAX_TILE_SIDE * STORE // TILE  # picked tiles a stored tile may join
        runs: list[tuple[int, int, int]] = []  # (row, column, tiles) in cells
        for r, c in sorted(picked):
            if runs and runs[-1][0] == r and runs[-1][1] + TILE * runs[-1][2] == c \
                    and runs[-1][2] < span:
                runs[-1] = (r, runs[-1][1], runs[-1][2] + 1)
            else:
                runs.append((r, c, 1))
        tiles = []
        for r, c, n in runs:
            h = (min(r + TILE, d.shape[0]) - r) // STORE
            w = (min(c + n * TILE, d.shape[1]) - c) // STORE
            if h == 0 or w == 0:
                continue
            cells = (slice(r, r + STORE * h), slice(c, c + STORE * w))
            base = cv2.resize(self.base[cells], (w, h), interpolation=cv2.INTER_AREA)
            target = cv2.resize(self.base[cells] + d[cells], (w, h),
                                interpolation=cv2.INTER_AREA)
            tiles.append(Tile(SCALE * (self.rows.start + r), SCALE * (self.cols.start + c),
                              tile_diff(target, base)))
        return tiles

    def close(self) -> None:
        """Free the hand tracker and the segmentation (a second call does nothing)."""
        if self._finder is not None:
            self._finder.close()
        if self._outline is not None:
            self._outline.close()
        self._finder = self._outline = None
