"""Coverage: which states of the face a model's layers were taken from, said plainly.

A region's layers can only show what its enrollment frames showed: a model built from a
video without a blink has no closed-eye layer, and the receiver then draws the nearest
layer it has. ``model build`` therefore measures, on the frames each region's layers were
taken from (``sender.enroll.layers``: the states of a region are frames chosen along its
cue, ``region_cues``, from rest to extreme, in layer order), which of ten states they show,
and says for each one it lacks what the rendering will do instead.

Measures of one frame (``state_measures``, from the tracked 68 points, the sent residuals,
the cues of ``sender.cues.region_cues`` and the frame; ``MEASURES`` order):

============  =============================================================================
measure       definition
============  =============================================================================
ear_right,    eye aspect ratio of that eye (``models.landmarks.eye_aspect_ratio``)
ear_left
iris_right,   the eyeball cue of ``region_cues``: the iris's centroid across the eyeball
iris_left     sample, 0 .. 1 along the model's +x, the person's own left (image right):
              the axis the eyeball layers are ordered on
brow_mm       the forehead cue: mean y residual of the brows 19, 21, 22, 24 (mm, up)
furrow_mm     the brow furrow cue: x residual of 21 minus that of 22 (mm, together)
mouth_gap     the mouth cue: inner-lip gap |p66 - p62| over the outer-eye distance
teeth         share of the inner-lip polygon (60 .. 67) that looks like teeth: grey over
              the lips' median grey by ``TEETH_OVER_LIPS`` and HSV saturation under
              ``TEETH_SATURATION`` (0 .. 255); 0 while the gap is under 0.02
============  =============================================================================

Values (``state_values``) are taken against a *reference*. The brows' and the furrow's
residuals are already offsets from the model's neutral shape, the rest the receiver draws:
they are taken as they are (mm). The eyes' measures are taken against their median over
every observed frame, the person's typical eyes: the neutral frame is the least expressive
one, but it may still glance aside or open the eyes wide (openface_gaze's neutral looks up,
which made half of that clip's frames read as a look down). Eye openness is the EAR over the
median's (a ratio), gaze the mean of both irises' offsets from theirs. The mouth's gap and
teeth are taken as they are. A short range that shows an eye state most of the time has it
as its reference: build from a range that is mostly at rest.

A state is covered when each region that draws it has a layer taken from a frame whose
value lies in the state's interval (``STATES``). The 68 points carry no iris, so vertical
gaze is read from the lids, which follow it: a look down lowers them (an eyelid layer with
the lids lowered but open), a look up raises them (an eyeball layer with the eyes wide);
no region holds a vertical gaze of the iris.

The thresholds, and the frames they pass on the shared clips (``../shared/data/video``,
whole clips, per-frame measures of the real sender, the enrollment's own observation step;
frame ranges inclusive):

- eyes closed, EAR ratio under ``CLOSED_EAR`` = 0.5: lp_d3 48-49 (a wink), 112-132 and
  230-247 (eyes shut in the frown); lp_d14 16-19, 51-52, 126-207 (its wink and blinks);
  lp_d18 95-97 (eyes squeezed). On openface_gaze none: its blinks, at 30 Hz and a small
  face, narrow to about 0.6 at the tracker.
- gaze down, EAR ratio in [0.5, ``DOWN_EAR`` = 0.8): lp_d3's lowered eyes 57-115 and
  125-162; openface_gaze's looks down 553-567. Gaze up, over ``UP_EAR`` = 1.15: lp_d3's
  wide eyes 257-353, openface_gaze 164-183 and 761-770; but lp_d3 keeps its lids low most
  of the time, so its wide-open ahead frames 165-209 pass too: the lids are a weak proxy.
- gaze to the person's left / right, mean iris offset over +``GAZE_ACROSS`` = 0.18 / under
  -0.18: lp_d3's look to the image's right 320-336 passes as left (checked by eye);
  openface_gaze's gaze shifts pass in runs (48-62, 375-388, 425-466 one way; 75-87,
  489-525 the other). There, with light irises and a small face, the cue's darkness
  centroid appeared by eye to move against the iris (frames 48 and 84): the cue, and so
  the eyeball layers' order, is only as good as the iris is darker than the lids' shadow.
- brows raised, over ``BROW_RAISE_MM`` = 3.0 mm: lp_d3's surprise 291-322, lp_d14
  312-345, openface_gaze's raise 615-694; talking and frowning stay under it on lp_d3 and
  lp_d18. But openface_gaze's neutral frame has its brows low, and against it much of that
  clip reads raised (0-151, 283-328): the residuals are only as neutral as the neutral.
- brows furrowed, over ``FURROW_MM`` = 3.0 mm: lp_d3's frown 110-178 and 230-270, lp_d14
  114-121; lp_d18 5 frames; openface_gaze none.
- mouth open, gap over ``OPEN_GAP`` = 0.15: lp_d3's surprise 299-353, lp_d18 64-96 and
  115-155; talking and grimacing lips stay under 0.13 (lp_d3, lp_d14, openface_gaze).
  Mouth wide open (a yawn), over ``WIDE_GAP`` = 0.30: lp_d18's yawn and wide-open mouth
  67-94 and 119-153; lp_d3's surprise peaks at 0.26.
- a smile showing teeth, teeth over ``TEETH_SHARE`` = 0.12 of the inner lips: lp_d18's
  grin 114-128, lp_d14's smile 22-51; no frame of lp_d3 or openface_gaze (no teeth
  shown). This is teeth showing, smiling or not: what the mouth's layers would draw.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from facewire.models.landmarks import eye_aspect_ratio, outer_eye_distance

MEASURES = ("ear_right", "ear_left", "iris_right", "iris_left", "brow_mm", "furrow_mm",
            "mouth_gap", "teeth")
CLOSED_EAR = 0.5
DOWN_EAR = 0.8
UP_EAR = 1.15
GAZE_ACROSS = 0.18
BROW_RAISE_MM = 3.0
FURROW_MM = 3.0
OPEN_GAP = 0.15
WIDE_GAP = 0.30
TEETH_SHARE = 0.12
TEETH_OVER_LIPS = 40.0
TEETH_SATURATION = 90.0
_INNER_LIPS = list(range(60, 68))
_OUTER_LIPS = list(range(48, 60))
_INF = float("inf")


@dataclass(frozen=True)
class StateTest:
    """One state of ``STATES``.

    Attributes:
        name: the state's key in the report and the model.
        label: how a person says it.
        regions: the regions whose layers draw it; each must have a layer showing it.
        values: the ``state_values`` key judged for each region, same order.
        low, high: a layer shows the state when low <= value < high.
        instead: what the rendering does when no layer shows it.
    """

    name: str
    label: str
    regions: tuple[str, ...]
    values: tuple[str, ...]
    low: float
    high: float
    instead: str


_EYELIDS = ("eyelid_right", "eyelid_left")
_EYEBALLS = ("eyeball_right", "eyeball_left")
_AHEAD = "the eyes render looking ahead (the nearest gaze layer)"
STATES: tuple[StateTest, ...] = (
    StateTest("eyes_closed", "eyes closed", _EYELIDS, ("open_right", "open_left"),
              -_INF, CLOSED_EAR, "the eyelids render as the most closed layer seen (open "
              "or half-closed): a blink does not close them"),
    StateTest("gaze_left", "gaze left (the person's own)", _EYEBALLS, ("gaze", "gaze"),
              GAZE_ACROSS, _INF, _AHEAD),
    StateTest("gaze_right", "gaze right (the person's own)", _EYEBALLS, ("gaze", "gaze"),
              -_INF, -GAZE_ACROSS, _AHEAD),
    StateTest("gaze_up", "gaze up", _EYEBALLS, ("open_right", "open_left"), UP_EAR, _INF,
              "the eyes render level, the lids as at rest"),
    StateTest("gaze_down", "gaze down", _EYELIDS, ("open_right", "open_left"), CLOSED_EAR,
              DOWN_EAR, "the lids stay up as at rest (or close fully): a look down does "
              "not show"),
    StateTest("brows_raised", "brows raised", ("forehead",), ("brows",), BROW_RAISE_MM, _INF,
              "the brows rise with the mesh over the neutral forehead (no wrinkles)"),
    StateTest("brows_furrowed", "brows furrowed", ("brow_furrow",), ("furrow",), FURROW_MM,
              _INF, "the brows draw together with the mesh, without the frown's creases"),
    StateTest("mouth_open", "mouth open", ("mouth",), ("gap",), OPEN_GAP, _INF,
              "the lips part over a made-up mouth interior (dark, with teeth), not the "
              "person's own"),
    StateTest("mouth_wide", "mouth wide open", ("mouth",), ("gap",), WIDE_GAP, _INF,
              "a wide-open mouth shows the widest opening's layer, stretched, and the "
              "made-up interior where that frame did not see into the mouth"),
    StateTest("smile_teeth", "a smile showing teeth", ("mouth",), ("teeth",), TEETH_SHARE,
              _INF, "a smile shows the lips' or the open mouth's layer: the teeth an "
              "open-mouth frame showed, or the made-up interior's, not the smile's"),
)
STATE_NAMES = tuple(s.name for s in STATES)
NEUTRAL_INSTEAD = "the neutral texture shows (the mesh still moves)"
NEUTRAL_ONLY = ("only the neutral: the model has no layers (one photo, or no appearance "
                "step); every expression moves the mesh over the neutral texture")


@dataclass(frozen=True)
class Coverage:
    """Which states a model covers, and what it says about the others.

    Attributes:
        states: {state: covered} in ``STATES`` order.
        lines: one line per state not covered (``"eyes closed: not seen; ..."``), after a
            first line ``NEUTRAL_ONLY`` for a model without layers.
        detail: per state, per region: the value of each layer's frame, rounded, in layer
            order ({} for a model without layers).
    """

    states: dict[str, bool]
    lines: tuple[str, ...]
    detail: dict[str, dict[str, list[float | None]]]

    def summary(self) -> dict[str, Any]:
        """The ``--json`` keys: ``coverage`` {state: bool}, ``coverage_lines``,
        ``coverage_detail``."""
        return {"coverage": dict(self.states), "coverage_lines": list(self.lines),
                "coverage_detail": self.detail}


def state_measures(points: np.ndarray, residuals: np.ndarray, cues: dict[str, float],
                   image: np.ndarray) -> np.ndarray:
    """The measures of one frame (module docstring).

    Args:
        points: (68, 2) tracked points, px.
        residuals: (9, 3) the sent residuals, mm (``models.landmarks.NONRIGID`` order).
        cues: the frame's ``region_cues`` by region name (the eyeballs' are used).
        image: (H, W, 3) uint8 BGR frame.

    Returns:
        (len(MEASURES),) float64; NaN where not defined.
    """
    ear_right, ear_left = (float(v) for v in eye_aspect_ratio(points))
    gap = float(np.linalg.norm(points[66] - points[62])
                / max(float(outer_eye_distance(points)), 1e-6))
    values = {
        "ear_right": ear_right, "ear_left": ear_left,
        "iris_right": cues["eyeball_right"], "iris_left": cues["eyeball_left"],
        "brow_mm": float(residuals[:4, 1].mean()),
        "furrow_mm": float(residuals[1, 0] - residuals[2, 0]),
        "mouth_gap": gap,
        "teeth": teeth_share(image, points) if gap >= 0.02 else 0.0,
    }
    return np.array([values[m] for m in MEASURES], np.float64)


def teeth_share(image: np.ndarray, points: np.ndarray) -> float:
    """The share of the inner-lip polygon's pixels that look like teeth (module docstring)."""
    lips = points[_OUTER_LIPS]
    x0, y0 = (int(v) - 2 for v in np.floor(lips.min(axis=0)))
    x1, y1 = (int(v) + 3 for v in np.ceil(lips.max(axis=0)))
    h, w = image.shape[:2]
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return 0.0
    crop = np.ascontiguousarray(image[y0:y1, x0:x1])
    offset = np.array([x0, y0], np.float64)
    inner = np.zeros(crop.shape[:2], np.uint8)
    cv2.fillPoly(inner, [np.rint(points[_INNER_LIPS] - offset).astype(np.int32)], 1)
    outer = np.zeros_like(inner)
    cv2.fillPoly(outer, [np.rint(lips - offset).astype(np.int32)], 1)
    ring = (outer > 0) & (inner == 0)
    if inner.sum() < 4 or ring.sum() < 4:
        return 0.0
    grey = cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY).astype(np.float32)
    saturation = cv2.cvtColor(crop, cv2.COLOR_BGR2HSV)[..., 1].astype(np.float32)
    teeth = (grey > float(np.median(grey[ring])) + TEETH_OVER_LIPS) \
        & (saturation < TEETH_SATURATION)
    return float(teeth[inner > 0].mean())


