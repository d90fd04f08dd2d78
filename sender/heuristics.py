"""The paper's heuristics for noisy or missing feature points, applied to the 9 residuals.

Input per frame: the 9 non-rigid residuals (``models.landmarks.NONRIGID`` order: brows 19,
21, 22, 24; mouth corners 48, 54; lip middles 51, 57; chin 8) as (9, 3) displacements from
the person's neutral feature points, in model space (mm; x toward the person's left, y up,
z out of the face), after pose and lift; a per-point validity (bool, or a confidence in
[0, 1] compared with ``min_confidence``); whether a face was seen; and the time step
``dt``. Output: the (9, 3) residuals to send and the packet flags they earn. Working on
residuals rather than image points makes "neutral" exactly 0 and mirroring a sign flip;
packing them into each point's tangent frame (u, v) happens later. Pose smoothing and hold
are ``sender.pose``'s business, not this module's.

Each frame, for each point, in this order:

1. Extreme (``extreme_mm`` = 40): a measured residual longer than this is outside a face's
   range and counts as missing. Measured on the 12 shared clips (tracked by
   ``sender.tracker``, non-rigid points after a 2D similarity fit of the 9 rigid points to
   the generic head's, in mm, minus each clip's median): the largest genuine excursion was
   33.6 mm (lower lip 57, mouth wide open; chin 8: 29.2 mm, mouth corners 27.0 mm, brows
   21.2 mm).
2. Jump (``jump_mm`` = 15 per 1/30 s, scaled by ``max(1, 30 dt)`` for longer steps): a point
   whose measurement moved farther than this from its last output keeps the last output
   (HELD). The new value is taken once ``release_frames`` = 3 consecutive measurements
   agree with each other (each within the threshold of the one before), so a genuinely fast
   move is delayed by 2 frames, not lost. A point held that long without agreement counts
   as missing. Measured frame-to-frame motion of the same residuals on the 10 clips with
   one face throughout (30,861 point steps, 15-30 Hz): 99th percentile 3.7 mm, 99.9th
   6.4 mm, largest 12.0 mm; steps over 15 mm appeared only where the tracker wandered off a
   small face (hamilton_short.mp4, 19-27 mm) or switched faces (openface_multi_face.avi,
   35 mm).
3. Missing (not valid, extreme, or held too long), in order of preference:
   a. Symmetric completion: a point whose mirror partner (``models.landmarks.MIRROR``: 19
      with 24, 21 with 22, 48 with 54) was measured and accepted this frame takes the
      partner's residual reflected in the model's midplane, ``(x, y, z) -> (-x, y, z)``
      (MIRRORED). Midline points (51, 57, 8) have no partner.
   b. Decay: ``r <- r * 2 ** (-dt / decay_half_life_s)`` toward neutral (0) from the last
      output (HELD), half-life 0.5 s ("decays slowly"): a 6-frame drop keeps 76 % of the
      expression, a 2.7 s loss (the longest in the shared clips) ends within 3 % of
      neutral.
4. Face loss (no face this frame): every point decays as in 3b; the frame is flagged
   TRACKING_LOST (and HELD). The first frame with a face again is REACQUIRED: the jump
   reference restarts at the new measurements, and the output blends linearly from the
   last (decayed) output to the filtered measurements over ``reacquire_s`` = 0.3 s, so a
   30 mm change is spread over 9 frames at 30 Hz (at most 3.3 mm a frame plus the face's own
   motion) instead of one step.

The first frame of a stream, when it has a face, is taken as measured (no jump test, no
blend; its missing points start at neutral). A stream that starts without a face is lost
from neutral, and its first face frame is REACQUIRED as in 4. So is the next frame after
``restart`` (the tracker acquired another face from one frame to the next: no frame without
a face in between, but not the same face).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from facewire.models.landmarks import MIRROR, NONRIGID
from facewire.protocol.packet import Flag

N_POINTS = len(NONRIGID)
FRAME_S = 1.0 / 30.0

# Position (in NONRIGID order) of each point's mirror partner; itself on the midline.
PARTNER = np.array([NONRIGID.tolist().index(MIRROR[i]) for i in NONRIGID], dtype=np.int64)
PARTNER.setflags(write=False)
REFLECT = np.array([-1.0, 1.0, 1.0], dtype=np.float32)
_FACE_PRESENT, _HELD, _MIRRORED, _REACQUIRED, _TRACKING_LOST = (
    int(f) for f in (Flag.FACE_PRESENT, Flag.HELD, Flag.MIRRORED, Flag.REACQUIRED,
                     Flag.TRACKING_LOST))


@dataclass(frozen=True)
class Counts:
    """How many of the 9 points each case applied to on one frame."""

    measured: int  # taken from this frame's measurement
    held: int  # kept at the last output after a jump
    mirrored: int  # completed from the partner
    decayed: int  # decayed toward neutral (missing, extreme, held too long, or no face)
    extreme: int  # measurements rejected as extreme (then mirrored or decayed)


@dataclass(frozen=True)
class FilterOutput:
    """One frame's filtered residuals and the flags they earn.

    Attributes:
        residuals: (9, 3) float32, mm, model space, NONRIGID order.
        face_present: a face was seen this frame.
        held: at least one point was held or decayed (Flag.HELD).
        mirrored: at least one point was completed from its partner (Flag.MIRRORED).
        reacquired: first frame with a face after a loss (Flag.REACQUIRED).
        tracking_lost: no face this frame (Flag.TRACKING_LOST).
        counts: per-case point counts.
    """

    residuals: np.ndarray
    face_present: bool
    held: bool
    mirrored: bool
    reacquired: bool
    tracking_lost: bool
    counts: Counts

    @property
    def flags(self) -> Flag:
        """The packet flags this frame earns (FACE_PRESENT included)."""
        bits = 0
        for on, bit in ((self.face_present, _FACE_PRESENT), (self.held, _HELD),
                        (self.mirrored, _MIRRORED), (self.reacquired, _REACQUIRED),
                        (self.tracking_lost, _TRACKING_LOST)):
            if on:
                bits |= bit
        return Flag(bits)


class ResidualFilter:
    """Per-stream state of the heuristics (module docstring); one instance per stream."""

    def __init__(self, *, decay_half_life_s: float = 0.5, jump_mm: float = 15.0,
                 release_frames: int = 3, extreme_mm: float = 40.0, reacquire_s: float = 0.3,
                 min_confidence: float = 0.5) -> None:
        """Set the thresholds (defaults and their measurements in the module docstring).

        Args:
            decay_half_life_s: half-life of a missing point's decay to neutral, s (> 0).
            jump_mm: largest accepted change of a point in 1/30 s, mm (> 0).
            release_frames: consecutive agreeing measurements that end a hold (>= 1).
            extreme_mm: longest plausible residual, mm (> 0).
            reacquire_s: blend time after re-acquisition, s (>= 0; 0 switches the blend off).
            min_confidence: confidences below this count as missing, in [0, 1].
        """
        for name, value in (("decay_half_life_s", decay_half_life_s), ("jump_mm", jump_mm),
                            ("extreme_mm", extreme_mm)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: expected a positive number, got {value}")
        if not (math.isfinite(reacquire_s) and reacquire_s >= 0):
            raise ValueError(f"reacquire_s: expected a number >= 0, got {reacquire_s}")
        if not (isinstance(release_frames, int) and release_frames >= 1):
            raise ValueError(f"release_frames: expected an integer >= 1, got {release_frames}")
        if not 0.0 <= min_confidence <= 1.0:
            raise ValueError(f"min_confidence: expected a value in [0, 1], got {min_confidence}")
        self.decay_half_life_s = float(decay_half_life_s)
        self.jump_mm = float(jump_mm)
        self.release_frames = release_frames
        self.extreme_mm = float(extreme_mm)
        self.reacquire_s = float(reacquire_s)
        self.min_confidence = float(min_confidence)
        self.reset()

    def reset(self) -> None:
        """Forget the stream: the next frame with a face is taken as measured."""
        self._value = np.zeros((N_POINTS, 3), np.float32)  # filtered value (jump reference)
        self._output = np.zeros((N_POINTS, 3), np.float32)  # last output (after the blend)
        self._pending = np.zeros((N_POINTS, 3), np.float32)  # candidate after a jump
        self._agree = np.zeros(N_POINTS, np.int64)  # measurements agreeing with it
        self._held_for = np.zeros(N_POINTS, np.int64)  # frames held in a row
        self._started = False
        self._lost = False
        self._blend_from = np.zeros((N_POINTS, 3), np.float32)
        self._blend_left = 0.0  # seconds of blend still to run

    def restart(self) -> None:
        """The face changed: the next frame with a face is REACQUIRED (module docstring)."""
        self._lost = self._started

    def step(self, residuals: np.ndarray | None, valid: np.ndarray | None,
             dt: float) -> FilterOutput:
        """Filter one frame.

        Args:
            residuals: (9, 3) measured residuals, mm; None when no face was seen. Entries of
                invalid points may be NaN; valid ones must be finite.
            valid: (9,) bool, or (9,) confidences in [0, 1]; None means all valid. Ignored
                when ``residuals`` is None.
            dt: seconds since the previous frame (> 0).

        Returns:
            The residuals to send and their flags.
        """
        if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt: expected a positive number of seconds, got {dt!r}")
        keep = np.float32(2.0 ** (-dt / self.decay_half_life_s))
        if residuals is None:
            return self._lose(keep)
        measured, ok = self._check(residuals, valid)
        extreme = ok & (_lengths(measured) > self.extreme_mm)
        ok &= ~extreme
        reacquired = self._lost
        if not self._started or reacquired:
            accept, held = ok, np.zeros(N_POINTS, bool)
            self._agree[:] = 0
            self._held_for[:] = 0
            if reacquired and self.reacquire_s > 0:
                self._blend_from = self._output.copy()
                self._blend_left = self.reacquire_s
        else:
            accept, held = self._jump_test(measured, ok, dt)
        value = self._value
        np.copyto(value, measured, where=accept[:, None])
        missing = ~(accept | held)
        partner_ok = accept[PARTNER] & missing
        mirrored = int(np.count_nonzero(partner_ok))
        if mirrored:
            value[partner_ok] = measured[PARTNER][partner_ok] * REFLECT
        decay = missing & ~partner_ok
        decayed = int(np.count_nonzero(decay))
        if decayed:
            value[decay] *= keep
        self._started, self._lost = True, False
        output = self._blend(value, dt)
        n_held = int(np.count_nonzero(held))
        return FilterOutput(
            residuals=output, face_present=True, held=bool(n_held or decayed),
            mirrored=bool(mirrored), reacquired=reacquired, tracking_lost=False,
            counts=Counts(int(np.count_nonzero(accept)), n_held, mirrored, decayed,
                          int(np.count_nonzero(extreme))))

    def _check(self, residuals: np.ndarray, valid: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray]:
        """Validate one frame's inputs; (9, 3) float32 residuals and (9,) bool validity."""
        r = np.asarray(residuals)
        if r.shape != (N_POINTS, 3) or r.dtype.kind not in "fiu":
            raise ValueError(f"residuals: expected a (9, 3) array of numbers, got shape "
                             f"{r.shape}, dtype {r.dtype}")
        if valid is None:
            ok = np.ones(N_POINTS, bool)
        else:
            v = np.asarray(valid)
            if v.shape != (N_POINTS,):
                raise ValueError(f"valid: expected shape (9,), got {v.shape}")
            if v.dtype == bool:
                ok = v.copy()
            elif v.dtype.kind in "fiu" and np.all((v >= 0) & (v <= 1)):
                ok = v >= self.min_confidence
            else:
                raise ValueError("valid: expected bools or confidences in [0, 1]")
        finite = np.isfinite(r).all(axis=1)
        if not finite[ok].all():
            bad = int(np.flatnonzero(ok & ~finite)[0])
            raise ValueError(f"residuals: point {bad} (landmark {NONRIGID[bad]}) is marked "
                             f"valid but is not finite")
        return np.where(ok[:, None], r, 0).astype(np.float32), ok

    def _jump_test(self, measured: np.ndarray, ok: np.ndarray, dt: float
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(accepted, held) masks of the valid points after the jump test (module doc, 2).

        A valid point far from its last value starts or extends a run of agreeing
        measurements (``_agree``); the run's ``release_frames``-th measurement is accepted.
        Until then the point is held, for at most ``release_frames - 1`` frames in a row
        (``_held_for``); after that it is neither accepted nor held: missing.
        """
        limit = self.jump_mm * max(1.0, dt / FRAME_S)
        near = ok & (_lengths(measured - self._value) <= limit)
        jumped = ok & ~near
        if not jumped.any():  # the common case: no run starts, every run ends
            self._agree[:] = 0
            self._held_for[:] = 0
            return near, jumped
        agrees = (self._agree > 0) & (_lengths(measured - self._pending) <= limit)
        self._agree = np.where(jumped, np.where(agrees, self._agree + 1, 1), 0)
        self._pending[jumped] = measured[jumped]
        released = jumped & (self._agree >= self.release_frames)
        held = jumped & ~released & (self._held_for < self.release_frames - 1)
        self._agree[released] = 0
        self._held_for = np.where(held, self._held_for + 1,
                                  np.where(jumped & ~released, self._held_for, 0))
        return near | released, held

    def _lose(self, keep: np.float32) -> FilterOutput:
        """No face: everything decays from the last output (module doc, 4)."""
        self._value = self._output * keep
        self._output = self._value.copy()
        self._blend_left = 0.0
        self._agree[:] = 0
        self._held_for[:] = 0
        self._lost = True
        return FilterOutput(
            residuals=self._output.copy(), face_present=False, held=True, mirrored=False,
            reacquired=False, tracking_lost=True,
            counts=Counts(0, 0, 0, N_POINTS, 0))

    def _blend(self, value: np.ndarray, dt: float) -> np.ndarray:
        """The output: ``value``, or on its way to it from ``_blend_from`` after re-acquiring."""
        if self._blend_left > 0:
            self._blend_left = max(0.0, self._blend_left - dt)
            w = np.float32(1.0 - self._blend_left / self.reacquire_s)
            output = ((1 - w) * self._blend_from + w * value).astype(np.float32, copy=False)
        else:
            output = value.copy()
        self._output = output
        return output.copy()


def _lengths(d: np.ndarray) -> np.ndarray:
    """(9,) Euclidean lengths of (9, 3) rows, in their dtype (as ``np.linalg.norm(d, axis=1)``)."""
    return np.sqrt(np.add.reduce(d * d, axis=1))
