"""How each region's layers spent the enrollment frames: used, rejected and why, or unchosen.

``sender.enroll.layers`` decides, frame by frame, which frames each region may take a layer
from; this module only counts those decisions (no second scoring pass) into the model's
``region_frames`` record (``models.manifest.RegionFrames``), which ``model build`` and
``model info`` print and the preview draws.

Every frame of the build's range is a *candidate* of every region. A candidate is rejected
for the first of these reasons that holds (``REASONS``, in this order):

=============  ==================================================================================
reason         the frame gives the region nothing because
=============  ==================================================================================
no_face        the sender's pipeline found no face, or no head pose, in it (tracking failed)
occluded       the region's part of the face is occluded in it (``sender.enroll.evidence``, 4)
lid_closed     an eyeball's lid is not open in it, so the gaze cue is not defined there
no_cue         the region's cue is not defined otherwise (an eyeball with no dark iris found)
=============  ==================================================================================

The others are clean. The region's layers take one clean frame per state (the *used* frames:
a frame can give several states only as the rest state's neutral frame); the remaining clean
frames were not chosen. A region with no clean frame uses none: its layers draw the base
texture (``sender.enroll.layers``), and ``model build`` says so on its line.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from facewire.models.manifest import RegionFrames
from facewire.models.modelfile import PersonModel

REASONS = ("no_face", "occluded", "lid_closed", "no_cue")
LABELS = {"no_face": "no face", "occluded": "occluded", "lid_closed": "lid closed",
          "no_cue": "no cue"}


def region_frames(candidates: int, occluded: np.ndarray, lid_closed: np.ndarray,
                  no_cue: np.ndarray, observed: Sequence[int],
                  used: Sequence[Sequence[int]], names: Sequence[str]
                  ) -> dict[str, RegionFrames]:
    """Each region's record (module docstring).

    Args:
        candidates: the frames of the build's range.
        occluded: (F, R) bool, per observed frame (a frame with a head pose) and region: the
            region's part is occluded there.
        lid_closed: (F, R) bool: the region is an eyeball whose lid is not open there.
        no_cue: (F, R) bool: the region's cue is not defined there (any cause).
        observed: (F,) the observed frames' video indices.
        used: per region, the video indices its layers were taken from (empty: none).
        names: (R,) the regions' names.

    Returns:
        {name: RegionFrames}, in ``names`` order.
    """
    no_face = candidates - len(observed)
    out = {}
    for r, name in enumerate(names):
        counts = {"no_face": no_face}
        left = np.ones(len(observed), bool)
        for reason, flags in (("occluded", occluded[:, r]), ("lid_closed", lid_closed[:, r]),
                              ("no_cue", no_cue[:, r])):
            counts[reason] = int((left & flags).sum())
            left &= ~flags
        out[name] = RegionFrames(candidates, tuple(sorted(set(used[r]))),
                                 {k: v for k, v in counts.items() if v > 0})
    return out


def ordered(rejected: dict[str, int]) -> list[tuple[str, int]]:
    """The (reason, count) pairs in ``REASONS`` order, any other reason (a newer build's)
    after them by name: the file stores them by name."""
    rank = {reason: k for k, reason in enumerate(REASONS)}
    return sorted(rejected.items(), key=lambda item: (rank.get(item[0], len(REASONS)), item[0]))


def usage_line(frames: RegionFrames) -> str:
    """One region's counts: ``4 of 140 frames used; rejected: 61 occluded, 2 no face; 73
    clean not chosen``, or, with none used, ``no clean frame (...): draws the base texture``."""
    rejected = ", ".join(f"{count} {LABELS.get(reason, reason)}"
                         for reason, count in ordered(frames.rejected))
    if not frames.used:
        return (f"no clean frame of {frames.candidates} (rejected: {rejected or 'none'}): "
                f"draws the base texture")
    return (f"{len(frames.used)} of {frames.candidates} frames used; rejected: "
            f"{rejected or 'none'}; {frames.clean} clean not chosen")


def region_frames_summary(model: PersonModel) -> dict[str, Any] | None:
    """``model build/info --json``'s ``region_frames``: per region its candidates, the frames
    used, the counts rejected per reason and the clean ones not chosen
    (``sender.enroll.usage``); None when the model does not record them."""
    if model.region_frames is None:
        return None
    return {name: {**frames.as_dict(), "clean": frames.clean}
            for name, frames in model.region_frames.items()}
