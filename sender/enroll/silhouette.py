"""The person's silhouette in an enrollment frame, found by a segmentation model.

The base texture is the frames projected onto the fitted head (``sender.enroll.texture``).
The head is a generic mesh morphed to the 68 landmarks, which say nothing of the head's
outline beyond the jaw's contour: where the mesh is wider than the real head (a temple, the
side of the head, the hair's top), its texels project onto the room behind the person, and
the texture shows the wall there (latentsync_demo2: a shelf and white tiles down the side of
the head). The depth test cannot see this: the mesh is all it knows. So a model made for it
says which pixels are the person: MediaPipe's selfie segmentation (``WEIGHT``, carried by
the ``mediapipe`` wheel with the hand model, ``sender.enroll.occluders``; nothing is
downloaded), a network that takes a 256 x 256 picture of a person and gives each pixel the
probability that it is the person (hair, face, neck and body; a hand in front of the face
too: that is the occluder finder's work, not this).

Per frame (``SilhouetteFinder.find``):

1. The head's crop: a square centred on the 68 points' box, shifted up by ``CROP_UP`` of the
   box's height (the hair), of side ``CROP_SIDE`` times the box's longer side, cut at the
   image's borders. The model sees the head and shoulders at its own scale, as in a selfie,
   however small the face is in the frame (a phone's portrait clip: a face 260 px wide in
   1080 x 1920), and its mask is read at the crop's resolution.
2. The mask (H, W) bool: the crop's pixels whose probability is at least ``PERSON``;
   every pixel outside the crop is background (the whole head lies within it).

``sender.enroll.texture`` takes a pixel outside the silhouette as an edge pixel: no texel
takes its colour, and views fade out before it as before any edge, so the side of the head
that only the room was seen behind gets the hole filling's colours from the skin and hair
beside it, and a confidence of 0 (``sender.enroll.confidence``). Measured in docs/DESIGN.md
§7 ("The person's outline").
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.sender.enroll.occluders import OccluderError, load_mediapipe, native_stderr_quiet

CROP_SIDE = 2.4  # the crop's side, in the landmarks' box's longer side
CROP_UP = 0.25  # the crop's centre above the box's, in the box's height
PERSON = 0.5  # a pixel at least this likely the person is the person's
WEIGHT = "selfie_segmentation/selfie_segmentation.tflite"


class SilhouetteFinder:
    """MediaPipe's selfie segmentation over the head's crop of a frame (module docstring).

    Raises:
        OccluderError: mediapipe is not installed.
    """

    def __init__(self) -> None:
        segmentation = load_mediapipe().solutions.selfie_segmentation
        with native_stderr_quiet():  # made and run once on a blank image: all it says, said
            self._model: Any = segmentation.SelfieSegmentation(model_selection=0)
            self._model.process(np.zeros((64, 64, 3), np.uint8))

    def close(self) -> None:
        """Free the model's graph."""
        with native_stderr_quiet():
            self._model.close()

    def __enter__(self) -> SilhouetteFinder:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def find(self, image: np.ndarray, points: np.ndarray) -> np.ndarray:
        """The person's silhouette (module docstring).

        Args:
            image: (H, W, 3) uint8 BGR frame.
            points: (68, 2) the face's landmarks, px.

        Returns:
            (H, W) bool: True on the person's pixels in the head's crop.

        Raises:
            OccluderError: bad inputs, named.
        """
        if not (isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3
                and image.shape[2] == 3):
            raise OccluderError(f"image: expected an (H, W, 3) uint8 array, got "
                                f"{getattr(image, 'shape', type(image).__name__)}")
        points = np.asarray(points, np.float64)
        if points.shape != (68, 2) or not np.isfinite(points).all():
            raise OccluderError(f"points: expected (68, 2) finite px, got {points.shape}")
        low, high = points.min(axis=0), points.max(axis=0)
        size = high - low
        centre = (low + high) / 2 - [0.0, CROP_UP * size[1]]
        half = CROP_SIDE * float(size.max()) / 2
        h, w = image.shape[:2]
        x0, y0 = np.maximum(np.floor(centre - half).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(centre + half).astype(int), [w, h])
        mask = np.zeros((h, w), bool)
        if x1 - x0 < 8 or y1 - y0 < 8:
            return mask
        crop = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_BGR2RGB)
        probability = self._model.process(crop).segmentation_mask
        mask[y0:y1, x0:x1] = probability >= PERSON
        return mask


def check_silhouette_model() -> str:
    """One line naming the segmentation model's weights, as ``facewire check`` prints it.

    Raises:
        OccluderError: mediapipe is missing, or its wheel lacks the weights.
    """
    mp = load_mediapipe()
    path = Path(mp.__file__).parent / "modules" / WEIGHT
    if not path.is_file():
        raise OccluderError(f"{path}: mediapipe {mp.__version__} lacks it; run ./install.sh")
    return f"person model: mediapipe {mp.__version__} ({WEIGHT})"
