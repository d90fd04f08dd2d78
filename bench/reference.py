"""Agreement of our per-region Q with OpenFace's per-frame action units (``q_reference``).

Reference format. OpenFace 2.x ``FeatureExtraction`` writes one CSV row per frame (and per
face): ``frame, face_id, timestamp, confidence, success, pose_Tx..pose_Rz, AUxx_r, AUxx_c``.
``frame`` is 1-based (CSV frame 1 is video frame 0); headers and cells may carry a space
after the comma. ``AUxx_r`` is an intensity in [0, 5], ``AUxx_c`` a presence 0/1. We read
``frame``, ``success``, ``confidence`` and every ``AUxx_r`` / ``AUxx_c`` column; the others
are ignored. Rows are returned sorted by frame; a frame may appear once (one face).

Measures. Over the frames present in both series where OpenFace reports ``success`` and the
Q values involved are finite, with Q_n = Q / (k - 1) in [0, 1] (k = the region's layers):

    eyelid_au45         r( (Q_n[eyelid_left] + Q_n[eyelid_right]) / 2 ,  AU45_r )
    forehead_au01_au02  r( Q[forehead] ,  AU01_r + AU02_r )
    mouth_au25_au26     r( Q[mouth] ,  AU25_r + AU26_r )

with r Pearson's correlation, r = cov(x, y) / (sd(x) sd(y)); each entry is
``{"r", "frames", "reason"}`` where ``r`` is None (JSON null) with a reason when the region
is missing from the stream, fewer than 3 frames are usable, or either series is constant.
OpenFace's gaze is not in these files, so the eyeball regions have no reference.

Blink events. Ours: maximal runs of consecutive video frames where the mean normalised
eyelid Q (above) exceeds 0.5, i.e. the lids cross half their range toward closed.
Reference: maximal runs of ``AU45_c == 1``. Both are taken over the same compared frames; a
frame missing from them (no face, or no OpenFace success) ends a run. An event of ours and a
reference event match when their onsets (first frames) are within +-2 frames
(``BLINK_TOLERANCE``); the matching is one-to-one and greedy by distance: all candidate
pairs sorted by onset distance (ties: earlier onsets first), each taken when both events are
still free. Then

    precision = matched / ours,   recall = matched / reference,
    F1 = 2 matched / (ours + reference)

(None when the denominator is 0). Onset rather than overlap: the issue's "matched within +-2
frames" only has a meaning for the onset (an overlap test is indifferent to a shift of a
long event by many frames), the onset is the moment the animation must show the lids
closing, and an overlap test lets one long run (eyes lowered for 35 frames, as around frame
244 of openface_default) absorb any short event inside it. The cost: a long closure whose
onsets differ by more than 2 frames counts as a miss on both sides; ``disagreements`` lists
the unmatched events of each side as [first, last] video frames for a human to look at.
"""

from __future__ import annotations

import csv
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facewire.protocol.errors import FacewireError


class OpenFaceError(FacewireError, ValueError):
    """An OpenFace reference file is missing or malformed; the message names the file,
    the line and/or the column."""


REQUIRED_COLUMNS = ("frame", "success", "AU01_r", "AU02_r", "AU25_r", "AU26_r", "AU45_r",
                    "AU45_c")
MAX_BYTES = 64 << 20  # an OpenFace CSV of an hour at 30 Hz is about 30 MB
BLINK_THRESHOLD = 0.5  # normalised eyelid Q above which the eye counts as closed
BLINK_TOLERANCE = 2  # frames between the onsets of matched events
MIN_FRAMES = 3  # fewest frames for a correlation

_AU_COLUMN = re.compile(r"AU\d\d_[rc]", re.ASCII)
EYELIDS = ("eyelid_left", "eyelid_right")


@dataclass(frozen=True)
class OpenFaceReference:
    """One face's OpenFace output, sorted by frame.

    Attributes:
        path: the file read.
        frames: (F,) int64 0-based video frame indices, strictly increasing.
        success: (F,) bool, OpenFace tracked the face on that frame.
        confidence: (F,) float64 in [0, 1]; NaN when the file has no ``confidence`` column.
        au: action unit columns, name -> (F,) float64: ``AUxx_r`` intensities, ``AUxx_c``
            presences (0.0 or 1.0).
    """

    path: Path
    frames: np.ndarray
    success: np.ndarray
    confidence: np.ndarray
    au: dict[str, np.ndarray]


