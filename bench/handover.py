"""A reproduction: a real hand held over the mouth and cheek of a talking clip for most of its
enrollment frames, the later frames clean.

The hand (``HANDS``) is cut from one real frame of a clip where a hand is seen in front of
the chest: ``back``, the back of the man's left hand lying over his other wrist in
``latentsync_demo2.mp4`` frame 210 (against his black sweater; sharp, 300 px long), or
``raised``, the woman's right hand raised, fingers curled, in ``mediapipe_selfie.mp4``
frame 178 (against her white top and yellow jacket; small, 60 px, and motion-blurred: laid
on a face it is a soft hand, scaled up). Cutting (``cut_hand``): MediaPipe's hand
landmarker (the model its wheel carries) gives the hand's 21 points; GrabCut, started from
them, draws its outline: definitely the hand along the bones (wrist to each knuckle, along
each finger: 3.5 % of the hand's length wide) and in the palm's polygon (points 0, 1, 5, 9,
13, 17); probably the hand in its shape (the bones drawn ``FINGER`` of its length wide, the
palm, and the forearm's strip: from the wrist away from the middle knuckle, ``FOREARM``
hand lengths long, 1.1 palms wide); probably not in the rest of the points' convex hull
grown by twice ``HULL_GROW`` of the hand's length; certainly not beyond. What GrabCut calls
the hand is kept within the shape grown by ``HULL_GROW`` (a hand lying on another, skin on
skin, is told apart by its shape, not its colour), its largest connected piece, its edge
feathered over ``FEATHER_PX`` source pixels; the forearm fades out over its far half (its
cut end never shows as an edge). The hand keeps its own pixels: its shading, its hair, its
edges.

Laying it on the face (``lay_hand``), per frame, from the sender's tracker's 68 points of
the clean frame:

- scale: the palm's length (wrist 0 to middle knuckle 9) becomes the hand's
  ``HANDS`` ratio of the outer eye distance (36-45): 1.0 for ``back``, as a real palm
  (about 95 mm) to real eye corners (about 95 mm); 0.7 for ``raised``, whose curled
  fingers reach far beyond its palm;
- rotation: the hand's axis (wrist to middle knuckle) points up across the face towards
  the person's right cheek, ``TILT_DEG`` above the eye line, the wrist below the other
  cheek, rolling with the face (the eye line's angle);
- place: the palm's centre (points 0, 5, 9, 13, 17) over the point ``CHEEK`` of the way
  from the mouth's centre (48-67) to the person's left cheek (point 13), ``DROP`` of the
  eye distance down the face, so the palm covers the mouth and the fingers the cheek and
  the side of the nose;
- its own motion: a slow sway, ``SWAY_DEG`` of rotation, ``SWAY_SHIFT`` of the eye distance
  in x and y, ``SWAY_SCALE`` of scale, at incommensurate periods (``SWAY_PERIODS_S``);
- light: the hand's colour is pulled towards the face's by a per-channel gain (the ratio
  of the cheeks' median colour to the hand's, to the power ``COLOUR_PULL``), as one light
  falls on both;
- sharpness: the scaled hand is blurred by ``SOFTEN_PX`` (the talking clips are softer
  than the cut frame);
- contact: the face darkens by up to ``SHADOW`` where the hand's mask, blurred over a
  tenth of the eye distance and shifted down by a twentieth of it, lies beside the hand.

Which frames: the first ``part`` of the range carries the hand, every frame of it (a
hand held there); the rest is clean. The output is a real H.264 file
(``bench.occluded.write_h264``) at the clip's rate, frames indexed from 0.

Deterministic: the same clip, range, hand and part give the same pixels.

    python -m facewire.bench.handover hdtf_edmarkey.mp4 OUT.mp4 --frames 0:200 --part 0.45
        [--hand back]
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from facewire.bench.occluded import write_h264
from facewire.models.infra.video import frame_range, read_frames, video_info
from facewire.models.landmarks import outer_eye_distance
from facewire.sender.enroll.occluders import load_mediapipe
from facewire.sender.tracker import LandmarkTracker

# name: (clip, frame, the hand's image x (px) nearest which the wanted hand's wrist lies,
# its palm's length (wrist to middle knuckle) laid over the outer eye distance)
HANDS = {"back": ("latentsync_demo2.mp4", 210, 660.0, 1.0),
         "raised": ("mediapipe_selfie.mp4", 178, 269.0, 0.7)}
HULL_GROW = 0.12  # of the hand's length (wrist to middle fingertip)
FINGER = 0.12  # a finger's width drawn on the bones, of the hand's length
FOREARM = 0.9  # hand lengths
FEATHER_PX = 1.5
TILT_DEG = 50.0
CHEEK = 0.15
DROP = 0.15  # of the eye distance, down the face
SWAY_DEG, SWAY_SHIFT, SWAY_SCALE = 5.0, 0.05, 0.03
SWAY_PERIODS_S = (2.3, 3.1, 3.7, 4.3)  # rotation, x, y, scale
COLOUR_PULL = 0.85
SOFTEN_PX = 0.7
SHADOW = 0.3
_BONES = ((0, 1), (1, 2), (2, 3), (3, 4), (0, 5), (5, 6), (6, 7), (7, 8), (5, 9), (9, 10),
          (10, 11), (11, 12), (9, 13), (13, 14), (14, 15), (15, 16), (13, 17), (0, 17),
          (17, 18), (18, 19), (19, 20))
_PALM = (0, 5, 9, 13, 17)


@dataclass(frozen=True)
class Hand:
    """A hand cut from a real frame: (h, w, 3) uint8 BGR pixels, (h, w) float32 alpha in
    [0, 1], and its 21 landmarks (21, 2) in the cut's pixels."""

    image: np.ndarray
    alpha: np.ndarray
    points: np.ndarray
    palm_over_eyes: float


