"""Hands in front of the face in the enrollment frames, found by a hand landmark model.

The ring test (``sender.clean``) compares a frame with the base texture, so it fails
when the base texture itself shows the occluder, and a skin-coloured hand that moves with
the face passes it. This module asks a model made for hands instead: MediaPipe's hand
tracker (palm detection, then 21 hand landmarks followed from frame to frame), whose
weights the ``mediapipe`` wheel carries (``hand_landmark_full.tflite`` and
``palm_detection_full.tflite`` in its ``modules`` folder: nothing is downloaded).

Per frame with face landmarks (``OccluderFinder.find``):

1. The face's crop: the 68 points' box grown by ``CROP_GROW`` of its size on every side
   (a hand over the face is within it; a small face's hand is seen larger by the model).
2. The hands in it: the tracker in video mode (its palm detector runs only when no hand is
   followed), at most two, each (21, 2) px in the frame.
3. The occluder's mask (H, W): each hand's convex hull grown by ``HAND_GROW`` of its size
   from its centre (the landmarks run along the fingers' middles, the hull misses their
   outer halves).
4. The verdict: the share of the face hull (the 68 points' convex hull) the mask covers
   (``Occlusion.face``), and the parts of the face (``sender.clean.PARTS``, each the
   convex hull of its points grown by ``PART_GROW``) it covers on more than
   ``PART_COVERED`` of their pixels (``Occlusion.parts``). A frame is occluded when the
   mask covers more than ``FACE_COVERED`` of the face or any part.

Every ``stride``-th frame with a face is examined (``OccluderScan``; ``STRIDE`` 1: every
one); a frame between two examined ones, a frame without a face too, takes the union of
their verdicts (a hand coming or going is counted occluded on both sides). The mask of a
frame is kept as its hands' points (``Occlusion.mask`` draws it), not as an image per frame.
``check_hand_model`` (``facewire check``) loads nothing but says whether the wheel holds
the weights (``WEIGHTS``). Why this detector and not the palm detector alone, the lite
model or BlazePose's hand points: measured in docs/DESIGN.md §7 ("Hands on the face").

The enrollment (``sender.enroll.build``) takes an occluded frame neither as the neutral
nor as a view of the base texture, and the regions (``sender.enroll.layers``) take
nothing from a frame whose part is covered, as with the ring test.
"""

from __future__ import annotations

import os
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.protocol.errors import FacewireError
from facewire.sender.clean import PARTS

CROP_GROW = 0.6  # of the face box's size, on every side
HAND_GROW = 0.15  # of the hand's hull, from its centre
PART_GROW = 0.3  # of each part's hull, from its centre
PART_COVERED = 0.2  # of a part's pixels covered: the part is occluded
FACE_COVERED = 0.05  # of the face hull covered: the frame is occluded
STRIDE = 1
WEIGHTS = ("palm_detection/palm_detection_full.tflite", "hand_landmark/hand_landmark_full.tflite")


class OccluderError(FacewireError, RuntimeError):
    """The hand model cannot be loaded (mediapipe missing: ``./install.sh`` installs it)."""


@dataclass(frozen=True)
class Occlusion:
    """One frame's verdict: the share of the face hull covered, the parts covered
    (``sender.clean.PARTS`` names), and the hands found ((21, 2) px each)."""

    face: float = 0.0
    parts: frozenset[str] = frozenset()
    hands: tuple[np.ndarray, ...] = field(default=(), compare=False)

    @property
    def occluded(self) -> bool:
        """Whether the frame is occluded (module docstring, 4)."""
        return self.face > FACE_COVERED or bool(self.parts)

    def mask(self, shape: tuple[int, ...]) -> np.ndarray:
        """(H, W) bool: the frame's occluder mask (module docstring, 3) in an image of
        ``shape``; empty for a frame not examined."""
        return hand_mask(shape, self.hands)

    def merged(self, other: Occlusion) -> Occlusion:
        """The union of two verdicts (a frame between two examined ones)."""
        return Occlusion(max(self.face, other.face), self.parts | other.parts)


def _hull_mask(shape: tuple[int, ...], points: np.ndarray, grow: float) -> np.ndarray:
    """(H, W) bool: the convex hull of (N, 2) ``points`` grown by ``grow`` from its centre."""
    centre = points.mean(axis=0)
    grown = (points - centre) * (1.0 + grow) + centre
    hull = cv2.convexHull(grown.astype(np.float32)).reshape(-1, 2)
    mask = np.zeros(shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.rint(hull).astype(np.int32)], 1)
    return mask > 0


def hand_mask(shape: tuple[int, ...], hands: Sequence[np.ndarray]) -> np.ndarray:
    """(H, W) bool: the hands' (21, 2) px hulls grown by ``HAND_GROW`` (module docstring, 3)."""
    mask = np.zeros(shape[:2], bool)
    for hand in hands:
        mask |= _hull_mask(shape, hand, HAND_GROW)
    return mask


def verdict(mask: np.ndarray, points: np.ndarray, hands: Sequence[np.ndarray] = ()
            ) -> Occlusion:
    """The verdict of an (H, W) bool occluder mask on the face of ``points`` (68, 2) px
    (module docstring, 4)."""
    face = _hull_mask(mask.shape, points, 0.0)
    share = float((mask & face).sum() / max(int(face.sum()), 1))
    covered = frozenset(name for name, idx in PARTS.items()
                        if (part := _hull_mask(mask.shape, points[idx], PART_GROW)).any()
                        and (mask & part).sum() > PART_COVERED * part.sum())
    return Occlusion(share, covered, tuple(hands))


