"""Whose model a build makes: the person chosen among the faces of the enrollment clip.

A clip may show several people. Before tracking (``sender.enroll.build``, step 1), the
build samples ``SAMPLES`` frames spread evenly over its range (the first included), finds
every face in them (``sender.tracker``'s detector and predictor) and computes each one's
descriptor (``sender.identity``). Then, by ``--person``:

- nothing: the person most present. The descriptors are grouped greedily, in frame order,
  each joining the group whose mean lies nearest if that is within
  ``sender.identity.MATCH_DISTANCE``, else starting a group; the group seen in the most
  sampled frames is the person (a tie: the larger median face);
- ``N`` (an integer): the N-th face of the range's first frame, counted from 0 left to
  right (by the left edge of its box);
- a photo: the face of the photo (its largest), matched against the sampled faces:
  the group nearest to it within ``MATCH_DISTANCE``; none is near enough: refused.

The person's descriptors that seed the tracker are their group's (or, for ``N``, that
face's). Failures a user can cause (no face in the first frame or the photo, an index out
of range, a photo of nobody in the clip) raise ``PersonError`` naming the input.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.models.fields import MAX_DESCRIPTORS
from facewire.models.infra.video import VideoFrame
from facewire.protocol.errors import FacewireError
from facewire.sender.identity import MATCH_DISTANCE, face_descriptor
from facewire.sender.tracker import Box, LandmarkTracker

SAMPLES = 12


class PersonError(FacewireError, ValueError):
    """The person asked for cannot be found; the message names the input and says why."""


@dataclass(frozen=True)
class Face:
    """One face found in a sampled frame: its frame index, box ``(left, top, right,
    bottom)`` (inclusive, pixels), (68, 2) points and (128,) float32 descriptor."""

    frame: int
    box: Box
    points: np.ndarray
    descriptor: np.ndarray


@dataclass(frozen=True)
class Chosen:
    """The person a build is of.

    Attributes:
        descriptors: (D, 128) float32, the chosen faces' descriptors (the tracker's seed;
            at most ``MAX_DESCRIPTORS``).
        how: ``"most present"``, ``"index"`` or ``"photo"``.
        people: how many people the sampled frames showed (groups of faces).
        frames: in how many of the ``sampled`` frames the person was seen.
        sampled: the frames sampled.
        index: the person's index in the first frame, left to right, or None when not
            there.
        first: the first frame's index and its faces' boxes, left to right.
        faces: the sampled faces, the person's marked (for the preview): (face, is theirs).
    """

    descriptors: np.ndarray
    how: str
    people: int
    frames: int
    sampled: int
    index: int | None
    first: tuple[int, tuple[Box, ...]]
    faces: tuple[tuple[Face, bool], ...]

    def summary(self) -> dict[str, Any]:
        """``model build --json``'s ``person``."""
        return {"chosen": self.how, "index": self.index, "people": self.people,
                "seen_frames": self.frames, "sampled_frames": self.sampled}

    def line(self) -> str:
        """``model build``'s line on the person."""
        where = "not in the first frame" if self.index is None else \
            f"face {self.index} of {len(self.first[1])} in frame {self.first[0]}, left to right"
        how = {"most present": "the one most present", "index": "chosen by --person N",
               "photo": "chosen by --person PHOTO"}[self.how]
        return (f"person:   {how}, of {self.people} seen: in {self.frames} of {self.sampled} "
                f"sampled frames; {where}")


def sample_faces(frames: Iterable[VideoFrame], indices: list[int],
                 tracker: LandmarkTracker) -> list[list[Face]]:
    """Every face of the frames whose index is in ``indices``, each frame's left to right.

    Args:
        frames: the range's frames in order (they may be more than ``indices``).
        indices: the frame indices to sample, increasing.
        tracker: supplies the detector and predictor (it is reset).

    Returns:
        Per sampled frame, its faces.
    """
    wanted = set(indices)
    out = []
    for frame in frames:
        if frame.index in wanted:
            out.append(faces_in(frame.image, frame.index, tracker))
    return out