@dataclass(frozen=True)
class HandOver:
    """What ``hand_over`` wrote: the file, the source range, the frames carrying the hand
    (indices in the output, 0-based) and per frame the hand's (H, W) bool mask's pixel
    count (0 on clean frames)."""

    path: Path
    source: Path
    start: int
    frames: int
    covered: tuple[int, ...]
    hand_pixels: tuple[int, ...]

    def summary(self) -> dict[str, object]:
        return {"path": str(self.path), "source": str(self.source), "start": self.start,
                "frames": self.frames, "covered": len(self.covered),
                "covered_frames": list(self.covered)}


def hand_landmarks(image: np.ndarray) -> list[np.ndarray]:
    """The hands MediaPipe's landmarker finds in one image: each (21, 2) float64 px."""
    h, w = image.shape[:2]
    with load_mediapipe().solutions.hands.Hands(static_image_mode=True, max_num_hands=2,
                                  model_complexity=1, min_detection_confidence=0.3) as hands:
        found = hands.process(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    return [np.array([[p.x * w, p.y * h] for p in lm.landmark])
            for lm in found.multi_hand_landmarks or []]


def cut_hand(data: str | os.PathLike[str], name: str = "back") -> Hand:
    """The hand ``name`` (``HANDS``) cut from its clip in the video folder ``data`` (module
    docstring).

    Raises:
        ValueError: an unknown name, or the landmarker finds no hand in the frame.
    """
    if name not in HANDS:
        raise ValueError(f"hand {name!r}: expected one of {sorted(HANDS)}")
    clip, index, wrist_x, palm_over_eyes = HANDS[name]
    image = next(iter(read_frames(Path(data) / clip, slice(index, index + 1)))).image
    found = hand_landmarks(image)
    if not found:
        raise ValueError(f"{Path(data) / clip}: no hand found in frame {index}")
    points = min(found, key=lambda p: abs(p[0, 0] - wrist_x))
    length = float(np.linalg.norm(points[12] - points[0]))
    palm = float(np.linalg.norm(points[5] - points[17]))
    axis = (points[9] - points[0]) / max(np.linalg.norm(points[9] - points[0]), 1e-9)
    elbow = points[0] - axis * FOREARM * length
    grow = HULL_GROW * length
    # the working box: the hand, its forearm and a margin
    corners = np.vstack([points, elbow[None]])
    x0, y0 = np.floor(corners.min(axis=0) - 3 * grow).astype(int)
    x1, y1 = np.ceil(corners.max(axis=0) + 3 * grow).astype(int)
    x0, y0 = max(0, x0), max(0, y0)
    x1, y1 = min(image.shape[1], x1), min(image.shape[0], y1)
    crop = np.ascontiguousarray(image[y0:y1, x0:x1])
    local = points - [x0, y0]
    seed: np.ndarray = np.full(crop.shape[:2], cv2.GC_BGD, np.uint8)
    hull = cv2.convexHull(local.astype(np.float32)).reshape(-1, 2)
    centre = hull.mean(axis=0)

    def grown(poly: np.ndarray, by: float) -> np.ndarray:
        out = centre + (poly - centre) * (1 + by / max(float(np.linalg.norm(
            poly - centre, axis=1).mean()), 1e-9))
        return np.rint(out).astype(np.int32)

    side = np.array([-axis[1], axis[0]]) * palm * 0.55
    wrist = local[0]
    strip = np.array([wrist + side, wrist - side, elbow - [x0, y0] - side,
                      elbow - [x0, y0] + side])
    cv2.fillPoly(seed, [grown(hull, 2 * grow)], cv2.GC_PR_BGD)
    shape = np.zeros(crop.shape[:2], np.uint8)  # the hand's shape: fingers, palm, forearm
    _draw_hand(shape, local, FINGER * length, 1)
    cv2.fillPoly(shape, [np.rint(strip).astype(np.int32)], 1)
    seed[shape > 0] = cv2.GC_PR_FGD
    _draw_hand(seed, local, 0.035 * length, cv2.GC_FGD)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(crop, seed, (0, 0, 1, 1), bgd, fgd, 6, cv2.GC_INIT_WITH_MASK)  # rect unused
    bound = cv2.dilate(shape, cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (int(2 * grow) | 1, int(2 * grow) | 1)))
    mask = (((seed == cv2.GC_FGD) | (seed == cv2.GC_PR_FGD)) & (bound > 0)).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count > 1:
        mask = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    alpha = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), FEATHER_PX)
    # the forearm fades out over its far half: position along the axis past the wrist
    yy, xx = np.mgrid[0:crop.shape[0], 0:crop.shape[1]].astype(np.float32)
    along = ((xx - wrist[0]) * -axis[0] + (yy - wrist[1]) * -axis[1]) / (FOREARM * length)
    alpha *= np.clip((1.0 - along) / 0.5, 0.0, 1.0)
    return Hand(crop, alpha.astype(np.float32), local, palm_over_eyes)