def read_openface(path: str | os.PathLike[str]) -> OpenFaceReference:
    """Read an OpenFace 2.x per-frame CSV (module docstring).

    Raises:
        OpenFaceError: the file is missing, too large, empty, lacks a required column, has a
            row of the wrong length, a cell that is not a finite number, a frame that is not
            an integer >= 1, a ``success`` or ``AUxx_c`` value other than 0/1, or a frame
            twice (several faces); the message names the file, line and column.
    """
    path = Path(path)
    if not path.is_file():
        raise OpenFaceError(f"{path}: no such file")
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise OpenFaceError(f"{path}: {size} bytes, more than the {MAX_BYTES} allowed")
    try:
        with path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f, skipinitialspace=True))
    except (UnicodeDecodeError, csv.Error) as e:
        raise OpenFaceError(f"{path}: not a readable CSV text file ({e})") from e
    if not rows or not any(cell.strip() for cell in rows[0]):
        raise OpenFaceError(f"{path}: empty file, expected an OpenFace CSV header")
    header = [cell.strip() for cell in rows[0]]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise OpenFaceError(f"{path}: line 1: missing column(s) {', '.join(missing)}")
    duplicated = sorted({c for c in header if header.count(c) > 1})
    if duplicated:
        raise OpenFaceError(f"{path}: line 1: column(s) {', '.join(duplicated)} appear twice")
    wanted = ["frame", "success", *(["confidence"] if "confidence" in header else []),
              *(c for c in header if _AU_COLUMN.fullmatch(c))]
    columns = {name: header.index(name) for name in wanted}

    values: dict[str, list[float]] = {name: [] for name in wanted}
    lines: list[int] = []
    for line, row in enumerate(rows[1:], start=2):
        if not row or (len(row) == 1 and not row[0].strip()):
            continue  # blank line (e.g. at the end)
        if len(row) != len(header):
            raise OpenFaceError(f"{path}: line {line}: {len(row)} cells, the header has "
                                 f"{len(header)}")
        for name, i in columns.items():
            values[name].append(_number(path, line, name, row[i]))
        lines.append(line)
    if not lines:
        raise OpenFaceError(f"{path}: no data rows after the header")

    data = {name: np.array(v, np.float64) for name, v in values.items()}
    line_of = np.array(lines)
    frame = data.pop("frame")
    bad = np.flatnonzero((frame != np.round(frame)) | (frame < 1))
    if bad.size:
        raise OpenFaceError(f"{path}: line {line_of[bad[0]]}, column 'frame': "
                             f"{frame[bad[0]]:g} is not an integer >= 1")
    for name in ["success", *(c for c in data if c.endswith("_c"))]:
        bad = np.flatnonzero((data[name] != 0) & (data[name] != 1))
        if bad.size:
            raise OpenFaceError(f"{path}: line {line_of[bad[0]]}, column {name!r}: "
                                 f"{data[name][bad[0]]:g} is not 0 or 1")
    order = np.argsort(frame, kind="stable")
    frame, line_of = frame[order], line_of[order]
    twice = np.flatnonzero(np.diff(frame) == 0)
    if twice.size:
        i = twice[0]
        raise OpenFaceError(f"{path}: lines {line_of[i]} and {line_of[i + 1]}, column "
                             f"'frame': frame {frame[i]:g} appears twice (several faces? "
                             f"keep one face_id)")
    data = {name: v[order] for name, v in data.items()}
    confidence = data.pop("confidence", np.full(len(frame), np.nan))
    success = data.pop("success").astype(bool)
    return OpenFaceReference(path=path, frames=frame.astype(np.int64) - 1, success=success,
                             confidence=confidence, au=data)


def _number(path: Path, line: int, column: str, cell: str) -> float:
    """A finite float from one CSV cell, or a OpenFaceError naming where it is."""
    try:
        value = float(cell)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise OpenFaceError(f"{path}: line {line}, column {column!r}: {cell.strip()!r} "
                             f"is not a finite number")
    return value


