"""A reproduction: an enrollment video with a real occluder over the mouth (or an eye) in its
first part.

Issue 16's first failure: a model built from frames where a hand covers the mouth keeps the
hand. The shared data has no hand over a face, so the occluder is cut from another real
frame of another clip, of a different person (``OCCLUDERS``): ``hair``, the back of an
audience member's head in ``hamilton_short.mp4`` (dark: the tracker reads it as an open
mouth), or ``skin``, the forehead of the man in ``lp_d0.mp4`` (skin-coloured like a hand:
the tracker reads it as a closed mouth, so such a frame can become the neutral one).

``occlude`` decodes a range of a real clip, tracks it with the sender's tracker
(``sender.tracker``), and on the chosen frames pastes the patch over a part of the face
(``TARGETS``; the mouth by default). The patch is scaled to a box centred on the mean of the
part's points: over the mouth (points 48-67) 1.6 times the width and 2.2 times the height of
their bounding box; over an eye (points 36-41 for the right eye, 42-47 for the left) 1.6 and
0.9 times the eye's width, whether the eye is open or closed (a hand does not shrink when the
eye closes), which covers the lids and the skin beside them but not the brow. It is blended
in with an elliptical alpha whose edge is feathered over a tenth of the box (no rectangle's
edge shows). Which frames: those in the first ``part`` of the range, each kept clean with
probability ``gap`` (a seeded generator), so many but not all of the enrollment frames carry
the occluder, and the clean ones that remain in the first part are scattered among them.
The result is written as a real H.264 file (PyAV, libx264, CRF 16, yuv420p) at the clip's
rate; the frames keep their indices from 0, so ``--frames A:B`` of the original clip is
``--frames 0:B-A`` of the output.

Deterministic: the same clip, range and seed give the same frames and the same pixels.

    python -m facewire.bench.occluded lp_d3.mp4 OUT.mp4 --frames 0:140 [--occluder skin]
        [--over right_eye]
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import dataclass
from pathlib import Path

import av
import cv2
import numpy as np

from facewire.models.infra.video import frame_range, read_frames, video_info
from facewire.sender.tracker import LandmarkTracker

# name: (clip, frame, rows, columns) of the patch
OCCLUDERS = {"hair": ("hamilton_short.mp4", 0, (290, 360), (60, 200)),
             "skin": ("lp_d0.mp4", 0, (135, 195), (180, 330))}
# part of the face: (its points, the patch's box: its width and its height over the width
# and the height of the points' box); an eye's patch takes its height from the eye's width,
# as a hand does not shrink when the eye closes
TARGETS = {"mouth": (np.arange(48, 68), (1.6, 2.2), False),
           "right_eye": (np.arange(36, 42), (1.6, 0.9), True),
           "left_eye": (np.arange(42, 48), (1.6, 0.9), True)}
FEATHER = 0.1  # fraction of the box the alpha's edge fades over
CRF = 16


@dataclass(frozen=True)
class Occluded:
    """What ``occlude`` wrote: the file, the source range, and the occluded frames (indices
    in the output, 0-based) and the patch's boxes (x0, y0, x1, y1) in pixels."""

    path: Path
    source: Path
    start: int
    frames: int
    occluded: tuple[int, ...]
    boxes: tuple[tuple[int, int, int, int], ...]

    def summary(self) -> dict[str, object]:
        return {"path": str(self.path), "source": str(self.source), "start": self.start,
                "frames": self.frames, "occluded": len(self.occluded),
                "occluded_frames": list(self.occluded)}


def occluder_patch(data: str | os.PathLike[str], occluder: str = "hair") -> np.ndarray:
    """The occluder: (h, w, 3) uint8 BGR cut from its clip (``OCCLUDERS``) in the video
    folder ``data``."""
    clip, index, rows, cols = OCCLUDERS[occluder]
    for frame in read_frames(Path(data) / clip, slice(index, index + 1)):
        return frame.image[rows[0]:rows[1], cols[0]:cols[1]].copy()
    raise ValueError(f"{data}: {clip} has no frame {index}")


def choose_frames(count: int, part: float, gap: float, seed: int) -> np.ndarray:
    """(count,) bool: which of ``count`` frames get the occluder (module docstring)."""
    rng = np.random.default_rng(seed)
    first = np.arange(count) < int(round(part * count))
    return first & (rng.random(count) >= gap)