def reference(measures: np.ndarray) -> np.ndarray:
    """The reference of the values (module docstring): each measure's median over the
    frames, but 0 mm for the brows and the furrow (residuals are offsets from the model's
    neutral shape).

    Args:
        measures: (F, len(MEASURES)) the measures of every observed frame.

    Returns:
        (len(MEASURES),) float64 (NaN for a measure never defined).
    """
    measures = np.asarray(measures, np.float64)
    ref = np.full(measures.shape[1], np.nan)
    for k in range(measures.shape[1]):
        column = measures[:, k][np.isfinite(measures[:, k])]
        if len(column):
            ref[k] = float(np.median(column))
    ref[[MEASURES.index("brow_mm"), MEASURES.index("furrow_mm")]] = 0.0  # the model's rest
    return ref


def state_values(measures: np.ndarray, ref: np.ndarray) -> dict[str, np.ndarray]:
    """The values the states are judged on (module docstring), for K frames.

    Args:
        measures: (K, len(MEASURES)) frames' measures.
        ref: (len(MEASURES),) the reference (``reference``).

    Returns:
        {"open_right", "open_left", "gaze", "brows", "furrow", "gap", "teeth": (K,)}.
    """
    m = np.atleast_2d(np.asarray(measures, np.float64))
    k = {name: i for i, name in enumerate(MEASURES)}
    irises = m[:, [k["iris_right"], k["iris_left"]]] - ref[[k["iris_right"], k["iris_left"]]]
    with warnings.catch_warnings():  # a frame with neither iris: NaN, quietly
        warnings.simplefilter("ignore", RuntimeWarning)
        gaze = np.nanmean(irises, axis=1)
    return {
        "open_right": m[:, k["ear_right"]] / max(float(ref[k["ear_right"]]), 1e-6),
        "open_left": m[:, k["ear_left"]] / max(float(ref[k["ear_left"]]), 1e-6),
        "gaze": gaze,
        "brows": m[:, k["brow_mm"]] - ref[k["brow_mm"]],
        "furrow": m[:, k["furrow_mm"]] - ref[k["furrow_mm"]],
        "gap": m[:, k["mouth_gap"]],
        "teeth": m[:, k["teeth"]],
    }