def q_agreement(q: dict[str, np.ndarray], frames: np.ndarray, layers: dict[str, int],
                reference: OpenFaceReference) -> dict[str, Any]:
    """The ``q_reference`` object: correlations and blink events (module docstring).

    Args:
        q: region name -> (N,) float Q in [0, k-1]; NaN where the sender had no face.
        frames: (N,) int 0-based video frame indices of those values, unique.
        layers: region name -> k (>= 2), the layer count; needed for the eyelids.
        reference: ``read_openface`` of the same video.

    Returns:
        A JSON-ready dict: ``frames_compared`` (frames in both with OpenFace success),
        ``eyelid_au45``, ``forehead_au01_au02``, ``mouth_au25_au26`` (each ``{"r", "frames",
        "reason"}``), ``blink_f1``, ``blink_precision``, ``blink_recall``, ``blink_events``,
        ``blink_events_reference``, ``blink_matched``, ``blink_frames``, ``blink_reason``,
        ``blink_rule`` and ``disagreements`` (``{"ours_unmatched": [[first, last], ...],
        "reference_unmatched": [...]}``, video frame indices). Null values carry a reason.

    Raises:
        ValueError: ``frames`` is not 1-D integral and unique, a Q series has another length,
            or an eyelid region in ``q`` has no layer count >= 2 in ``layers``.
    """
    frames = np.asarray(frames)
    if frames.ndim != 1 or not np.issubdtype(frames.dtype, np.integer):
        raise ValueError(f"frames: expected a 1-D integer array, got {frames.shape} "
                         f"{frames.dtype}")
    if np.unique(frames).size != frames.size:
        raise ValueError("frames: a video frame index appears twice")
    series = q_series(q, frames.shape)
    for name in EYELIDS:
        if name in series and not (isinstance(layers.get(name), int) and layers[name] >= 2):
            raise ValueError(f"layers[{name!r}]: expected an int >= 2, got "
                             f"{layers.get(name)!r}")

    # Frames in both, with OpenFace success: ``ours`` indexes q, ``theirs`` the reference.
    _, ours, theirs = np.intersect1d(frames, reference.frames, assume_unique=True,
                                     return_indices=True)
    keep = reference.success[theirs]
    ours, theirs = ours[keep], theirs[keep]
    at = frames[ours]
    au = {name: v[theirs] for name, v in reference.au.items()}

    eyelid = None
    if all(name in series for name in EYELIDS):
        eyelid = sum(series[name][ours] / (layers[name] - 1) for name in EYELIDS) / 2
    missing_eyelids = ", ".join(n for n in EYELIDS if n not in series)
    result: dict[str, Any] = {
        "frames_compared": int(at.size),
        "eyelid_au45": _correlation(eyelid, au["AU45_r"], f"no {missing_eyelids} Q"),
        "forehead_au01_au02": _correlation(
            series["forehead"][ours] if "forehead" in series else None,
            au["AU01_r"] + au["AU02_r"], "no forehead Q"),
        "mouth_au25_au26": _correlation(
            series["mouth"][ours] if "mouth" in series else None,
            au["AU25_r"] + au["AU26_r"], "no mouth Q"),
        "blink_rule": (f"ours: runs of mean eyelid Q/(k-1) > {BLINK_THRESHOLD}; reference: "
                       f"runs of AU45_c == 1; matched one-to-one, greedy by onset distance, "
                       f"onsets within +-{BLINK_TOLERANCE} frames"),
    }
    result.update(_blinks(eyelid, au["AU45_c"], at, f"no {missing_eyelids} Q"))
    return result


