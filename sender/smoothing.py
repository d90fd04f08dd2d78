"""Temporal smoothing of what the sender sends: the One-Euro filter on the head pose.

The tracker's points are whole pixels and a fresh fit each frame, so a still face's raw
pose jitters. It is smoothed by a One-Euro filter (Casiez, Roussel and Vogel 2012): each
frame the filtered value ``y`` moves toward the raw one ``x`` by

    y <- y + alpha(f_c) (x - y),        alpha(f) = 1 / (1 + 1 / (2 pi f dt)),

an exponential low-pass of cutoff ``f_c`` Hz, with the cutoff following the filtered speed

    s <- s + alpha(f_speed) (|x - y| / dt - s),      f_c = f_min + beta s,

so a still face gets the low cutoff ``f_min`` (strong smoothing) and a moving one a high
cutoff (little lag: an exponential low-pass trails a ramp by ``(1 - alpha) / alpha``
frames, under 1 once ``alpha >= 1/2``, i.e. ``f_c >= 1 / (2 pi dt)``, 4.8 Hz at 30 Hz).

``PoseFilter``: the rotation and the translation are filtered separately, each with one
speed (rad/s, mm/s). The rotation is filtered on the manifold,
``R_f <- R_f exp(alpha log(R_f^T R_raw))``. After a loss or a new face the filter restarts
at the first new pose (no blend: a new acquisition has no history to keep).

Constants (``ROTATION_FILTER``: f_min 1 Hz, beta 2 per rad/s; ``TRANSLATION_FILTER``: f_min
1 Hz, beta 0.05 per mm/s), chosen on openface_gaze.avi, lp_d0.mp4 and lp_d3.mp4 (generic
head): on each clip's stillest second the raw pose turns 0.54-0.87 deg from frame to frame
(median), the filtered one 0.15-0.27 deg; during head motion the filtered pose trails the
raw one by 1.7-1.9 deg (95th percentile). f_min 0.5 Hz smooths more (0.13-0.23 deg) but
trails more (1.9-2.1 deg); beta 0.5 trails 2.2-3.5 deg. The sender lifts the residuals with
the filtered pose, so the points the packet describes land on the tracked ones and the
filter's lag shows only in the points the residuals do not move (``bench quality``'s
``filter_lag_frames``, ``bench.jitter``; docs/DESIGN.md §8, "Steadiness").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from facewire.models.geometry import Pose, rotation_matrix, rotation_vector

__all__ = ["OneEuro", "PoseFilter", "alpha", "ROTATION_FILTER", "TRANSLATION_FILTER"]


@dataclass(frozen=True)
class OneEuro:
    """One-Euro filter constants: cutoff ``f_min + beta |speed|`` Hz, speed low-passed at
    ``f_speed`` Hz; speed in rad/s (rotation) or mm/s (translation)."""

    f_min: float
    beta: float
    f_speed: float = 1.0

    def check(self, name: str) -> None:
        """Raise ValueError naming ``name`` unless f_min, f_speed > 0 and beta >= 0."""
        if not (self.f_min > 0 and self.beta >= 0 and self.f_speed > 0):
            raise ValueError(f"{name}: f_min and f_speed must be > 0, beta >= 0, got {self}")


ROTATION_FILTER = OneEuro(f_min=1.0, beta=2.0)
TRANSLATION_FILTER = OneEuro(f_min=1.0, beta=0.05)


def alpha(cutoff: float, dt: float) -> float:
    """The exponential low-pass's step ``1 / (1 + 1 / (2 pi cutoff dt))`` (cutoff in Hz, dt
    in s)."""
    return 1.0 / (1.0 + 1.0 / (2.0 * math.pi * cutoff * dt))


def _check_dt(dt: float) -> None:
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt: expected a positive number of seconds, got {dt!r}")


class PoseFilter:
    """One-Euro smoothing of a pose stream (module docstring); one instance per stream."""

    def __init__(self, rotation: OneEuro = ROTATION_FILTER,
                 translation: OneEuro = TRANSLATION_FILTER) -> None:
        rotation.check("rotation")
        translation.check("translation")
        self.rotation_constants = rotation
        self.translation_constants = translation
        self.reset()

    def reset(self) -> None:
        """Forget the stream: the next pose is taken as it is."""
        self._pose: Pose | None = None
        self._speed = [0.0, 0.0]  # filtered rotation (rad/s) and translation (mm/s) speeds

    def step(self, raw: Pose, dt: float) -> Pose:
        """Filter one raw pose, ``dt`` seconds after the previous one (> 0)."""
        _check_dt(dt)
        if self._pose is None:
            self._pose = Pose(rotation=raw.rotation.copy(), translation=raw.translation.copy())
            self._speed = [0.0, 0.0]
            return self._pose
        prev = self._pose
        delta_r = rotation_vector(prev.rotation.T @ raw.rotation)  # model-frame increment
        delta_t = raw.translation - prev.translation
        out = []
        for k, (delta, c) in enumerate(((delta_r, self.rotation_constants),
                                        (delta_t, self.translation_constants))):
            speed = math.sqrt(float(delta @ delta)) / dt
            self._speed[k] += alpha(c.f_speed, dt) * (speed - self._speed[k])
            out.append(alpha(c.f_min + c.beta * self._speed[k], dt) * delta)
        self._pose = Pose(rotation=prev.rotation @ rotation_matrix(out[0]),
                          translation=prev.translation + out[1])
        return self._pose