def measure_coverage(layer_measures: dict[str, np.ndarray], ref: np.ndarray) -> Coverage:
    """Which states the layers show (module docstring).

    Args:
        layer_measures: per region name, (k, len(MEASURES)) the measures of the frames its k
            layers were taken from, in layer order; a model without layers passes {}.
        ref: (len(MEASURES),) the reference (``reference``).

    Returns:
        The coverage; without layers, every state missing after the ``NEUTRAL_ONLY`` line.
    """
    if not layer_measures:
        none = {s.name: False for s in STATES}
        return Coverage(none, tuple(missing_lines(none, neutral_only=True)), {})
    values = {name: state_values(m, ref) for name, m in layer_measures.items()}
    states: dict[str, bool] = {}
    detail: dict[str, dict[str, list[float | None]]] = {}
    lines = []
    for s in STATES:
        seen = []
        detail[s.name] = {}
        for region, key in zip(s.regions, s.values):
            if region not in values:
                seen.append(False)
                continue
            v = values[region][key]
            detail[s.name][region] = [round(float(x), 4) if np.isfinite(x) else None for x in v]
            with np.errstate(invalid="ignore"):
                seen.append(bool(((v >= s.low) & (v < s.high)).any()))
        states[s.name] = all(seen)
        if not any(seen):
            lines.append(f"{s.label}: not seen; {s.instead}")
        elif not all(seen):
            have = ", ".join(r for r, ok in zip(s.regions, seen) if ok)
            missing = ", ".join(r for r, ok in zip(s.regions, seen) if not ok)
            lines.append(f"{s.label}: seen by {have} only; in {missing} {s.instead}")
    return Coverage(states, tuple(lines), detail)



