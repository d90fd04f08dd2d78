"""Whether one frame is clean evidence of a part of the face: sharp, and not occluded there.

Enrollment (``sender.enroll.evidence``, which holds the measurements behind these bounds)
and the sender's learning during a session (``sender.learn``) take a frame's appearance
only when it is clean:

1. Sharp (``sharpness``): b, the variance of the Laplacian of the grey face box (the
   landmarks' bounding box, resized to ``BLUR_BOX_PX`` wide so faces of any size compare).
   Motion blur lowers b; a frame is sharp when b >= ``SHARP_RATIO`` (0.6) times the median
   b of the frames it is judged among (``sender.enroll.registration`` measured the ratio).

2. Not occluded (``ring_mask``, ``ring_occluded``). A part of the face (``PARTS``; the
   regions judged by their part: ``REGION_PARTS``) is judged on the skin *around* it, which
   the part's own expressions barely change (a blink moves the lids, not the skin beside
   the eye; a jaw drop is followed by the morph): the ring between the part's UV box
   (``part_rect``: the UV bounding box of the part's landmark vertices) grown by
   ``RING_INNER`` and by ``RING_OUTER`` of its size, read from the frame on the morphed,
   posed mesh like a layer (``sender.texels``), its colours scaled per channel by the
   ratio of medians to the base texture's (exposure), and compared with the base texture in
   luma. When more than ``RING_OCCLUDED_FRACTION`` (15 %) of the ring's seen texels depart
   by more than ``RING_DEPART_LEVELS`` grey levels, the part is occluded in that frame.
"""

from __future__ import annotations

import cv2
import numpy as np

from facewire.models.mesh import Mesh
from facewire.models.texelgrid import texel_rect

BLUR_BOX_PX = 128
SHARP_RATIO = 0.6  # a frame is sharp when its sharpness is at least this times the median
RING_INNER = 0.1  # the ring around a part: its box grown by 10 % ...
RING_OUTER = 0.6  # ... to 60 % of its size on every side
RING_DEPART_LEVELS = 40.0  # grey levels a ring texel must depart by to count
RING_OCCLUDED_FRACTION = 0.15  # of the ring's seen texels, beyond which the part is occluded
RING_MIN_TEXELS = 50
REGION_PARTS = {"mouth": "mouth", "eyelid_right": "right_eye", "eyeball_right": "right_eye",
                "eyelid_left": "left_eye", "eyeball_left": "left_eye"}  # judged per frame
PARTS = {"mouth": np.arange(48, 68), "right_eye": np.arange(36, 42),
         "left_eye": np.arange(42, 48), "nose": np.arange(27, 36),
         "brows": np.arange(17, 27)}


def sharpness(image: np.ndarray, points: np.ndarray) -> float:
    """b: the variance of the Laplacian of the grey face box (module docstring, 1).

    Args:
        image: (h, w, 3) uint8 BGR frame.
        points: (68, 2) its landmarks, px.
    """
    x0, y0 = np.floor(points.min(axis=0)).astype(int)
    x1, y1 = np.ceil(points.max(axis=0)).astype(int)
    h, w = image.shape[:2]
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(w, x1 + 1), min(h, y1 + 1)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return 0.0
    grey = cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_BGR2GRAY)
    size = (BLUR_BOX_PX, max(4, round(BLUR_BOX_PX * (y1 - y0) / (x1 - x0))))
    grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_32F).var())


def part_rect(mesh: Mesh, part: str, grow: float) -> tuple[float, float, float, float]:
    """(u0, v0, u1, v1): the UV bounding box of a part's landmark vertices, grown by
    ``grow`` of its size on every side and clipped to [0, 1]."""
    uv = mesh.uv[mesh.landmarks[PARTS[part]]].astype(np.float64)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    margin = grow * (hi - lo)
    (u0, v0), (u1, v1) = np.clip(lo - margin, 0, 1), np.clip(hi + margin, 0, 1)
    return float(u0), float(v0), float(u1), float(v1)


def ring_mask(mesh: Mesh, part: str, shape: tuple[int, int]
              ) -> tuple[tuple[float, float, float, float], np.ndarray]:
    """The skin around a part (module docstring, 2): the UV rectangle grown by
    ``RING_OUTER``, and the (h, w) bool mask of its texels outside the one grown by
    ``RING_INNER``."""
    outer, (rows, cols) = texel_rect(part_rect(mesh, part, RING_OUTER), shape)
    inner = np.zeros(shape, bool)
    inner[texel_rect(part_rect(mesh, part, RING_INNER), shape)[1]] = True
    return outer, ~inner[rows, cols]


def ring_occluded(colour: np.ndarray, seen: np.ndarray, base: np.ndarray,
                  ring: np.ndarray) -> bool:
    """Whether a frame's ring around a part departs from the base texture (module
    docstring, 4).

    Args:
        colour: (h, w, 3) float RGB, the frame read at the ring's texels.
        seen: (h, w) bool, where the frame sees them.
        base: (h, w, 3) uint8 RGB, the base texture there.
        ring: (h, w) bool, the ring's texels (``ring_mask``).
    """
    use = seen & ring
    if use.sum() < RING_MIN_TEXELS:
        return False
    c, b = colour[use].astype(np.float64), base[use].astype(np.float64)
    gain = np.clip(np.median(b, axis=0) / np.maximum(np.median(c, axis=0), 1.0), 0.5, 2.0)
    luma = np.array([0.299, 0.587, 0.114])
    depart = np.abs((c * gain) @ luma - b @ luma) > RING_DEPART_LEVELS
    return bool(depart.mean() > RING_OCCLUDED_FRACTION)
