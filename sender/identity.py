"""Who the model is of: a face's descriptor, and whether it is the model's person's.

The descriptor is dlib's face recognition network (``dlib_face_recognition_resnet_model_v1``,
shipped with ``face_recognition_models``: a 29-layer ResNet trained by metric learning):
the face is aligned by its 68 points into a 150 x 150 chip (padding 0.25) and mapped to a
vector of 128 numbers, such that faces of one person lie close together in Euclidean
distance and faces of different people far apart. dlib states 0.6 as the usual
same-person threshold for two single descriptors (99.38 % on LFW).

The model stores a few descriptors of its person, taken at well-spread enrollment frames
(``models.modelfile``: ``PersonModel.descriptors``). A face is the person's when its
descriptor lies within ``MATCH_DISTANCE`` of their mean (``Person.distance``). The mean is
steadier than any one of them, and on our clips it separates people better than dlib's
pairwise 0.6: on ``openface_multi_face.avi`` (three people, faces of 73 and 125 px, a
descriptor every 30th frame) a person's descriptors lie 0.16-0.36 from their own mean (a
few turned faces 0.5), the other two people's 0.59 or more, while single descriptors of
one person lie up to 0.72 apart and of two people as close as 0.40. Hence 0.5: a turned face
of the person may go unrecognised for a moment (the sender then says the face is absent),
another person's face is not taken for theirs.

Cost: one descriptor is the network's forward pass, about 100 ms of CPU time (90-180 ms
of wall time on one core of the shared 2-core machine under load; the 68-point prediction
is 1.3-2.3 ms), so the sender checks identity only when it takes a face, not every frame
(``sender.tracker``, "Identity"). Loading the network costs about 80 ms of CPU more, paid
when a ``Person`` is made, not on a frame. The descriptor is the same computed from the
150 x 150 chip (``dlib.get_face_chip``, 0.4 ms) as from the frame and the points (measured
distance 0), but dlib holds Python's lock while it computes (a Python loop in another
thread stood still for the whole 0.6-0.9 s of a descriptor on the loaded machine), so a
thread cannot take it off the frame path; only another process could.

Image coordinates as ``sender.tracker``'s. The network runs single-threaded, with no BLAS.
"""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import dlib
import numpy as np

from facewire.models.fields import DESCRIPTOR_SIZE
from facewire.models.modelfile import check_descriptors
from facewire.sender.tracker import box_from_points, predictor_path

NETWORK_FILE = "dlib_face_recognition_resnet_model_v1.dat"
MATCH_DISTANCE = 0.5

_NETWORKS: dict[str, dlib.face_recognition_model_v1] = {}
_NETWORKS_LOCK = threading.Lock()


def network_path() -> Path:
    """The installed face recognition network (beside the 68-point predictor)."""
    path = predictor_path().parent / NETWORK_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: dlib face recognition network not found")
    return path


def face_descriptor(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The descriptor of the face whose 68 points are given.

    Args:
        image: (H, W, 3) uint8 BGR or (H, W) uint8 grey frame.
        points: (68, 2) landmarks of one face in it, pixels (``sender.tracker``).

    Returns:
        (128,) float32.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or not (
            image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ValueError("image: expected an (H, W, 3) BGR or (H, W) grey uint8 array")
    points = np.asarray(points, np.float32)
    rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB if image.ndim == 2 else cv2.COLOR_BGR2RGB)
    parts = dlib.points([dlib.point(int(round(x)), int(round(y))) for x, y in points.tolist()])
    shape = dlib.full_object_detection(dlib.rectangle(*box_from_points(points)), parts)
    return np.asarray(_network().compute_face_descriptor(rgb, shape), np.float32)


class Person:
    """The model's person: the mean of their stored descriptors.

    Args:
        descriptors: (D, 128) float32, finite (``PersonModel.descriptors``).
        threshold: the largest distance from the mean that is the person (> 0).
    """

    def __init__(self, descriptors: np.ndarray, threshold: float = MATCH_DISTANCE) -> None:
        check_descriptors(descriptors)
        if not (np.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold: expected a positive distance, got {threshold!r}")
        self.centre = descriptors.astype(np.float64).mean(axis=0)
        self.threshold = float(threshold)
        _network()  # loaded now (about 80 ms of CPU), so that the first check does not pay for it

    def distance(self, image: np.ndarray, points: np.ndarray) -> float:
        """The face's descriptor's distance from the person's mean (``face_descriptor``)."""
        return self.distance_of(face_descriptor(image, points))

    def distance_of(self, descriptor: np.ndarray) -> float:
        """A (128,) descriptor's distance from the person's mean."""
        if np.shape(descriptor) != (DESCRIPTOR_SIZE,):
            raise ValueError(f"descriptor: expected shape ({DESCRIPTOR_SIZE},), "
                             f"got {np.shape(descriptor)}")
        return float(np.linalg.norm(np.asarray(descriptor, np.float64) - self.centre))

    def matches(self, image: np.ndarray, points: np.ndarray) -> bool:
        """Whether the face is the person's (its distance under the threshold)."""
        return self.distance(image, points) < self.threshold


def _network() -> dlib.face_recognition_model_v1:
    """The network, loaded once per process (about 22 MB; computing does not change it)."""
    path = network_path()
    with _NETWORKS_LOCK:
        net = _NETWORKS.get(str(path))
        if net is None:
            net = _NETWORKS[str(path)] = dlib.face_recognition_model_v1(str(path))
    return net