def missing_lines(coverage: dict[str, bool], neutral_only: bool | None = None) -> list[str]:
    """The lines of a coverage, in ``STATES`` order (a stored one too: ``model info``): one
    per state not covered. With no state covered (or ``neutral_only``), ``NEUTRAL_ONLY``
    first, and each state is drawn by the neutral texture. States this version does not
    know are named as they are, last."""
    if neutral_only is None:
        neutral_only = not any(coverage.values())
    lines = [NEUTRAL_ONLY] if neutral_only else []
    known = [s for s in STATES if s.name in coverage]
    for s in known:
        if not coverage[s.name]:
            lines.append(f"{s.label}: not seen; " + (NEUTRAL_INSTEAD if neutral_only
                                                     else s.instead))
    names = {s.name for s in known}
    lines += [f"{name}: not seen" for name, ok in coverage.items() if name not in names
              and not ok]
    return lines


def covered_line(coverage: dict[str, bool]) -> str:
    """One line naming the states covered, by their labels (``STATES`` order)."""
    labels = {s.name: s.label for s in STATES}
    seen = [labels.get(name, name) for name in sorted(
        (n for n, ok in coverage.items() if ok),
        key=lambda n: STATE_NAMES.index(n) if n in STATE_NAMES else len(STATE_NAMES))]
    if not seen:
        return "none of the expression states"
    return f"{len(seen)} of {len(coverage)} states: {', '.join(seen)}"
