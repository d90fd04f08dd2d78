"""The generic head's samples placed by design, as ray directions (the half x >= 0).

- the eyelid margin loop and the inner lip lines: the boundaries of the openings, which
  become mesh edges;
- two rows parallel to each (1.4 and 3.0 mm outside the margin, 1.5 and 3.2 mm beside the lip
  lines; offsets along the polyline's normal), so that the triangles along the openings are
  regular;
- the landmarks seen from the front (``anatomy``), and the jaw line 8-16: the frontal
  silhouette of the face without neck and ears (in front of z = 10; found by bisection along
  27 lines in the (x, y) plane from (0, -45)), evenly spaced along it from the chin (8) up to
  eye height (y = -2), moved 0.5 mm inside;
- the phantoms, on the rays through their designed points.

A point designed by where it is seen from the front, (x, y), becomes the direction of the
ray through the skin point that a line along z through (x, y) meets first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facewire.models.head.anatomy import (
    FRONT_LANDMARKS,
    LIP_LANDMARK_STEP,
    LIP_STEPS,
    MARGIN_LANDMARKS,
    PHANTOM_POINTS,
    eyelid_margin_xy,
    lip_lines,
    outer_lip_xy,
)
from facewire.models.head.primitives import unit
from facewire.models.head.rays import directions_to, front_directions, seen_from_front
from facewire.models.head.skin import face_field


def _offset_rows(xy: np.ndarray, closed: bool, left_normal: bool,
                 distances: tuple[float, ...]) -> np.ndarray:
    """Copies of a 2D polyline (N, 2) moved by each distance along its normal (the left-hand
    one if ``left_normal``); rows of regular samples along the eye and lip openings."""
    nxt = np.roll(xy, -1, axis=0) if closed else np.concatenate([xy[1:], xy[-1:]])
    prv = np.roll(xy, 1, axis=0) if closed else np.concatenate([xy[:1], xy[:-1]])
    t = unit(nxt - prv)
    n = np.column_stack([-t[:, 1], t[:, 0]]) * (1.0 if left_normal else -1.0)
    return np.concatenate([xy + d * n for d in distances])


_JAW_CENTRE = np.array([0.0, -45.0])
_JAW_TOP_Y = -2.0  # height of jaw points 0 and 16


def _jaw_contour() -> np.ndarray:
    """(x, y) of jaw points 8..16: the frontal silhouette of the face (no neck, no ears, in
    front of z = 10), from the chin (x = 0) up to eye height, evenly spaced along it."""

    def face(p: np.ndarray) -> np.ndarray:
        return face_field(np.column_stack([np.abs(p[:, 0]), p[:, 1], p[:, 2]]))

    angles = np.radians(np.linspace(-90.0, 40.0, 27))
    u = np.column_stack([np.cos(angles), np.sin(angles)])
    lo, hi = np.full(len(u), 20.0), np.full(len(u), 140.0)
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        hit = seen_from_front(_JAW_CENTRE + u * mid[:, None], face, 10.0)
        lo, hi = np.where(hit, mid, lo), np.where(hit, hi, mid)
    pts = _JAW_CENTRE + u * lo[:, None]
    k = int(np.argmax(pts[:, 1] > _JAW_TOP_Y))
    f = (_JAW_TOP_Y - pts[k - 1, 1]) / (pts[k, 1] - pts[k - 1, 1])
    pts = np.concatenate([pts[:k], [pts[k - 1] + f * (pts[k] - pts[k - 1])]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s = np.linspace(0.0, arc[-1], 9)
    out = np.column_stack([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])])
    out[0, 0] = 0.0
    # Half a millimetre inside the silhouette, so the skin point seen from the front is the
    # face at its edge and not the neck behind it.
    inward = unit(_JAW_CENTRE - out)
    return out + 0.5 * inward


@dataclass(frozen=True)
class FixedSamples:
    """The samples placed by design: margin and lip lines (the openings' boundaries), the
    rows beside them, landmarks and phantoms."""

    dirs: np.ndarray             # (K, 3) unit directions: margin, lip lines, named, rows
    margin: np.ndarray           # indices of the margin loop (counter-clockwise from front)
    lip: np.ndarray              # indices of the half lip loop, 62 .. corner 64 .. 66
    named: dict[int | str, int]  # landmark index or phantom name -> index

    def segments(self) -> np.ndarray:
        """(S, 2, 3): the margin and lip-line segments that must be mesh edges."""
        m, lip = self.dirs[self.margin], self.dirs[self.lip]
        return np.concatenate([np.stack([m, np.roll(m, -1, axis=0)], axis=1),
                               np.stack([lip[:-1], lip[1:]], axis=1)])

    def holes(self) -> list[np.ndarray]:
        """The eye opening and the lip slit (closed through the midline from 66 to 62)."""
        return [self.dirs[self.margin], self.dirs[self.lip]]


def fixed_samples() -> FixedSamples:
    """The samples placed by design (module docstring), in the order margin, lip lines,
    landmarks seen from the front, phantoms, rows."""
    margin_xy = eyelid_margin_xy()
    upper_xy, lower_xy = lip_lines()
    lip_xy = np.concatenate([upper_xy, lower_xy])
    lip_rows = _offset_rows(lip_xy, False, True, (1.5, 3.2)).reshape(2, len(lip_xy), 2)
    lip_rows[:, [0, -1], 0] = 0.0  # the rows start and end on the midline
    rows_xy = np.concatenate([_offset_rows(margin_xy, True, False, (1.4, 3.0)),
                              lip_rows.reshape(-1, 2)])
    front = dict(FRONT_LANDMARKS)
    front.update(outer_lip_xy())
    front.update(zip(range(8, 17), map(tuple, _jaw_contour())))
    front_xy = np.array(list(front.values()))
    all_xy = np.concatenate([margin_xy, lip_xy, front_xy, rows_xy])
    seen = front_directions(all_xy)
    seen[all_xy[:, 0] == 0.0, 0] = 0.0
    n_margin, n_lip, n_front = len(margin_xy), len(lip_xy), len(front_xy)
    phantoms = directions_to(np.array(list(PHANTOM_POINTS.values())))
    cut = n_margin + n_lip + n_front
    dirs = np.concatenate([seen[:cut], phantoms, seen[cut:]])

    margin = np.arange(n_margin)
    lip = n_margin + np.arange(n_lip)
    keys = list(front) + list(PHANTOM_POINTS)
    named: dict[int | str, int] = {k: n_margin + n_lip + i for i, k in enumerate(keys)}
    named.update({lm: int(margin[step]) for lm, step in MARGIN_LANDMARKS.items()})
    upper, lower = lip[:LIP_STEPS + 1], lip[LIP_STEPS + 1:]
    named.update({62: int(upper[0]), 63: int(upper[LIP_LANDMARK_STEP]), 64: int(upper[-1]),
                  65: int(lower[-1 - LIP_LANDMARK_STEP]), 66: int(lower[-1])})
    return FixedSamples(dirs, margin, lip, named)
