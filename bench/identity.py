"""Whom the sender followed: ``bench quality``'s ``identity_switches`` and ``reacquire_s``.

Judged on the real frames with the model's person (``sender.identity.Person``: the mean
of the model's descriptors, a match under ``MATCH_DISTANCE``), independently of what the
sender decided.

The people of the run (the judge's census): every face the detector finds on every
``CENSUS_EVERY``-th frame of the run, its descriptor computed, grouped by person as the
build groups a clip's faces (``sender.enroll.person.group_faces``: greedily, a face joining
the group whose mean lies under ``MATCH_DISTANCE``). A group whose mean lies ``NEAR_MISS``
(dlib's pairwise threshold, 0.6) or more from the person's is another person; one between
``MATCH_DISTANCE`` and ``NEAR_MISS`` is nobody's (on hamilton_short the singer's own face,
turning into view, made a group of its own at 0.51 from his mean).

- Each tracked frame: the descriptor computed on the real frame at the sender's 68 points
  (the tracked face). Under ``MATCH_DISTANCE`` from the person's mean: the person. Else
  it is an identity switch (``identity_switches``) when the judge can tell whose face it
  is instead:

  - it is another person's: it lies under ``MATCH_DISTANCE`` from another person's mean,
    and nearer that mean than the person's; or
  - the person is elsewhere in the frame: a face the detector finds there, overlapping
    the tracked face's box by less than ``APART_IOU``, is the person's.

  Neither: the face is recognised as nobody (``identity_unrecognised``), not a switch: the
  person blurred by a fast move, turned, cut by the frame's edge or half hidden, whom the
  descriptor does not recognise while the tracker's points still sit on them (or, the
  judge cannot tell, someone the census never saw with the person out of the picture).
  A tracker that follows another person of the clip while the person is in the picture
  is caught by both rules. ``identity_frames`` says how many tracked frames were judged,
  ``identity_distance_max`` the largest distance from the person's mean seen.
- ``reacquire_s``: the median, over the person's returns, of the time from the return to
  the first packet with ``FACE_PRESENT``. A return is found on the frames where the
  packets say the face is absent, after the first face packet: every face the detector
  finds there (``LandmarkTracker.faces``, as the tracker's acquisition runs it) is
  identified, and the first frame of such a stretch that shows the person is their
  return (none: they came back on the frame the packets resumed, a delay of 0). None when
  no absence of the face was followed by a face packet (the person never left, or left
  for good).
  ``reacquire_max_s`` is the largest delay, ``returns`` how many there were, and
  ``reacquire_missed`` the returns never followed by a face packet before the clip ended.

Cost: a descriptor per tracked frame, per face on the census frames, per face on absent
frames and per other face on the frames recognised as nobody (about 100 ms of CPU each,
``sender.identity``). A model without descriptors gives None for all of them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from facewire.models.infra.progress import Progress
from facewire.models.modelfile import PersonModel
from facewire.sender.enroll.person import faces_in, group_faces, group_mean
from facewire.sender.identity import Person, face_descriptor
from facewire.sender.tracker import NEAR_MISS, LandmarkTracker, box_from_points, box_iou

CENSUS_EVERY = 15  # frames: half a second at 30 Hz
APART_IOU = 0.3  # a detection overlapping the tracked face's box less than this is another face

KEYS = ("identity_switches", "identity_unrecognised", "identity_frames",
        "identity_distance_max", "reacquire_s", "reacquire_max_s", "returns",
        "reacquire_missed")


def identity_measures(model: PersonModel, images: list[np.ndarray],
                      tracked: list[np.ndarray | None], times: list[float],
                      face: np.ndarray, tracker: LandmarkTracker,
                      progress: Progress) -> dict[str, Any]:
    """The module docstring's measures over a run of F frames.

    Args:
        model: the model the sender ran with.
        images: F (H, W, 3) uint8 BGR frames.
        tracked: F sender tracker results, (68, 2) pixels or None.
        times: F frame times, seconds.
        face: (F,) bool, the packet's ``FACE_PRESENT``.
        tracker: supplies the detector and predictor for the census and the returns.
        progress: wraps an iterable to show progress.
    """
    if model.descriptors is None:
        return dict.fromkeys(KEYS)
    person = Person(model.descriptors)
    verdicts = judge_frames(person, images, tracked, tracker, progress)
    distances = [d for d, _ in verdicts.values()]
    delays, missed = _returns(person, images, times, np.asarray(face, bool), tracker)
    return {"identity_switches": sum(v == "switch" for _, v in verdicts.values()),
            "identity_unrecognised": sum(v == "nobody" for _, v in verdicts.values()),
            "identity_frames": len(verdicts),
            "identity_distance_max": round(max(distances), 3) if distances else None,
            "reacquire_s": round(float(np.median(delays)), 3) if delays else None,
            "reacquire_max_s": round(max(delays), 3) if delays else None,
            "returns": len(delays) + missed, "reacquire_missed": missed}


def judge_frames(person: Person, images: list[np.ndarray], tracked: list[np.ndarray | None],
                 tracker: LandmarkTracker, progress: Progress) -> dict[int, tuple[float, str]]:
    """Per tracked frame (index into ``images``), the tracked face's distance from the
    person's mean and the verdict: ``"person"``, ``"switch"`` or ``"nobody"`` (module
    docstring).

    Args:
        person: the model's person.
        images: F (H, W, 3) uint8 BGR frames.
        tracked: F tracker results, (68, 2) pixels or None (not judged).
        tracker: supplies the detector and predictor.
        progress: wraps an iterable to show progress.
    """
    others = other_people(person, images, tracker, progress)
    verdicts = {}
    judged = [k for k, p in enumerate(tracked) if p is not None]
    for k in progress(judged, "identity", len(judged)):
        points = tracked[k]
        assert points is not None
        descriptor = face_descriptor(images[k], points)
        distance = person.distance_of(descriptor)
        if distance < person.threshold:
            verdict = "person"
        elif _another(descriptor, distance, others, person.threshold) or \
                _elsewhere(person, images[k], box_from_points(points), tracker):
            verdict = "switch"
        else:
            verdict = "nobody"
        verdicts[k] = (distance, verdict)
    return verdicts


def other_people(person: Person, images: list[np.ndarray], tracker: LandmarkTracker,
                 progress: Progress) -> list[np.ndarray]:
    """The (128,) descriptor means of the people of the run's census other than the person
    (module docstring)."""
    census = range(0, len(images), CENSUS_EVERY)
    faces = [f for k in progress(census, "people", len(census))
             for f in faces_in(images[k], k, tracker)]
    means = [group_mean(g) for g in group_faces(faces)]
    return [m for m in means if person.distance_of(m) >= NEAR_MISS]


def _another(descriptor: np.ndarray, distance: float, others: list[np.ndarray],
             threshold: float) -> bool:
    """Whether the descriptor is another person's: under ``threshold`` from their mean and
    nearer it than ``distance``, its distance from the person's."""
    nearest = min((float(np.linalg.norm(descriptor - m)) for m in others), default=np.inf)
    return nearest < threshold and nearest < distance