def q_series(q: dict[str, np.ndarray], shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Each region's Q as a float64 array of ``shape``.

    Raises:
        ValueError: a series has another shape (names the region).
    """
    series = {}
    for name, values in q.items():
        v = np.asarray(values, np.float64)
        if v.shape != shape:
            raise ValueError(f"q[{name!r}]: expected shape {shape}, got {v.shape}")
        series[name] = v
    return series


def _correlation(x: np.ndarray | None, y: np.ndarray, missing: str) -> dict[str, Any]:
    """Pearson r of x and y over the frames where x is finite, or None with a reason."""
    if x is None:
        return {"r": None, "frames": 0, "reason": missing}
    finite = np.isfinite(x)
    x, y = x[finite], y[finite]
    n = int(x.size)
    if n < MIN_FRAMES:
        return {"r": None, "frames": n, "reason": f"{n} frames with Q and OpenFace success, "
                                                   f"need {MIN_FRAMES}"}
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        which = "our Q" if np.ptp(x) == 0 else "the reference"
        return {"r": None, "frames": n, "reason": f"{which} is constant over {n} frames"}
    r = float(np.corrcoef(x, y)[0, 1])
    return {"r": round(r, 4), "frames": n, "reason": None}


def _blinks(eyelid: np.ndarray | None, au45_c: np.ndarray, at: np.ndarray,
            missing: str) -> dict[str, Any]:
    """Blink event counts, matching, precision/recall/F1 and the unmatched events."""
    if eyelid is None:
        return {"blink_f1": None, "blink_precision": None, "blink_recall": None,
                "blink_events": None, "blink_events_reference": None, "blink_matched": None,
                "blink_frames": 0, "blink_reason": missing,
                "disagreements": {"ours_unmatched": None, "reference_unmatched": None}}
    finite = np.isfinite(eyelid)
    at = at[finite]
    mine = _runs(eyelid[finite] > BLINK_THRESHOLD, at)
    theirs = _runs(au45_c[finite] == 1, at)
    pairs = match_events(mine[:, 0], theirs[:, 0], BLINK_TOLERANCE)
    matched = len(pairs)
    n_mine, n_theirs = len(mine), len(theirs)
    reason = None
    if n_mine + n_theirs == 0:
        reason = f"no blink event on either side over {at.size} frames"
    elif n_mine == 0 or n_theirs == 0:
        reason = f"no blink event {'of ours' if n_mine == 0 else 'in the reference'}"
    free_mine = sorted(set(range(n_mine)) - {i for i, _ in pairs})
    free_theirs = sorted(set(range(n_theirs)) - {j for _, j in pairs})
    return {
        "blink_f1": _ratio(2 * matched, n_mine + n_theirs),
        "blink_precision": _ratio(matched, n_mine),
        "blink_recall": _ratio(matched, n_theirs),
        "blink_events": n_mine,
        "blink_events_reference": n_theirs,
        "blink_matched": matched,
        "blink_frames": int(at.size),
        "blink_reason": reason,
        "disagreements": {"ours_unmatched": mine[free_mine].tolist(),
                          "reference_unmatched": theirs[free_theirs].tolist()},
    }


def _ratio(a: int, b: int) -> float | None:
    return None if b == 0 else round(a / b, 4)


def _runs(flag: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Maximal runs of true flags over consecutive video frames.

    Args:
        flag: (N,) bool per compared frame.
        at: (N,) int increasing video frame indices of those frames; a jump > 1 ends a run.

    Returns:
        (E, 2) int64 [first, last] video frame of each run, in order.
    """
    if at.size == 0:
        return np.zeros((0, 2), np.int64)
    starts = flag & np.r_[True, ~flag[:-1] | (np.diff(at) != 1)]
    ends = flag & np.r_[~flag[1:] | (np.diff(at) != 1), True]
    return np.column_stack([at[starts], at[ends]]).astype(np.int64)


def match_events(onsets: np.ndarray, reference: np.ndarray, tolerance: int
                 ) -> list[tuple[int, int]]:
    """One-to-one matching of event onsets, greedy by distance.

    Every pair (i, j) with |onsets[i] - reference[j]| <= tolerance is a candidate; candidates
    are taken in order of distance (ties: smaller i, then smaller j) when neither event is
    matched yet.

    Args:
        onsets: (E,) int frames of our events.
        reference: (R,) int frames of the reference events.
        tolerance: largest onset distance of a match, frames.

    Returns:
        The matched (i, j) index pairs, sorted by i.
    """
    a = np.asarray(onsets, np.int64)
    b = np.asarray(reference, np.int64)
    distance = np.abs(a[:, None] - b[None, :])
    i, j = np.nonzero(distance <= tolerance)
    order = np.lexsort((j, i, distance[i, j]))
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for k in order:
        if i[k] not in used_a and j[k] not in used_b:
            used_a.add(int(i[k]))
            used_b.add(int(j[k]))
            pairs.append((int(i[k]), int(j[k])))
    return sorted(pairs)