def _draw_hand(canvas: np.ndarray, points: np.ndarray, width: float, value: int) -> None:
    """Draw the hand's bones ``width`` px thick and its palm polygon with ``value``."""
    thick = max(2, int(round(width)))
    for a, b in _BONES:
        cv2.line(canvas, tuple(np.rint(points[a]).astype(int)),
                 tuple(np.rint(points[b]).astype(int)), value, thick)
    cv2.fillPoly(canvas, [np.rint(points[list(_PALM) + [1]]).astype(np.int32)], value)


def _cheek_colour(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(3,) the median BGR of the cheeks and nose (the polygon 1-3, 31-35, 13-15)."""
    mask = np.zeros(image.shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.rint(points[[1, 2, 3, 31, 33, 35, 13, 14, 15, 28]]).astype(
        np.int32)], 1)
    return np.median(image[mask > 0], axis=0) if mask.any() else np.full(3, 128.0)


def lay_hand(image: np.ndarray, hand: Hand, points: np.ndarray, t: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """``image`` (H, W, 3) uint8 BGR with ``hand`` over the mouth and cheek of the face of
    ``points`` (68, 2) at time ``t`` seconds (module docstring); and the hand's (H, W) float32
    alpha in the image."""
    eyes = float(outer_eye_distance(points))
    roll = np.arctan2(*(points[45] - points[36])[::-1])
    ph = SWAY_PERIODS_S
    sway = np.sin(2 * np.pi * t / np.array(ph))
    scale = hand.palm_over_eyes * eyes / float(np.linalg.norm(hand.points[9] - hand.points[0]))
    scale *= 1 + SWAY_SCALE * sway[3]
    axis = hand.points[9] - hand.points[0]
    # the person's right cheek is the image's left: fingers point to -x, tilted up
    want = np.pi + roll + np.radians(TILT_DEG) + np.radians(SWAY_DEG) * sway[0]
    turn = want - np.arctan2(axis[1], axis[0])
    mouth = points[48:68].mean(axis=0)
    down = np.array([-np.sin(roll), np.cos(roll)])
    target = (mouth + CHEEK * (points[13] - mouth) + DROP * eyes * down
              + SWAY_SHIFT * eyes * sway[1:3])
    palm = hand.points[list(_PALM)].mean(axis=0)
    c, s = np.cos(turn) * scale, np.sin(turn) * scale
    warp = np.array([[c, -s, 0.0], [s, c, 0.0]])
    warp[:, 2] = target - warp[:, :2] @ palm
    h, w = image.shape[:2]
    pixels = cv2.warpAffine(hand.image, warp, (w, h), flags=cv2.INTER_AREA if scale < 1
                            else cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    alpha = cv2.warpAffine(hand.alpha, warp, (w, h), flags=cv2.INTER_LINEAR)
    pixels = cv2.GaussianBlur(pixels, (0, 0), SOFTEN_PX).astype(np.float32)
    inside = alpha > 0.5
    if inside.any():
        gain = _cheek_colour(image, points) / np.maximum(np.median(pixels[inside], axis=0), 1)
        pixels *= gain ** COLOUR_PULL
    soft = cv2.GaussianBlur(alpha, (0, 0), max(0.1 * eyes, 1.0))
    shift = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.05 * eyes]], np.float32)
    shade = np.clip(cv2.warpAffine(soft, shift, (w, h)) - alpha, 0, 1)
    face = image.astype(np.float32) * (1 - SHADOW * shade)[..., None]
    out = face * (1 - alpha[..., None]) + pixels * alpha[..., None]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8), alpha


def hand_over(source: str | os.PathLike[str], out: str | os.PathLike[str],
              frames: slice = slice(0, None), part: float = 0.45, hand: str = "back",
              data: str | os.PathLike[str] | None = None) -> HandOver:
    """Write the hand-over-mouth video (module docstring).

    Args:
        source: the real talking clip (a tuning clip: ``bench.clips``).
        out: the H.264 file to write.
        frames: the clip's range to copy.
        part: the first fraction of the range that carries the hand, in (0, 1].
        hand: a name of ``HANDS``.
        data: the folder holding the hand's clip; ``source``'s folder by default.

    Raises:
        ValueError: a bad part or hand name, no frames in the range, or no hand found.
    """
    source, out = Path(source), Path(out)
    if not 0 < part <= 1:
        raise ValueError(f"part {part}: expected (0, 1]")
    cut = cut_hand(source.parent if data is None else data, hand)
    decoded = list(read_frames(source, frames))
    if not decoded:
        raise ValueError(f"{source}: no frames in the range")
    first = decoded[0].time
    carried = int(round(part * len(decoded)))
    tracker = LandmarkTracker()
    images, covered, pixels = [], [], []
    for k, frame in enumerate(decoded):
        points = tracker.track(frame.image).points  # the clean frame's points, in order
        image, count = frame.image, 0
        if k < carried and points is not None:
            image, alpha = lay_hand(image, cut, points, frame.time - first)
            covered.append(k)
            count = int((alpha > 0.5).sum())
        images.append(image)
        pixels.append(count)
    write_h264(images, video_info(source).rate_hz, out)
    return HandOver(out, source, frames.start or 0, len(images), tuple(covered), tuple(pixels))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source")
    parser.add_argument("out")
    parser.add_argument("--frames", default=None)
    parser.add_argument("--part", type=float, default=0.45)
    parser.add_argument("--hand", choices=sorted(HANDS), default="back")
    args = parser.parse_args(argv)
    made = hand_over(args.source, args.out, frame_range(args.frames), args.part, args.hand)
    print(json.dumps(made.summary()))


if __name__ == "__main__":
    main()