def check_hand_model() -> str:
    """One line naming the hand model and its weights' files, as ``facewire check`` prints it.

    Raises:
        OccluderError: mediapipe is missing, or its wheel lacks the hand model's weights.
    """
    mp = load_mediapipe()
    folder = Path(mp.__file__).parent / "modules"
    missing = [w for w in WEIGHTS if not (folder / w).is_file()]
    if missing:
        raise OccluderError(f"{folder}: mediapipe {mp.__version__} lacks {', '.join(missing)}; "
                            "run ./install.sh")
    return f"hand model: mediapipe {mp.__version__} ({', '.join(WEIGHTS)})"


def load_mediapipe() -> Any:
    """The mediapipe module (``OccluderError`` naming the fix when it is missing)."""
    # its C++ log lines (glog) and protobuf 4's deprecation warning at every frame say
    # nothing to a user: kept quiet
    os.environ.setdefault("GLOG_minloglevel", "2")
    warnings.filterwarnings("ignore", message="SymbolDatabase.GetPrototype", category=UserWarning)
    try:
        import mediapipe as mp
    except ImportError as exc:  # the one optional import: say how to get it
        raise OccluderError(f"the hand model needs mediapipe ({exc}); run ./install.sh"
                            ) from None
    return mp


@contextmanager
def native_stderr_quiet() -> Iterator[None]:
    """File descriptor 2 sent to /dev/null for the block: TFLite's and absl's start-up lines
    (the XNNPACK delegate, the feedback manager), written there by C++ past Python's
    ``sys.stderr`` when the graph first runs or closes, would break a command's one-line
    messages."""
    sys.stderr.flush()
    saved = os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


class OccluderFinder:
    """MediaPipe's hand tracker over the face's crop of consecutive frames (module docstring).

    Raises:
        OccluderError: mediapipe is not installed.
    """

    def __init__(self) -> None:
        hands = load_mediapipe().solutions.hands
        with native_stderr_quiet():  # made and run once on a blank image: all it says, said
            self._hands: Any = hands.Hands(
                static_image_mode=False, max_num_hands=2, model_complexity=1,
                min_detection_confidence=0.5, min_tracking_confidence=0.5)
            self._hands.process(np.zeros((64, 64, 3), np.uint8))

    def close(self) -> None:
        """Free the model's graph."""
        with native_stderr_quiet():
            self._hands.close()

    def hands(self, image: np.ndarray, points: np.ndarray) -> list[np.ndarray]:
        """The hands found in the face's crop of ``image`` (H, W, 3) uint8 BGR, the face
        of ``points`` (68, 2) px: each (21, 2) float64 px in the frame."""
        low, high = points.min(axis=0), points.max(axis=0)
        grow = CROP_GROW * (high - low)
        h, w = image.shape[:2]
        x0, y0 = np.maximum(np.floor(low - grow).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(high + grow).astype(int), [w, h])
        if x1 - x0 < 8 or y1 - y0 < 8:
            return []
        crop = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_BGR2RGB)
        found = self._hands.process(crop)
        return [np.array([[p.x * (x1 - x0) + x0, p.y * (y1 - y0) + y0] for p in lm.landmark])
                for lm in found.multi_hand_landmarks or []]

    def find(self, image: np.ndarray, points: np.ndarray) -> Occlusion:
        """One frame's verdict (module docstring, 1-4)."""
        hands = self.hands(image, points)
        if not hands:
            return Occlusion()
        return verdict(hand_mask(image.shape, hands), points, hands)


class OccluderScan:
    """The verdicts of consecutive frames, fed one at a time (``see``): every
    ``stride``-th frame with a face is examined, the others take the union of their
    examined neighbours' (module docstring). ``finder``: the model to use (a new one by
    default, closed by ``verdicts``)."""

    def __init__(self, stride: int = STRIDE, finder: OccluderFinder | None = None) -> None:
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ValueError(f"stride: expected a positive frame count, got {stride!r}")
        self.stride = stride
        self._own = finder is None
        self._finder = OccluderFinder() if finder is None else finder
        self._found: dict[int, Occlusion] = {}
        self._count = self._faces = 0

    def see(self, image: np.ndarray, points: np.ndarray | None) -> None:
        """The next frame: (H, W, 3) uint8 BGR and its (68, 2) points, or None (no face)."""
        if points is not None:
            if self._faces % self.stride == 0:
                self._found[self._count] = self._finder.find(image, points)
            self._faces += 1
        self._count += 1

    def verdicts(self) -> list[Occlusion]:
        """One verdict per frame seen, in order."""
        if self._own:
            self._finder.close()
        return spread(self._found, self._count)


def spread(found: dict[int, Occlusion], count: int) -> list[Occlusion]:
    """(count) verdicts from those of the examined frames ``found`` (by index): an examined
    frame keeps its own, another takes the union of its examined neighbours'."""
    examined = sorted(found)
    out = []
    for k in range(count):
        if k in found:
            out.append(found[k])
            continue
        at = int(np.searchsorted(examined, k))
        near = [found[examined[j]] for j in (at - 1, at) if 0 <= j < len(examined)]
        merged = Occlusion()
        for other in near:
            merged = merged.merged(other)
        out.append(merged)
    return out
