"""What ``bench quality`` says of the texture's confidence and its healing during a session.

- ``texture_confidence_mean``: the mean of the model's confidence map
  (``PersonModel.confidence``, ``sender.enroll.confidence``) over the texels the enrollment
  saw (confidence over 0), in [0, 1]; None for a model without a map.
- ``texture_confidence_low``: the share of those texels under ``sender.heal.LOW_CONFIDENCE``.
- ``patches``: the texture patches the session issued (``models.patch``), and
  ``first_patch_s``: the time from the range's first frame to the first packet naming a
  version a patch made, s (what a receiver holding the session's updates shows from then
  on; the wire's own delay is ``bench bandwidth``'s ``update_first_s``); None without one.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from facewire.models.modelfile import PersonModel
from facewire.models.patch import TexturePatch
from facewire.models.update import Update
from facewire.sender.heal import LOW_CONFIDENCE


def healing_measures(model: PersonModel, updates: list[Update], serials: np.ndarray,
                     times: list[float]) -> dict[str, Any]:
    """The module docstring's keys.

    Args:
        model: the model file the session started from.
        updates: the session's updates, in serial order.
        serials: (F,) the model version each frame's packet names.
        times: (F,) the frames' times, s.
    """
    out: dict[str, Any] = {"texture_confidence_mean": None, "texture_confidence_low": None}
    if model.confidence is not None:
        seen = model.confidence[model.confidence > 0].astype(np.float64)
        if seen.size:
            out["texture_confidence_mean"] = round(float(seen.mean()) / 255.0, 4)
            out["texture_confidence_low"] = round(float((seen < LOW_CONFIDENCE).mean()), 4)
    patches = [u.serial for u in updates if isinstance(u, TexturePatch)]
    out["patches"] = len(patches)
    out["first_patch_s"] = None
    if patches:
        named = np.flatnonzero(np.asarray(serials) >= patches[0])
        if named.size:
            out["first_patch_s"] = round(float(times[int(named[0])] - times[0]), 3)
    return out
