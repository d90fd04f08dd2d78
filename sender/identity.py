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
150 x 150 chip (``dlib.get_face_chip``, 0.4 ms) as from the frame and the points (dlib
cuts the same chip inside), so the descriptor is computed from the chip (``face_chip``),
here or elsewhere. dlib holds Python's lock while it computes (a Python loop in another
thread stood still for the whole 0.6-0.9 s of a descriptor on the loaded machine), so a
thread cannot take it off the frame path; another process can.

Where the descriptor is computed. A ``Person`` answers a check (``submit``, then ``poll``)
either at once, in the caller's thread (files: the same answers on every run), or, made
with ``apart=True``, from a child process of its own (spawned, so that the camera's and the
sockets' threads are not forked): ``submit`` hands the 67 kB chip to a queue whose feeder
thread writes it to the pipe, so the frame path goes on at once, and the answer (0.5 kB,
on a one-way pipe of its own) is polled frames later (``sender.tracker``, "Identity", says
what the tracker does meanwhile). The child loads the network once (about 80 ms of CPU;
with Python's start and imports, 0.5-1 s of wall time, which the ``Person`` waits for, so
that the first frames are answered as fast as the later ones) and computes the chips in the
order given. A child that died is ``IdentityError`` at the next ``poll``: the tracker would
otherwise wait for an answer forever and never take the person.

Image coordinates as ``sender.tracker``'s. The network runs single-threaded, with no BLAS.
"""

from __future__ import annotations

import itertools
import multiprocessing
import queue
import threading
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import cv2
import dlib
import numpy as np

from facewire.models.fields import DESCRIPTOR_SIZE
from facewire.models.infra.childpipe import receive_from
from facewire.models.modelfile import check_descriptors
from facewire.protocol.errors import FacewireError
from facewire.sender.tracker import box_from_points, predictor_path

NETWORK_FILE = "dlib_face_recognition_resnet_model_v1.dat"
MATCH_DISTANCE = 0.5
CHIP_SIZE = 150  # the network's input: the face aligned into a 150 x 150 RGB chip
CHIP_PADDING = 0.25
START_S = 60.0  # how long a starting child is given to load the network
CLOSE_S = 2.0  # how long a closing child is given before it is killed
PARENT_POLL_S = 0.5  # how often the idle child checks that its parent lives

_NETWORKS: dict[str, dlib.face_recognition_model_v1] = {}
_NETWORKS_LOCK = threading.Lock()


def network_path() -> Path:
    """The installed face recognition network (beside the 68-point predictor)."""
    path = predictor_path().parent / NETWORK_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: dlib face recognition network not found")
    return path


class IdentityError(FacewireError, RuntimeError):
    """The identity process died or did not start; no check can be answered."""


def face_chip(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The face whose 68 points are given, aligned as the network takes it.

    Args:
        image: (H, W, 3) uint8 BGR or (H, W) uint8 grey frame.
        points: (68, 2) landmarks of one face in it, pixels (``sender.tracker``).

    Returns:
        (150, 150, 3) uint8 RGB, C-contiguous.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or not (
            image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ValueError("image: expected an (H, W, 3) BGR or (H, W) grey uint8 array")
    points = np.asarray(points, np.float32)
    colour = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
    parts = dlib.points([dlib.point(int(round(x)), int(round(y))) for x, y in points.tolist()])
    shape = dlib.full_object_detection(dlib.rectangle(*box_from_points(points)), parts)
    chip = dlib.get_face_chip(np.ascontiguousarray(colour), shape, CHIP_SIZE, CHIP_PADDING)
    return np.ascontiguousarray(chip[..., ::-1])  # cut per channel: BGR's chip, reordered


def chip_descriptor(chip: np.ndarray) -> np.ndarray:
    """The (128,) float32 descriptor of a (150, 150, 3) uint8 RGB chip (``face_chip``)."""
    return np.asarray(_network().compute_face_descriptor(chip), np.float32)


def face_descriptor(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The (128,) float32 descriptor of the face whose 68 points are given (``face_chip``'s
    arguments)."""
    return chip_descriptor(face_chip(image, points))


class Person:
    """The model's person: the mean of their stored descriptors, and the checks of faces
    against it (module docstring, "Where the descriptor is computed").

    Args:
        descriptors: (D, 128) float32, finite (``PersonModel.descriptors``).
        threshold: the largest distance from the mean that is the person (> 0).
        apart: compute the checks' descriptors in a child process; ``close`` ends it.
    """

    def __init__(self, descriptors: np.ndarray, threshold: float = MATCH_DISTANCE,
                 apart: bool = False) -> None:
        check_descriptors(descriptors)
        if not (np.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold: expected a positive distance, got {threshold!r}")
        self.centre = descriptors.astype(np.float64).mean(axis=0)
        self.threshold = float(threshold)
        self._tickets = itertools.count()
        self._answers: dict[int, float] = {}
        self._process: Any = None
        if not apart:
            _network()  # loaded now (about 80 ms of CPU), so that the first check does not pay
            return
        context = multiprocessing.get_context("spawn")
        self._chips: Any = context.Queue()
        self._descriptors, sending = context.Pipe(duplex=False)
        self._process = context.Process(target=_serve, name="facewire identity",
                                        args=(self._chips, sending), daemon=True)
        self._process.start()
        sending.close()  # the child's end: the pipe ends when the child does
        try:  # its word that the network is loaded: the first checks as fast as the later
            receive_from(self._process, self._descriptors, START_S)
        except (EOFError, OSError) as error:  # TimeoutError is an OSError
            code = self._process.exitcode
            self.close()
            raise IdentityError("the identity process " + (
                f"did not start within {START_S:g} s" if isinstance(error, TimeoutError)
                else f"exited with code {code} while starting")) from None

    def distance(self, image: np.ndarray, points: np.ndarray) -> float:
        """The face's descriptor's distance from the person's mean (``face_descriptor``), in
        this thread."""
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

    def submit(self, image: np.ndarray, points: np.ndarray) -> int:
        """Ask whether the face of these points is the person's; the check's ticket. Its
        distance is in a later ``poll`` (the next one, unless ``apart``).

        Args:
            image: (H, W, 3) uint8 BGR or (H, W) uint8 grey frame.
            points: (68, 2) landmarks of one face in it.
        """
        ticket = next(self._tickets)
        if self._process is None:
            self._answers[ticket] = self.distance(image, points)
        else:
            self._chips.put((ticket, face_chip(image, points)))
        return ticket

    def poll(self) -> dict[int, float]:
        """The distances of the checks answered since the last poll, by ticket.

        Raises:
            IdentityError: the identity process died.
        """
        answers, self._answers = self._answers, {}
        if self._process is None:
            return answers
        try:
            while self._descriptors.poll(0):
                ticket, descriptor = self._descriptors.recv()
                answers[ticket] = self.distance_of(descriptor)
        except (EOFError, OSError):
            pass  # the child is gone: said below
        if not answers and not self._process.is_alive():
            raise IdentityError(f"the identity process (pid {self._process.pid}) exited "
                                f"with code {self._process.exitcode}")
        return answers

    def close(self) -> None:
        """End the identity process, if any (the checks pending are not answered)."""
        if self._process is None:
            return
        self._chips.put(None)
        self._process.join(CLOSE_S)
        if self._process.exitcode is None:
            self._process.kill()
            self._process.join()
        self._chips.cancel_join_thread()
        self._chips.close()
        self._descriptors.close()
        self._process.close()
        self._process = None


def _serve(chips: Any, descriptors: Connection) -> None:
    """The identity process: its network loaded, a word that it is ready, then (ticket,
    chip) in, (ticket, descriptor) out, until None, or until the parent is gone (killed: the
    chips' queue stays open in this process, so it would wait forever, holding the
    parent's stdout). An answer is 0.5 kB: the pipe never holds the child up."""
    _network()
    parent = multiprocessing.parent_process()
    try:
        descriptors.send(None)
        while parent is None or parent.is_alive():
            try:
                item = chips.get(timeout=PARENT_POLL_S)
            except queue.Empty:
                continue
            if item is None:
                return
            ticket, chip = item
            descriptors.send((ticket, chip_descriptor(chip)))
    except (BrokenPipeError, ConnectionResetError):
        return  # the parent closed its end: nobody is asking


def _network() -> dlib.face_recognition_model_v1:
    """The network, loaded once per process (about 22 MB; computing does not change it)."""
    path = network_path()
    with _NETWORKS_LOCK:
        net = _NETWORKS.get(str(path))
        if net is None:
            net = _NETWORKS[str(path)] = dlib.face_recognition_model_v1(str(path))
    return net
