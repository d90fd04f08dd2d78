"""A lid does not close while the landmarks say the eye is open: the eyelids' Q, gated.

The eyelid templates span the lid's states from open to closed as enrollment saw them
(``sender.enroll.layers``). An eye opened wider than any of them (surprise, looking up) is
none of them, and the template matcher then picks whichever is least unlike it, often a
half-closed state looking down: the rendering winks at a wide-eyed face. The 68 points see
what the templates do not: how open the eye is. So, per eyelid region,

    r = EAR(tracked points) / EAR(the model's neutral landmarks, seen from the front)
    Q <- min(Q, rest)   when r >= OPEN_RATIO,

EAR the eye aspect ratio (``models.landmarks.eye_aspect_ratio``; the neutral landmarks are
the model mesh's landmark vertices, x and y in mm: the person's own eye at rest) and
``rest`` the region's rest state (``Region.rest``), which, for an eyelid, is an open state:
transparent, the gaze layers showing (``models.regions``). A blink or a wink lowers r, and
the templates decide as before. ``OPEN_RATIO`` = 0.9: on the generic head seen from
600 mm, a head pitched 15 degrees up or down lowers the ratio by 4 %, and one turned 20-30
degrees lowers the far eye's by 5-6 % (the near eye's rises), so an eye at rest stays above
the gate.
"""

from __future__ import annotations

import numpy as np

from facewire.models.landmarks import eye_aspect_ratio
from facewire.models.modelfile import Region

OPEN_RATIO = 0.9
_EYELIDS = {"eyelid_right": 0, "eyelid_left": 1}  # index into eye_aspect_ratio's (right, left)


class EyeGate:
    """The gate for one model's regions (module docstring)."""

    def __init__(self, regions: tuple[Region, ...], neutral_landmarks: np.ndarray) -> None:
        """
        Args:
            regions: the model's regions in packet order.
            neutral_landmarks: (68, 3) the model's neutral landmarks, mm.
        """
        rest = eye_aspect_ratio(np.asarray(neutral_landmarks, np.float64)[:, :2])
        self._gates = [(r, _EYELIDS[region.name], float(rest[_EYELIDS[region.name]]),
                        region.rest) for r, region in enumerate(regions)
                       if region.name in _EYELIDS]

    def apply(self, q: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Q with every open eye's eyelid at most its rest state.

        Args:
            q: (R,) float32 the classifier's Q, packet order.
            points: (68, 2) the frame's tracked points, px.

        Returns:
            (R,) float32, a copy.
        """
        q = q.copy()
        live = eye_aspect_ratio(points)
        for r, eye, rest_ear, rest in self._gates:
            if rest_ear > 0 and live[eye] >= OPEN_RATIO * rest_ear:
                q[r] = min(q[r], rest)
        return q
