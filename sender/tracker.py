"""68-point face tracking: dlib's HOG detector to find a face, its shape predictor to follow it.

Per frame (converted to grayscale, uint8):

1. Acquire. With no face held, the HOG frontal-face detector runs on the whole frame
   (downscaled so that it is at most ``detect_width`` pixels wide; it finds faces from about
   80 px at the scale it runs) and the largest face wins. The shape predictor (Kazemi and
   Sullivan 2014; the 68-point iBUG model shipped with ``face_recognition_models``) places
   68 points in that box. No face found: "no face" for this frame.
2. Track. Otherwise the predictor runs in a box derived from the previous frame's points and
   the detector is skipped. The derived box imitates the detector's: with ``c`` the centroid
   of the 68 points and ``s`` their RMS distance from it, it is the square of side
   ``BOX_SCALE * s`` centred at ``c + BOX_OFFSET * s``. The constants are medians over 870
   HOG detections in 12 real clips (``../shared/data/video``, every 5th frame); there the
   derived box is off the detector's by 4 % of its side (median) in centre and in side, and
   the points predicted in it differ from those predicted in the detector's box by 0.5-0.8 %
   of the outer-eye distance (median), less than the detector box's own frame-to-frame
   jitter causes.
3. Check. The predictor returns 68 points whatever the box holds, so loss is tested:
   - every frame, cheaply: the face patch (the derived box resampled to 24x24) must
     correlate with the previous frame's (normalised cross-correlation >=
     ``min_similarity``; on faces tracked through the shared clips it stays above 0.65
     except while a hand or microphone crosses the face, down to 0.36; across a scene cut
     it was 0.26 and 0.01) and the box must not jump (by more than a quarter of its side,
     in centre or in side);
   - on such a failure, and every ``verify_every`` frames regardless (a slow slide off the
     face, onto a hand or a microphone, keeps the patch similar from frame to frame), the
     detector runs on the box's neighbourhood only (the box grown by a quarter of its side
     on each side, scaled so the box is 80 px: about 1.4 ms) with a lenient threshold
     (``verify_threshold``). If it finds the face the track goes on, restarted from the
     detector's box when that overlaps the derived box by less than ``reseat_iou``; if not,
     the face is lost and step 1 runs on the same frame.
4. Switch. Every ``search_every`` frames the whole frame is searched for a face at least
   ``SWITCH_RATIO`` times the tracked face's side (at the scale where such a face is 80 px,
   so a large tracked face makes the search cheap); the largest such face replaces the
   tracked one, so a background face that happened to be the only one visible when the
   track started does not keep the camera's main subject from being tracked.

Identity. Given the model's person (``sender.identity.Person``), the tracker follows that
person and nobody else:

- acquiring, it takes the largest face whose descriptor is the person's, trying the faces
  the detector found from the largest down; none is: "no face" (the person is absent). A
  face found not to be the person (a stranger) is not identified again for
  ``stranger_every`` frames while a detection overlaps its box (IoU >= ``STRANGER_IOU``;
  the box follows it): each check is a descriptor (``sender.identity``, "Cost"), and
  without this memory a frame with strangers and no person would pay one per stranger. A
  near miss (a distance under ``NEAR_MISS``, dlib's pairwise threshold: the person
  turning back into view or blurred by motion, more often than another person) is tried
  again after ``NEAR_RETRY`` frames: on openface_multi_face the man at the back came back
  at 0.53-0.57 and matched a frame or two later, and a 10-frame wait after each near miss
  had kept him out for up to 1.3 s;
- tracking, the face's descriptor is checked again when the track is restarted from the
  detector's box (the verification reseated it: what the box holds changed, e.g. a face
  crossed in front) and every ``identify_every`` frames (a slow slide from one face to
  another, which the cheap checks of step 3 do not catch if the faces touch; 1800, a
  minute at 30 Hz: a descriptor's 100 ms of CPU spread over the frames of that minute is
  0.06 ms a frame, 1 % of the sender's frame); not the person: the track is dropped, the
  face becomes a stranger, and step 1 runs on the frame;
- step 4 never runs: a larger face is another person.

The person's return is found by step 1, which runs on every frame without a track (as
without identity): the delay is at most ``stranger_every`` frames when the person comes
back where a stranger's box was, else none.

Answers that come later. A check is asked (``Person.submit``) and its distance read
(``Person.poll``) on the same frame when the person computes descriptors in this thread
(files: the outcome above, the same on every run). A person made ``apart``
(``sender.identity``: a live stream) answers frames later, the frames going on meanwhile;
until then:

- acquiring, a face whose check is out is pending: no face is said for it, its box
  follows the detections (IoU >= ``STRANGER_IOU``, as a stranger's) and no second check is
  asked for it; the answer, when in, makes it the person's (the track starts on that
  frame's detection, ``acquired``) or a stranger. A pending face the detector no longer
  finds is forgotten with its answer;
- tracking, the periodic check lets the track go on while it is out (a slow slide is
  rare; a stranger would drive the stream until the answer, frames later); a reseated
  track's check is stronger: no face is said until the answer says the person (that frame
  is ``acquired``: the pose is fitted afresh), so a face that crossed in front never drives
  the stream.

Cost on 640x480 (openface_default.wmv, one core of the shared 2-core test machine, medians
of runs that differ by +-20 %): tracked frame 1.6-2.3 ms, of which the predictor alone is
1.3-1.8 ms; the neighbourhood check +1.4 ms; full-frame detection 20.5 ms
(5.8 ms at half scale, which misses faces under about 160 px, e.g. every face in
hamilton_short.mp4, hence ``detect_width=640``); a search for a larger face behind a
215-px face 2.7 ms.

Predictor memory. The loaded 68-point predictor is about 70 MB resident (as 15 cascades of
500 regression trees of depth 4 would be, each leaf a separately allocated 68 x 2 float
vector), and one prediction reads one leaf of each of its 7,500 trees: some 4 MB scattered
over the whole model, so the predictor is bound by memory latency, cache and TLB misses,
more than by arithmetic (1.2 ms on a quiet core, 2-3 ms of CPU time while other processes
share the cache). The model is therefore loaded once per process and file
(``_load_predictor``; trackers share it, prediction does not change it) and, on Linux 6.1
and later, the memory it was loaded into is backed by 2 MB pages
(``madvise(MADV_COLLAPSE)``, best effort, about 0.4 s once): one TLB entry then covers 2 MB
of trees instead of 4 kB. Measured on the shared 2-core machine under load, CPU time of the
sender's track stage per tracked frame (openface_default.wmv, medians of 4 alternating
runs): 3.66 ms with 4 kB pages, 2.97 ms with 2 MB pages. Where the kernel refuses (older
kernels, other systems) nothing changes but the speed; ``LandmarkTracker.huge_page_bytes``
says how much was backed.

Image coordinates: pixels, x right, y down, the centre of the top-left pixel at (0, 0). The
predictor's points are whole pixels (dlib rounds them). Boxes are ``(left, top, right,
bottom)``, dlib's inclusive convention (width = right - left + 1).

Threads: dlib runs this single-threaded; nothing here uses BLAS.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import dlib
import numpy as np

from facewire.models.landmarks import N_LANDMARKS

if TYPE_CHECKING:  # sender.identity imports this module
    from facewire.sender.identity import Person

PREDICTOR_FILE = "shape_predictor_68_face_landmarks.dat"

BOX_OFFSET = np.array([-0.007, -0.134], dtype=np.float32)
BOX_SCALE = 2.764
PATCH_SIZE = 24
VERIFY_SIDE = 80.0
VERIFY_MARGIN = 0.25
MAX_JUMP = 0.25
SWITCH_RATIO = 1.25
STRANGER_IOU = 0.5
NEAR_MISS = 0.6  # a stranger this near the person (dlib's pairwise threshold) is retried soon
NEAR_RETRY = 2  # frames

Box = tuple[int, int, int, int]

_MADV_COLLAPSE = 25  # linux/mman.h, Linux 6.1
_HUGE_PAGE = 2 << 20
# Loaded predictors, shared by every tracker of the process: (path, size, mtime) ->
# (predictor, bytes of its memory backed by huge pages).
_PREDICTORS: dict[tuple[str, int, int], tuple[dlib.shape_predictor, int]] = {}
_PREDICTORS_LOCK = threading.Lock()
# dlib's HOG face detector, one per thread: making one takes 1-3 s, and a detector keeps its
# image pyramid between calls, so two threads may not share one.
_DETECTORS = threading.local()


def predictor_path() -> Path:
    """The installed 68-point dlib model file (from ``face_recognition_models``).

    Found without importing that package, whose ``__init__`` imports ``pkg_resources``.
    """
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("face_recognition_models (ships the dlib model) is not installed")
    path = Path(spec.submodule_search_locations[0]) / "models" / PREDICTOR_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: dlib 68-point shape predictor not found")
    return path


@dataclass(frozen=True, eq=False)
class TrackResult:
    """One frame's tracking outcome.

    Attributes:
        points: (68, 2) float32 landmarks in pixels (iBUG order), or None when no face.
        box: the box the points were predicted in, ``(left, top, right, bottom)`` inclusive;
            None when no face.
        detected: the full-frame detector ran on this frame (to acquire a face, or to look
            for a larger one).
        verified: the detector ran on the tracked face's neighbourhood on this frame.
        acquired: the points are of a face the detector found on this frame rather than the
            one followed from the previous frame: the first face, a face found again after
            the tracked one was lost (possibly another person, without identity), or a
            switch to a larger face.
        identified: an identity check was asked on this frame: a face descriptor computed
            here, or its chip handed to the identity process (module docstring, "Identity").
    """

    points: np.ndarray | None
    box: Box | None
    detected: bool
    verified: bool
    acquired: bool = False
    identified: bool = False


def box_from_points(points: np.ndarray) -> Box:
    """The detector-like box of a 68-point shape (see the module docstring).

    Args:
        points: (68, 2) float32 landmarks, pixels.

    Returns:
        ``(left, top, right, bottom)``, inclusive, square.
    """
    n = np.float32(len(points))
    c = np.add.reduce(points, axis=0) / n  # float32 throughout, as points.mean(axis=0)
    d = points - c
    s = float(np.sqrt(np.add.reduce(np.add.reduce(d * d, axis=1)) / n))
    cx, cy = (c + BOX_OFFSET * s).tolist()
    side = max(round(BOX_SCALE * s), 1)
    left = round(cx - (side - 1) / 2)
    top = round(cy - (side - 1) / 2)
    return (left, top, left + side - 1, top + side - 1)


def _side(box: Box) -> int:
    """Width of a square box."""
    return box[2] - box[0] + 1


def box_iou(a: Box, b: Box) -> float:
    """Intersection over union of two inclusive boxes."""
    w = min(a[2], b[2]) - max(a[0], b[0]) + 1
    h = min(a[3], b[3]) - max(a[1], b[1]) + 1
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    area = (a[2] - a[0] + 1) * (a[3] - a[1] + 1) + (b[2] - b[0] + 1) * (b[3] - b[1] + 1)
    return inter / (area - inter)


def _scaled_box(r: dlib.rectangle, scale: float, x0: int, y0: int) -> Box:
    """A box found in an image resampled by ``scale`` from the origin (x0, y0), in frame pixels."""

    def back(u: int) -> float:
        return (u + 0.5) / scale - 0.5

    return (
        round(x0 + back(r.left())),
        round(y0 + back(r.top())),
        round(x0 + back(r.right())),
        round(y0 + back(r.bottom())),
    )


def _patch(gray: np.ndarray, box: Box) -> np.ndarray | None:
    """The box's pixels resampled to PATCH_SIZE^2, zero-mean, unit-norm; None if empty or flat.

    Rows and columns are first decimated to about twice the patch size (cheaper than
    averaging every pixel of a large face; consecutive frames correlate about as well).
    """
    h, w = gray.shape
    x0, y0 = max(box[0], 0), max(box[1], 0)
    x1, y1 = min(box[2] + 1, w), min(box[3] + 1, h)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return None
    step = max(_side(box) // (2 * PATCH_SIZE), 1)
    region = np.ascontiguousarray(gray[y0:y1:step, x0:x1:step])
    p = cv2.resize(region, (PATCH_SIZE, PATCH_SIZE), interpolation=cv2.INTER_AREA)
    v = p.astype(np.float32).ravel()
    v -= v.mean()
    norm = float(np.linalg.norm(v))
    return v / norm if norm > 1e-3 else None


def _jumped(a: Box, b: Box) -> bool:
    """Whether box ``b`` moved or resized too much from ``a`` for one frame of real motion."""
    sa, sb = _side(a), _side(b)
    shift = max(abs(a[0] + a[2] - b[0] - b[2]), abs(a[1] + a[3] - b[1] - b[3])) / 2
    return shift > MAX_JUMP * sa or abs(sb - sa) > MAX_JUMP * sa


class LandmarkTracker:
    """Track the 68 iBUG points of one face through a video: the largest when acquired, or,
    given a person, that person's only (module docstring, "Identity").

    Not thread-safe; one instance per video stream. See the module docstring for the method.
    Trackers of one process share the loaded shape predictor (read-only when predicting),
    and the trackers used in one thread share that thread's face detector.

    Attributes:
        huge_page_bytes: bytes of the predictor's memory backed by 2 MB pages when it was
            loaded (module docstring, "Predictor memory"); 0 where the system refused.
    """

    def __init__(
        self,
        predictor: str | os.PathLike | None = None,
        *,
        detect_width: int = 640,
        verify_every: int = 5,
        search_every: int = 30,
        min_similarity: float = 0.5,
        verify_threshold: float = -0.5,
        reseat_iou: float = 0.5,
        person: Person | None = None,
        identify_every: int = 1800,
        stranger_every: int = 10,
    ) -> None:
        """Load the models.

        Args:
            predictor: the dlib 68-point ``.dat`` file; the installed one when None.
            detect_width: frames wider than this are downscaled for full-frame detection
                (the HOG detector finds faces from about 80 px at the scale it runs).
            verify_every: check the tracked face with the detector at least every this many
                frames (>= 1).
            search_every: look for a face larger than the tracked one every this many
                frames (>= 1).
            min_similarity: lowest normalised cross-correlation of consecutive face patches
                accepted without a check, in [-1, 1].
            verify_threshold: HOG score above which a check finds the face (the detector's
                own threshold is 0; a tracked face is given some slack).
            reseat_iou: after a successful check, restart from the detector's box when it
                overlaps the tracked box by less than this, in [0, 1].
            person: follow only this person (``sender.identity.Person``), or None: the
                largest face.
            identify_every: with a person, check the tracked face's identity at least every
                this many frames (>= 1).
            stranger_every: with a person, identify a face found not to be theirs again
                after this many frames at the earliest (>= 1).
        """
        if detect_width < 80:
            raise ValueError(f"detect_width: expected >= 80 pixels, got {detect_width}")
        if verify_every < 1:
            raise ValueError(f"verify_every: expected >= 1, got {verify_every}")
        if search_every < 1:
            raise ValueError(f"search_every: expected >= 1, got {search_every}")
        if not -1.0 <= min_similarity <= 1.0:
            raise ValueError(f"min_similarity: expected a value in [-1, 1], got {min_similarity}")
        if not 0.0 <= reseat_iou <= 1.0:
            raise ValueError(f"reseat_iou: expected a value in [0, 1], got {reseat_iou}")
        if identify_every < 1 or stranger_every < 1:
            raise ValueError(f"identify_every, stranger_every: expected >= 1, got "
                             f"{identify_every}, {stranger_every}")
        path = Path(predictor) if predictor is not None else predictor_path()
        if not path.is_file():
            raise FileNotFoundError(f"{path}: shape predictor file not found")
        try:
            self._predictor, self.huge_page_bytes = _load_predictor(path)
        except RuntimeError as e:
            raise ValueError(f"{path}: not a dlib shape predictor ({e})") from e
        probe = self._predictor(np.zeros((32, 32), np.uint8), dlib.rectangle(0, 0, 31, 31))
        if probe.num_parts != N_LANDMARKS:
            raise ValueError(f"{path}: predicts {probe.num_parts} points, expected {N_LANDMARKS}")
        _detector()  # made now, so that the first frame does not pay for it
        self._detect_width = detect_width
        self._verify_every = verify_every
        self._search_every = search_every
        self._min_similarity = min_similarity
        self._verify_threshold = verify_threshold
        self._reseat_iou = reseat_iou
        self.person = person
        self._identify_every = identify_every
        self._stranger_every = stranger_every
        self.reset()

    def reset(self) -> None:
        """Forget the tracked face and the strangers; the next frame runs the full detector."""
        self._drop()
        self._frame = 0  # frames seen since the reset
        # (box, the frame it was identified on, frames to wait before identifying it again)
        self._strangers: list[tuple[Box, int, int]] = []
        # faces whose check is out while acquiring: (box, the check's ticket)
        self._pending: list[tuple[Box, int]] = []
        self._answers: dict[int, float] = {}  # checks answered and not yet used, by ticket

    def _drop(self) -> None:
        """Forget the tracked face."""
        self._since_identify = 0
        self._check: int | None = None  # the ticket of the tracked face's check, if out
        self._unsure = False  # the track was reseated and its check is out: no face said
        self._box: Box | None = None  # the box of the last frame's points
        self._next: Box | None = None  # the box derived from them: where to look next
        self._patch: np.ndarray | None = None  # the face patch in ``_next`` on the last frame
        self._since_check = 0
        self._since_search = 0

    def track(self, frame: np.ndarray, image: np.ndarray | None = None) -> TrackResult:
        """Find the 68 points in the next frame of the stream.

        Args:
            frame: (H, W, 3) uint8 BGR or (H, W) uint8 grayscale image.
            image: the same frame in colour, (H, W, 3) uint8 BGR, for the identity checks
                when ``frame`` is grey (``frame`` itself when None).

        Returns:
            The points (or None: no face) and what ran to get them.
        """
        gray = _gray(frame)
        colour = frame if image is None else image
        self._frame += 1
        if self._box is None or self._next is None:
            return self._acquire(gray, colour, verified=False)
        last_box, last_patch = self._box, self._patch
        box = self._next
        points = self._follow(gray, box)
        self._since_check += 1
        self._since_search += 1
        suspicious = (
            self._patch is None
            or last_patch is None
            or float(self._patch @ last_patch) < self._min_similarity
            or _jumped(last_box, box)
        )
        verified = suspicious or self._since_check >= self._verify_every
        reseated = False
        if verified:
            found = self._verify(gray, box)
            if found is None:
                return self._acquire(gray, colour, verified=True)
            self._since_check = 0
            if box_iou(found, box) < self._reseat_iou:
                box, reseated = found, True
                points = self._follow(gray, box)
        if self.person is not None:
            return self._hold(gray, colour, points, box, verified, reseated)
        detected = self._since_search >= self._search_every
        larger = None
        if detected:
            self._since_search = 0
            larger = self._find_larger(gray, box)
            if larger is not None:
                box = larger
                points = self._follow(gray, box)
        return TrackResult(points=points, box=box, detected=detected, verified=verified,
                           acquired=larger is not None)

    def faces(self, frame: np.ndarray) -> list[Box]:
        """Every face the full-frame detector finds in a frame, as acquisition runs it; the
        track is not touched.

        Args:
            frame: (H, W, 3) uint8 BGR or (H, W) uint8 grayscale image.
        """
        gray = _gray(frame)
        return self._detect(gray, min(1.0, self._detect_width / gray.shape[1]))

    def points_in(self, frame: np.ndarray, box: Box) -> np.ndarray:
        """The (68, 2) float32 points the predictor places in ``box`` of a BGR or grey
        frame; the track is not touched."""
        shape = self._predictor(_gray(frame), dlib.rectangle(*box))
        return np.array([(p.x, p.y) for p in shape.parts()], dtype=np.float32)

    def _follow(self, gray: np.ndarray, box: Box) -> np.ndarray:
        """Predict the (68, 2) float32 points in ``box`` and hold the face for the next frame."""
        points = self.points_in(gray, box)
        self._box = box
        self._next = box_from_points(points)
        self._patch = _patch(gray, self._next)
        return points

    def _detect(self, gray: np.ndarray, scale: float) -> list[Box]:
        """Faces found by the detector in the whole frame resampled by ``scale`` (<= 1)."""
        small = gray
        if scale < 1.0:
            size = (max(round(gray.shape[1] * scale), 1), max(round(gray.shape[0] * scale), 1))
            small = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        return [_scaled_box(r, scale, 0, 0) for r in _detector()(small)]

    def _acquire(self, gray: np.ndarray, colour: np.ndarray, verified: bool) -> TrackResult:
        """Full-frame detection; start a track on the largest face (the largest of the
        person's, given one), or report no face."""
        self._drop()
        faces = self._detect(gray, min(1.0, self._detect_width / gray.shape[1]))
        if not faces:
            self._strangers, self._pending, self._answers = [], [], {}
            return TrackResult(points=None, box=None, detected=True, verified=verified)
        if self.person is None:
            box = max(faces, key=_side)
            return TrackResult(points=self._follow(gray, box), box=box, detected=True,
                               verified=verified, acquired=True)
        strangers: list[tuple[Box, int, int]] = []  # those seen on this frame, boxes moved
        pending: list[tuple[Box, int]] = []  # likewise
        identified = False
        for box in sorted(faces, key=_side, reverse=True):
            known = max(self._strangers, key=lambda s: box_iou(s[0], box), default=None)
            if known is not None and box_iou(known[0], box) >= STRANGER_IOU \
                    and self._frame - known[1] < known[2]:
                strangers.append((box, known[1], known[2]))
                continue
            asked = max(self._pending, key=lambda p: box_iou(p[0], box), default=None)
            points: np.ndarray | None = None
            if asked is not None and box_iou(asked[0], box) >= STRANGER_IOU:
                ticket = asked[1]
            else:
                points = self._follow(gray, box)
                ticket = self._ask(colour, points)
                identified = True
            distance = self._answer(ticket)
            if distance is None:
                pending.append((box, ticket))
            elif distance < self.person.threshold:
                if points is None:
                    points = self._follow(gray, box)
                self._strangers, self._pending = strangers, []
                self._let_go()
                return TrackResult(points=points, box=box, detected=True, verified=verified,
                                   acquired=True, identified=identified)
            else:
                strangers.append((box, self._frame, self._wait(distance)))
            self._drop()
        self._strangers, self._pending = strangers, pending
        self._let_go()
        return TrackResult(points=None, box=None, detected=True, verified=verified,
                           identified=identified)

    def _hold(self, gray: np.ndarray, colour: np.ndarray, points: np.ndarray, box: Box,
              verified: bool, reseated: bool) -> TrackResult:
        """The tracked face's identity on this frame: checked when reseated or due, the
        track dropped (and acquisition run) when the answer is a stranger, no face said
        while a reseated track's check is out."""
        assert self.person is not None
        self._since_identify += 1
        identified = reseated or (self._check is None
                                  and self._since_identify >= self._identify_every)
        if identified:
            self._check = self._ask(colour, points)
        confirmed = False
        if self._check is not None:
            distance = self._answer(self._check)
            if distance is not None and distance >= self.person.threshold:
                self._strangers.append((box, self._frame, self._wait(distance)))
                found_again = self._acquire(gray, colour, verified=verified)
                return TrackResult(found_again.points, found_again.box, True, verified,
                                   found_again.acquired, identified=True)
            if distance is not None:
                self._check = None
                confirmed, self._unsure = self._unsure, False
            elif reseated:
                self._unsure = True
            self._let_go()
        if self._unsure:
            return TrackResult(points=None, box=None, detected=False, verified=verified,
                               identified=identified)
        return TrackResult(points=points, box=box, detected=False, verified=verified,
                           acquired=confirmed, identified=identified)

    def _ask(self, colour: np.ndarray, points: np.ndarray) -> int:
        """Check the face of these points against the person (a descriptor: about 100 ms of
        CPU, here or in the identity process); the check's ticket."""
        assert self.person is not None
        self._since_identify = 0
        return self.person.submit(colour, points)

    def _answer(self, ticket: int) -> float | None:
        """The distance a check found (the person's when under ``person.threshold``), or
        None while it is out."""
        assert self.person is not None
        self._answers.update(self.person.poll())
        return self._answers.pop(ticket, None)

    def _let_go(self) -> None:
        """Forget the answers to checks no longer wanted (faces gone, a track's earlier
        check replaced)."""
        wanted = {t for _, t in self._pending} | {self._check}
        self._answers = {t: d for t, d in self._answers.items() if t in wanted}

    def _wait(self, distance: float) -> int:
        """Frames before a stranger at this distance is identified again."""
        return NEAR_RETRY if distance < NEAR_MISS else self._stranger_every

    def _find_larger(self, gray: np.ndarray, box: Box) -> Box | None:
        """The largest other face at least SWITCH_RATIO times the tracked one's side, or None.

        The frame is downscaled so that such a face is still 80 px, the detector's smallest:
        the larger the tracked face, the cheaper the search.
        """
        least = SWITCH_RATIO * _side(box)
        scale = min(1.0, self._detect_width / gray.shape[1], VERIFY_SIDE / least)
        faces = [f for f in self._detect(gray, scale)
                 if _side(f) >= least and box_iou(f, box) < 0.3]
        return max(faces, key=_side) if faces else None

    def _verify(self, gray: np.ndarray, box: Box) -> Box | None:
        """Run the detector near ``box``; the face overlapping it most, or None."""
        h, w = gray.shape
        side = _side(box)
        pad = round(VERIFY_MARGIN * side)
        x0, y0 = max(box[0] - pad, 0), max(box[1] - pad, 0)
        x1, y1 = min(box[2] + pad + 1, w), min(box[3] + pad + 1, h)
        if x1 - x0 < side // 2 or y1 - y0 < side // 2:
            return None
        scale = VERIFY_SIDE / side
        size = (max(round((x1 - x0) * scale), 1), max(round((y1 - y0) * scale), 1))
        interp = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
        roi = cv2.resize(gray[y0:y1, x0:x1], size, interpolation=interp)
        faces, _, _ = _detector().run(roi, 0, self._verify_threshold)
        best: Box | None = None
        best_iou = 0.0
        for r in faces:
            found = _scaled_box(r, scale, x0, y0)
            overlap = box_iou(found, box)
            if overlap > best_iou:
                best, best_iou = found, overlap
        return best


def _detector() -> dlib.fhog_object_detector:
    """The calling thread's HOG face detector, made on its first use in that thread."""
    detector = getattr(_DETECTORS, "detector", None)
    if detector is None:
        detector = _DETECTORS.detector = dlib.get_frontal_face_detector()
    return detector


def _load_predictor(path: Path) -> tuple[dlib.shape_predictor, int]:
    """The shape predictor in ``path``, loaded once per process (module docstring, "Predictor
    memory"), and the bytes of its memory backed by 2 MB pages.

    Raises:
        RuntimeError: dlib cannot read the file.
    """
    stat = path.stat()
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    with _PREDICTORS_LOCK:
        loaded = _PREDICTORS.get(key)
        if loaded is None:
            before = _anonymous_memory()
            predictor = dlib.shape_predictor(str(path))
            loaded = predictor, _collapse_into_huge_pages(before)
            _PREDICTORS[key] = loaded
    return loaded


def _anonymous_memory() -> dict[int, tuple[int, bool]]:
    """start -> (end, is the heap) of this process's writable anonymous mappings, the heap
    included, from ``/proc/self/maps`` (Linux); {} where there is no such file."""
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return {}
    ranges = {}
    for line in maps.splitlines():
        fields = line.split()
        name = fields[5] if len(fields) > 5 else ""
        if len(fields) < 5 or "w" not in fields[1] or name not in ("", "[heap]"):
            continue
        start, end = (int(v, 16) for v in fields[0].split("-"))
        ranges[start] = (end, name == "[heap]")
    return ranges


def _collapse_into_huge_pages(before: dict[int, tuple[int, bool]]) -> int:
    """Back the memory the predictor was loaded into with 2 MB pages
    (``madvise(MADV_COLLAPSE)``): the heap (malloc may have placed trees in its free chunks)
    and the anonymous mappings made or grown since ``before`` (``_anonymous_memory``; a
    thread's malloc arena). Returns the bytes backed, 0 where the system refuses."""
    try:
        madvise = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return 0
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    madvise.restype = ctypes.c_int
    backed = 0
    for start, (end, heap) in _anonymous_memory().items():
        if not heap:  # a mapping that grew: its new part
            start = before.get(start, (start, False))[0]
        lo = -(-start // _HUGE_PAGE) * _HUGE_PAGE
        hi = end // _HUGE_PAGE * _HUGE_PAGE
        if hi > lo and madvise(lo, hi - lo, _MADV_COLLAPSE) == 0:
            backed += hi - lo
    return backed


def _gray(frame: np.ndarray) -> np.ndarray:
    """A C-contiguous (H, W) uint8 grayscale view or conversion of a BGR or gray frame."""
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8:
        kind = frame.dtype if isinstance(frame, np.ndarray) else type(frame).__name__
        raise ValueError(f"frame: expected a uint8 numpy array, got {kind}")
    if frame.ndim == 3 and frame.shape[2] == 3:
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    elif frame.ndim == 2:
        gray = np.ascontiguousarray(frame)
    else:
        raise ValueError(f"frame: expected shape (H, W, 3) BGR or (H, W) gray, got {frame.shape}")
    if gray.shape[0] < 16 or gray.shape[1] < 16:
        raise ValueError(f"frame: {gray.shape[1]}x{gray.shape[0]} is too small to hold a face")
    return gray