def paste(image: np.ndarray, patch: np.ndarray, points: np.ndarray, over: str = "mouth"
          ) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """``image`` with ``patch`` over the part ``over`` (``TARGETS``) of ``points`` (68, 2);
    the box it covers."""
    indices, scale, by_width = TARGETS[over]
    part = points[indices]
    box = part.max(axis=0) - part.min(axis=0)
    size = np.array([box[0], box[0] if by_width else box[1]]) * np.array(scale)
    centre = part.mean(axis=0)
    w, h = (max(4, int(round(s))) for s in size)
    x0, y0 = (int(round(c - s / 2)) for c, s in zip(centre, (w, h)))
    scaled = cv2.resize(patch, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot((xx + 0.5) / w * 2 - 1, (yy + 0.5) / h * 2 - 1)
    alpha = np.clip((1.0 - r) / (2 * FEATHER), 0.0, 1.0)[..., None]
    out = image.copy()
    ih, iw = image.shape[:2]
    a0, b0 = max(0, -x0), max(0, -y0)
    a1, b1 = min(w, iw - x0), min(h, ih - y0)
    if a1 <= a0 or b1 <= b0:
        return out, (x0, y0, x0 + w, y0 + h)
    region = out[y0 + b0:y0 + b1, x0 + a0:x0 + a1].astype(np.float32)
    blend = region * (1 - alpha[b0:b1, a0:a1]) + scaled[b0:b1, a0:a1] * alpha[b0:b1, a0:a1]
    out[y0 + b0:y0 + b1, x0 + a0:x0 + a1] = np.clip(np.rint(blend), 0, 255).astype(np.uint8)
    return out, (x0, y0, x0 + w, y0 + h)


def write_h264(images: list[np.ndarray], rate_hz: float, out: str | os.PathLike[str]) -> None:
    """Write (H, W, 3) uint8 BGR ``images`` as a real H.264 file (libx264, CRF ``CRF``,
    yuv420p) at ``rate_hz`` rounded to a whole rate."""
    h, w = images[0].shape[:2]
    with av.open(str(out), "w") as container:
        stream = container.add_stream("libx264", rate=int(round(rate_hz)))
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        stream.options = {"crf": str(CRF)}
        for image in images:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def occlude(source: str | os.PathLike[str], out: str | os.PathLike[str],
            frames: slice = slice(0, None), part: float = 0.6, gap: float = 0.25,
            seed: int = 16, data: str | os.PathLike[str] | None = None,
            occluder: str = "hair", over: str = "mouth") -> Occluded:
    """Write the occluded enrollment video (module docstring).

    Args:
        source: the real clip.
        out: the H.264 file to write.
        frames: the clip's range to copy.
        part: the first fraction of the range where the occluder may appear, in (0, 1].
        gap: the probability that a frame of that part stays clean, in [0, 1).
        seed: the generator's seed.
        data: the folder holding the occluder's clip; ``source``'s folder by default.
        occluder: a name of ``OCCLUDERS``.
        over: the part of the face it covers, a name of ``TARGETS``.
    """
    source, out = Path(source), Path(out)
    if not 0 < part <= 1 or not 0 <= gap < 1:
        raise ValueError(f"part {part}, gap {gap}: expected (0, 1] and [0, 1)")
    if occluder not in OCCLUDERS:
        raise ValueError(f"occluder {occluder!r}: expected one of {sorted(OCCLUDERS)}")
    if over not in TARGETS:
        raise ValueError(f"over {over!r}: expected one of {sorted(TARGETS)}")
    patch = occluder_patch(source.parent if data is None else data, occluder)
    images = [f.image for f in read_frames(source, frames)]
    if not images:
        raise ValueError(f"{source}: no frames in the range")
    chosen = choose_frames(len(images), part, gap, seed)
    tracker = LandmarkTracker()
    occluded, boxes = [], []
    for k, image in enumerate(images):
        points = tracker.track(image).points  # the clean frame's points, tracked in order
        if chosen[k] and points is not None:
            images[k], box = paste(image, patch, points, over)
            occluded.append(k)
            boxes.append(box)
    write_h264(images, video_info(source).rate_hz, out)
    return Occluded(out, source, frames.start or 0, len(images), tuple(occluded), tuple(boxes))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source")
    parser.add_argument("out")
    parser.add_argument("--frames", default=None)
    parser.add_argument("--part", type=float, default=0.6)
    parser.add_argument("--gap", type=float, default=0.25)
    parser.add_argument("--seed", type=int, default=16)
    parser.add_argument("--occluder", choices=sorted(OCCLUDERS), default="hair")
    parser.add_argument("--over", choices=sorted(TARGETS), default="mouth")
    args = parser.parse_args(argv)
    made = occlude(args.source, args.out, frame_range(args.frames), args.part, args.gap,
                   args.seed, occluder=args.occluder, over=args.over)
    print(json.dumps(made.summary()))


if __name__ == "__main__":
    main()