def faces_in(image: np.ndarray, index: int, tracker: LandmarkTracker) -> list[Face]:
    """The faces of one (H, W, 3) uint8 BGR image, left to right, with their descriptors."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    faces = []
    for box in sorted(tracker.faces(gray), key=lambda b: b[0]):
        points = tracker.points_in(gray, box)
        faces.append(Face(index, box, points, face_descriptor(image, points)))
    return faces


def choose_person(sampled: list[list[Face]], person: int | np.ndarray | None,
                  where: str, photo_name: str = "") -> Chosen:
    """The person of the build (module docstring).

    Args:
        sampled: per sampled frame, its faces left to right (``sample_faces``), the range's
            first frame first.
        person: None (the most present), an index into the first frame's faces, or the
            (128,) descriptor of a reference photo's face.
        where: names the clip in errors.
        photo_name: names the photo in errors.

    Raises:
        PersonError: no face in any sampled frame, an index the first frame does not have,
            or a photo whose face is nobody's in the clip.
    """
    faces = [f for frame in sampled for f in frame]
    if not faces:
        raise PersonError(f"{where}: no face found in the {len(sampled)} frames sampled")
    first = sampled[0]
    groups = group_faces(faces)
    if isinstance(person, int):
        if not 0 <= person < len(first):
            raise PersonError(f"--person {person}: frame {first[0].frame if first else 0} of "
                              f"{where} holds {len(first)} faces (0 to {len(first) - 1}, left "
                              f"to right)" if first else
                              f"--person {person}: the first frame of {where} holds no face")
        chosen = next(g for g in groups if any(f is first[person] for f in g))
        seed = np.stack([first[person].descriptor])
        how = "index"
    elif person is not None:
        distances = [float(np.linalg.norm(group_mean(g) - person)) for g in groups]
        best = int(np.argmin(distances))
        if distances[best] >= MATCH_DISTANCE:
            raise PersonError(f"--person {photo_name}: its face is nobody's in {where} (the "
                              f"nearest is {distances[best]:.2f} from it, a match is under "
                              f"{MATCH_DISTANCE})")
        chosen = groups[best]
        seed = np.stack([f.descriptor for f in chosen])
        how = "photo"
    else:
        chosen = max(groups, key=lambda g: (len({f.frame for f in g}),
                                            float(np.median([f.box[2] - f.box[0] for f in g]))))
        seed = np.stack([f.descriptor for f in chosen])
        how = "most present"
    mine = {id(f) for f in chosen}
    index = next((k for k, f in enumerate(first) if id(f) in mine), None)
    return Chosen(seed[:MAX_DESCRIPTORS].astype(np.float32), how, len(groups),
                  len({f.frame for f in chosen}), len(sampled), index,
                  (first[0].frame if first else -1, tuple(f.box for f in first)),
                  tuple((f, id(f) in mine) for f in faces))


def photo_descriptor(photo: str | os.PathLike[str], tracker: LandmarkTracker) -> np.ndarray:
    """The (128,) descriptor of the largest face in a reference photo (``--person PHOTO``).

    Raises:
        PersonError: not a readable image, or no face in it (names the file).
    """
    path = Path(photo)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR) if path.is_file() else None
    if image is None:
        raise PersonError(f"--person {path}: not an image file OpenCV can read")
    faces = faces_in(np.asarray(image), 0, tracker)
    if not faces:
        raise PersonError(f"--person {path}: no face found in the photo")
    return max(faces, key=lambda f: f.box[2] - f.box[0]).descriptor


def sample_indices(indices: list[int]) -> list[int]:
    """``SAMPLES`` frame indices spread evenly over ``indices``, the first included."""
    picks = np.linspace(0, len(indices) - 1, min(SAMPLES, len(indices)))
    return sorted({indices[int(round(k))] for k in picks})


def group_faces(faces: list[Face]) -> list[list[Face]]:
    """The faces grouped by person (module docstring), in order of first appearance."""
    groups: list[list[Face]] = []
    for face in faces:
        near = [(float(np.linalg.norm(group_mean(g) - face.descriptor)), k)
                for k, g in enumerate(groups)]
        best = min(near, default=None)
        if best is not None and best[0] < MATCH_DISTANCE:
            groups[best[1]].append(face)
        else:
            groups.append([face])
    return groups


def group_mean(group: list[Face]) -> np.ndarray:
    """The (128,) mean of a group's descriptors."""
    return np.mean([f.descriptor for f in group], axis=0)
