"""Whom the sender followed: ``bench quality``'s ``identity_switches`` and ``reacquire_s``.

Judged on the real frames with the model's person (``sender.identity.Person``: the mean
of the model's descriptors, a match under ``MATCH_DISTANCE``), independently of what the
sender decided:

- ``identity_switches``: the frames whose tracked face (the sender's 68 points) is not the
  person's: the descriptor computed on the real frame at those points lies
  ``MATCH_DISTANCE`` or more from the person's mean. Strict: a frame of the right person
  at a pose the descriptor does not recognise counts too. ``identity_frames`` says how
  many tracked frames were judged, ``identity_distance_max`` the largest distance seen.
- ``reacquire_s``: the median, over the person's returns, of the time from the return to
  the first packet with ``FACE_PRESENT``. A return is found on the frames where the
  packets say the face is absent, after the first face packet: every face the detector
  finds there (``LandmarkTracker.faces``, as the tracker's acquisition runs it) is
  identified, and the first frame of such a stretch that shows the person is their
  return (none: they came back on the frame the packets resumed, a delay of 0). None when
  the face was never absent after it was first sent (the person never left).
  ``reacquire_max_s`` is the largest delay, ``returns`` how many there were, and
  ``reacquire_missed`` the returns never followed by a face packet before the clip ended.

Cost: a descriptor per tracked frame and per face on absent frames (tens of ms each,
``sender.identity``). A model without descriptors gives None for all of them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from facewire.models.infra.progress import Progress
from facewire.models.modelfile import PersonModel
from facewire.sender.identity import Person
from facewire.sender.tracker import LandmarkTracker


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
        tracker: supplies the detector and predictor for the returns.
        progress: wraps an iterable to show progress.
    """
    keys = ("identity_switches", "identity_frames", "identity_distance_max", "reacquire_s",
            "reacquire_max_s", "returns", "reacquire_missed")
    if model.descriptors is None:
        return dict.fromkeys(keys)
    person = Person(model.descriptors)
    judged = [k for k, p in enumerate(tracked) if p is not None]
    distances = []
    for k in progress(judged, "identity", len(judged)):
        points = tracked[k]
        assert points is not None
        distances.append(person.distance(images[k], points))
    switches = sum(d >= person.threshold for d in distances)
    delays, missed = _returns(person, images, times, np.asarray(face, bool), tracker)
    return {"identity_switches": int(switches), "identity_frames": len(judged),
            "identity_distance_max": round(max(distances), 3) if distances else None,
            "reacquire_s": round(float(np.median(delays)), 3) if delays else None,
            "reacquire_max_s": round(max(delays), 3) if delays else None,
            "returns": len(delays) + missed, "reacquire_missed": missed}


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
