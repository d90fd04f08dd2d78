"""Readers for 68-point landmark annotations used in evaluation: iBUG ``.pts`` and OpenFace CSV.

Coordinates come out in 0-based pixel coordinates (x right, y down, the centre of the top-left
pixel at (0, 0)), the tracker's convention.

iBUG ``.pts`` (300-W): text, 1-based pixel coordinates (the top-left pixel's centre is (1, 1));
one is subtracted on reading::

    version: 1
    n_points:  68
    {
    x_0 y_0
    ...          (68 lines, "x y" as decimal numbers)
    x_67 y_67
    }

OpenFace 2.x CSV (FeatureExtraction / FaceLandmarkVid with ``-2Dfp``): comma-separated, one
header line; OpenFace writes ", " between fields, so column names are stripped of spaces.
Columns read: ``frame`` (1-based frame number), ``success`` (0/1), ``timestamp`` (seconds),
``confidence``, and the 2D landmarks ``x_0 .. x_67``, ``y_0 .. y_67`` (0-based pixels).
Rows where OpenFace failed (``success`` 0) carry meaningless landmarks (OpenFace writes
zeros): they are returned as NaN so that they cannot be used by mistake. Files from the
multi-face tools (more than one ``face_id``) are rejected.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facewire.models.landmarks import N_LANDMARKS
from facewire.protocol.errors import FacewireError

MAX_PTS_BYTES = 64 * 1024
MAX_CSV_BYTES = 1 << 30


class LandmarkFileError(FacewireError, ValueError):
    """A landmark file is missing, too large or malformed; the message names file and place."""


def _read_text(path: str | os.PathLike, limit: int) -> str:
    """The whole file as text, refusing files larger than ``limit`` bytes."""
    p = Path(path)
    try:
        size = p.stat().st_size
    except OSError as e:
        raise LandmarkFileError(f"{p}: cannot read ({e.strerror})") from e
    if size > limit:
        raise LandmarkFileError(f"{p}: {size} bytes, more than the {limit} allowed")
    try:
        return p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise LandmarkFileError(f"{p}: not UTF-8 text (byte {e.start})") from e


def _number(text: str, where: str) -> float:
    """A finite decimal number, or an error naming ``where``."""
    try:
        value = float(text)
    except ValueError:
        raise LandmarkFileError(f"{where}: expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise LandmarkFileError(f"{where}: expected a finite number, got {text!r}")
    return value


def read_pts(path: str | os.PathLike) -> np.ndarray:
    """Read an iBUG 68-point ``.pts`` file.

    Args:
        path: the file.

    Returns:
        (68, 2) float32 landmarks, 0-based pixel coordinates (x, y).

    Raises:
        LandmarkFileError: unreadable, too large, or not a 68-point ``.pts`` (names the line).
    """
    lines = _read_text(path, MAX_PTS_BYTES).splitlines()
    # (line number, stripped text) of the non-blank lines
    rows = [(n + 1, line.strip()) for n, line in enumerate(lines) if line.strip()]
    header = [("version", "1"), ("n_points", str(N_LANDMARKS))]
    if len(rows) < len(header):
        raise LandmarkFileError(f"{path}: expected a 'version: 1' / 'n_points: 68' header")
    for (n, text), (key, value) in zip(rows, header):
        k, sep, v = text.partition(":")
        if not sep or k.strip() != key or v.strip() != value:
            raise LandmarkFileError(f"{path}:{n}: expected '{key}: {value}', got {text!r}")
    expected = len(header) + 1 + N_LANDMARKS + 1
    if len(rows) != expected:
        raise LandmarkFileError(
            f"{path}: expected {expected} non-blank lines (header, '{{', {N_LANDMARKS} points, "
            f"'}}'), got {len(rows)}"
        )
    for (n, text), brace in ((rows[2], "{"), (rows[-1], "}")):
        if text != brace:
            raise LandmarkFileError(f"{path}:{n}: expected '{brace}', got {text!r}")
    points = np.empty((N_LANDMARKS, 2), dtype=np.float32)
    for i, (n, text) in enumerate(rows[3:-1]):
        fields = text.split()
        if len(fields) != 2:
            raise LandmarkFileError(f"{path}:{n}: expected 'x y' for point {i}, got {text!r}")
        points[i] = [_number(f, f"{path}:{n}") for f in fields]
    return points - np.float32(1.0)


@dataclass(frozen=True, eq=False)
class OpenFaceTrack:
    """Per-frame output of OpenFace for one face.

    Attributes:
        frame: (N,) int64 frame numbers as OpenFace writes them (1-based).
        timestamp: (N,) float64 seconds.
        confidence: (N,) float32 in [0, 1].
        success: (N,) bool, OpenFace found the face.
        landmarks: (N, 68, 2) float32, 0-based pixels; NaN where ``success`` is False.
    """

    frame: np.ndarray
    timestamp: np.ndarray
    confidence: np.ndarray
    success: np.ndarray
    landmarks: np.ndarray


def read_openface_csv(path: str | os.PathLike) -> OpenFaceTrack:
    """Read an OpenFace 2.x CSV with 2D landmarks (format in the module docstring).

    Args:
        path: the file.

    Returns:
        An ``OpenFaceTrack`` with one entry per data row, in file order.

    Raises:
        LandmarkFileError: unreadable, too large, a needed column is missing, or a cell is
            malformed (names the line and column).
    """
    text = _read_text(path, MAX_CSV_BYTES)
    reader = csv.reader(io.StringIO(text))
    names, column = _openface_header(path, next(reader, None))
    coords = [f"{axis}_{i}" for axis in "xy" for i in range(N_LANDMARKS)]
    needed = ["frame", "timestamp", "confidence", "success", *coords]
    needed += ["face_id"] if "face_id" in column else []

    frames: list[int] = []
    times: list[float] = []
    confs: list[float] = []
    oks: list[bool] = []
    values: list[list[float]] = []
    face_ids: set[str] = set()
    for row in reader:
        if not row:
            continue
        where = f"{path}:{reader.line_num}"
        if len(row) != len(names):
            raise LandmarkFileError(f"{where}: {len(row)} fields, header has {len(names)}")
        cells = {name: row[column[name]].strip() for name in needed}
        frame = _number(cells["frame"], f"{where}: column 'frame'")
        success = _number(cells["success"], f"{where}: column 'success'")
        if frame != int(frame) or success not in (0.0, 1.0):
            raise LandmarkFileError(
                f"{where}: expected an integer frame and success 0 or 1, "
                f"got frame {cells['frame']!r}, success {cells['success']!r}"
            )
        if "face_id" in cells:
            face_ids.add(cells["face_id"])
            if len(face_ids) > 1:
                raise LandmarkFileError(
                    f"{where}: more than one face_id ({', '.join(sorted(face_ids))}); "
                    "multi-face OpenFace output is not supported"
                )
        frames.append(int(frame))
        times.append(_number(cells["timestamp"], f"{where}: column 'timestamp'"))
        confs.append(_number(cells["confidence"], f"{where}: column 'confidence'"))
        oks.append(success == 1.0)
        if success == 1.0:
            values.append([_number(cells[c], f"{where}: column {c!r}") for c in coords])
        else:
            values.append([math.nan] * len(coords))

    if not frames:
        raise LandmarkFileError(f"{path}: no data rows after the header")
    xy = np.array(values, dtype=np.float32).reshape(len(frames), 2, N_LANDMARKS)
    return OpenFaceTrack(
        frame=np.array(frames, dtype=np.int64),
        timestamp=np.array(times, dtype=np.float64),
        confidence=np.array(confs, dtype=np.float32),
        success=np.array(oks, dtype=bool),
        landmarks=np.ascontiguousarray(xy.transpose(0, 2, 1)),
    )


def _openface_header(path: str | os.PathLike, header: list[str] | None
                     ) -> tuple[list[str], dict[str, int]]:
    """The CSV's column names and each name's index; every column the reader needs must be
    there, once."""
    if not header:
        raise LandmarkFileError(f"{path}: empty file, expected an OpenFace CSV header")
    names = [h.strip() for h in header]
    column = {name: j for j, name in enumerate(names)}
    if len(column) != len(names):
        raise LandmarkFileError(f"{path}:1: duplicate column names")
    missing = [c for c in ("frame", "timestamp", "confidence", "success") if c not in column]
    if missing:
        raise LandmarkFileError(f"{path}:1: missing column(s) {', '.join(missing)}")
    absent = [f"{axis}_{i}" for axis in "xy" for i in range(N_LANDMARKS)
              if f"{axis}_{i}" not in column]
    if absent:
        raise LandmarkFileError(
            f"{path}:1: no 2D landmark columns x_0..x_{N_LANDMARKS - 1}, y_0..y_{N_LANDMARKS - 1} "
            f"({len(absent)} of {2 * N_LANDMARKS} missing, first {absent[0]!r}); "
            "run OpenFace with -2Dfp"
        )
    return names, column