def _elsewhere(person: Person, image: np.ndarray, box: tuple[int, int, int, int],
               tracker: LandmarkTracker) -> bool:
    """Whether a face the detector finds in the frame apart from ``box`` is the person's."""
    return any(person.matches(image, tracker.points_in(image, found))
               for found in tracker.faces(image) if box_iou(found, box) < APART_IOU)


def _returns(person: Person, images: list[np.ndarray], times: list[float], face: np.ndarray,
             tracker: LandmarkTracker) -> tuple[list[float], int]:
    """Per return of the person, the delay to the next face packet, s; and how many
    returns no face packet followed (module docstring)."""
    delays: list[float] = []
    missed = 0
    if not face.any():
        return delays, missed
    k = int(np.argmax(face))
    while k < len(face):
        if face[k]:
            k += 1
            continue
        start = k
        while k < len(face) and not face[k]:
            k += 1
        back = next((j for j in range(start, k) if _shows(person, images[j], tracker)), None)
        if k == len(face):
            missed += back is not None
        else:
            delays.append(0.0 if back is None else float(times[k] - times[back]))
    return delays, missed


def _shows(person: Person, image: np.ndarray, tracker: LandmarkTracker) -> bool:
    """Whether any face the detector finds in the frame is the person's."""
    return any(person.matches(image, tracker.points_in(image, box))
               for box in tracker.faces(image))
