"""Steadiness: how much a still face shakes on the viewer's screen, and how late the sent face is.

Jitter (``render_jitter``). The project's tracker, run afresh on every image
(``bench.render_nme.track_fresh``), gives 68 points ``q_f`` on the real frame f and ``p_f``
on our rendering of it. For two consecutive video frames f-1, f, both measured, the motion
of each picture is the mean point displacement in units of the real frame's outer-eye
distance ``e = |q_f-1,36 - q_f-1,45|``:

    m_real(f)   = mean_i |q_f,i - q_f-1,i| / e
    m_render(f) = mean_i |p_f,i - p_f-1,i| / e

Whether the real face is still is judged on its trajectory, not on the pair's own points:
with ``Q_f`` the mean of ``q`` over the ``WINDOW`` = 5 frames centred on f (all measured and
consecutive), the face is still at f when

    mean_i |Q_f,i - Q_f-1,i| / e = mean_i |q_f+2,i - q_f-3,i| / (5 e) < STILL = 0.005,

a drift of half a pixel a frame on a face whose eyes are 100 px apart. The test does not
read ``q_f-1`` or ``q_f``, so it does not pick the pairs on which the tracker's noise on the
real frame happened to be small (judged by ``m_real(f)`` itself, the chosen pairs' real
motion is biased low and the ratio high: docs/DESIGN.md §8, "Steadiness").
Over the still pairs S,

    render_jitter_ratio = sum_S m_render(f) / sum_S m_real(f)

and ``still_frames`` = |S|. A ratio of 1 means the rendering shakes as much as the tracker
sees the real face shake; below 1, less. The same tracker measures both, so its own noise is
in both terms.

Lag (``filter_lag``). The sender's tracked points ``t_f`` (the pipeline's input) and the
points the packet describes ``s_f`` (``bench.geometry.project_landmarks``: pose, residuals,
morph, projected into the sender's camera) differ by what the sender's filters did. With
velocities ``v_f = x_f - x_f-1`` (consecutive frames both present, in outer-eye distances of
``t_f-1``), on the moving frames M (``mean_i |v^t_f,i| >= MOVING``, 0.02 a frame), the
normalised cross-correlation

    c(k) = sum_{f in M} <v^t_f, v^s_f+k> / sqrt(sum_M |v^t_f|^2 sum_M |v^s_f+k|^2)

is computed for k = -MAX_LAG..MAX_LAG; the lag is its peak, refined to a fraction of a frame
by the parabola through the peak and its neighbours. 0 means the sent face moves when the
tracked one does; 1, a frame later.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from facewire.bench.geometry import project_landmarks
from facewire.models.landmarks import outer_eye_distance
from facewire.models.rig import Rig

STILL = 0.005  # the real trajectory's motion a frame, outer-eye distances: below it, still
WINDOW = 5  # frames of the centred mean that judges stillness (odd)
MOVING = 0.02  # mean point motion a frame, outer-eye distances: at least it, the face moves
MAX_LAG = 5  # frames searched either side by ``filter_lag``


class Jitter(NamedTuple):
    """``render_jitter``'s result (module docstring).

    Attributes:
        ratio: render_jitter_ratio; None when no still pair was found.
        still_frames: |S|, the still pairs judged.
        real_motion: mean m_real over S (outer-eye distances); None without S.
        render_motion: mean m_render over S; None without S.
    """

    ratio: float | None
    still_frames: int
    real_motion: float | None
    render_motion: float | None


class Lag(NamedTuple):
    """``filter_lag``'s result: ``frames`` (None without enough motion) over ``moving_frames``."""

    frames: float | None
    moving_frames: int


def render_jitter(real: Mapping[int, np.ndarray], rendered: Mapping[int, np.ndarray],
                  indices: Sequence[int]) -> Jitter:
    """The rendering's motion over the real face's on the still frames (module docstring).

    Args:
        real: frame position -> (68, 2) the fresh tracker's points on the real frame.
        rendered: frame position -> (68, 2) its points on our rendering of that frame.
        indices: the video frame index of every position (consecutive frames differ by 1).
    """
    real_m: list[float] = []
    render_m: list[float] = []
    half = WINDOW // 2
    for k in range(half + 1, len(indices) - half):
        span = range(k - half - 1, k + half + 1)  # the frames of Q_k-1 and Q_k
        if indices[span[-1]] - indices[span[0]] != len(span) - 1:
            continue
        if not all(j in real for j in span) or k not in rendered or k - 1 not in rendered:
            continue
        scale = float(outer_eye_distance(real[k - 1]))
        if scale <= 0:
            continue
        drift = float(np.linalg.norm(real[span[-1]] - real[span[0]], axis=1).mean()) / scale
        if drift / WINDOW < STILL:
            real_m.append(float(np.linalg.norm(real[k] - real[k - 1], axis=1).mean()) / scale)
            render_m.append(float(np.linalg.norm(rendered[k] - rendered[k - 1], axis=1).mean())
                            / scale)
    if not real_m or sum(real_m) == 0:
        return Jitter(None, len(real_m), None, None)
    return Jitter(round(sum(render_m) / sum(real_m), 4), len(real_m),
                  round(float(np.mean(real_m)), 6), round(float(np.mean(render_m)), 6))


def filter_lag(tracked: Sequence[np.ndarray | None], sent: Sequence[np.ndarray | None]
               ) -> Lag:
    """How many frames the sent face trails the tracked one (module docstring).

    Args:
        tracked: F (68, 2) the sender tracker's points, or None.
        sent: F (68, 2) the points the packet describes, or None (no pose of its own).
            Positions are consecutive frames of one stream.

    Raises:
        ValueError: the sequences differ in length.
    """
    if len(tracked) != len(sent):
        raise ValueError(f"sent: {len(sent)} frames for {len(tracked)} tracked")
    n = len(tracked)
    vt = np.full((n, 136), np.nan)
    vs = np.full((n, 136), np.nan)
    for f in range(1, n):
        a, b, c, d = tracked[f - 1], tracked[f], sent[f - 1], sent[f]
        if a is None or b is None or c is None or d is None:
            continue
        scale = float(outer_eye_distance(a))
        vt[f] = (b - a).ravel() / scale
        vs[f] = (d - c).ravel() / scale
    speed = np.linalg.norm(vt.reshape(n, 68, 2), axis=2).mean(axis=1)
    moving = np.flatnonzero(np.nan_to_num(speed) >= MOVING)
    moving = moving[(moving >= MAX_LAG) & (moving < n - MAX_LAG)]
    scores = []
    for k in range(-MAX_LAG, MAX_LAG + 1):
        a, b = vt[moving], vs[moving + k]
        ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
        if ok.sum() < 3:
            return Lag(None, int(ok.sum()))
        a, b = a[ok], b[ok]
        scores.append(float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum())))
    c = np.array(scores)
    peak = int(np.argmax(c))
    shift = 0.0
    if 0 < peak < len(c) - 1:
        bend = c[peak - 1] - 2 * c[peak] + c[peak + 1]
        if bend < 0:
            shift = 0.5 * (c[peak - 1] - c[peak + 1]) / bend
    return Lag(round(peak - MAX_LAG + shift, 3), int(moving.size))


def sent_points(rig: Rig, camera: Any, decoded: np.ndarray, posed: np.ndarray
                ) -> list[np.ndarray | None]:
    """The 68 points each packet describes in the sender's image (``bench.geometry``).

    Args:
        rig: the person model's rig.
        camera: the sender's intrinsics (the Hello's camera).
        decoded: (F,) ``FRAME_DTYPE`` decoded packets.
        posed: (F,) bool, frames with a pose of their own; None elsewhere.
    """
    return [project_landmarks(rig, camera, r["rotation"], r["translation"], r["residuals"])
            if ok else None for r, ok in zip(decoded, posed)]


def summary(jitter: Jitter, lag: Lag) -> dict[str, Any]:
    """The report's keys: ``render_jitter_ratio``, ``jitter_still_frames``,
    ``jitter_real_motion``, ``jitter_render_motion`` (outer-eye distances a frame),
    ``jitter_still_below`` (``STILL``), ``filter_lag_frames``, ``lag_moving_frames``."""
    return {"render_jitter_ratio": jitter.ratio, "jitter_still_frames": jitter.still_frames,
            "jitter_real_motion": jitter.real_motion,
            "jitter_render_motion": jitter.render_motion, "jitter_still_below": STILL,
            "filter_lag_frames": lag.frames, "lag_moving_frames": lag.moving_frames}


def lines(r: Mapping[str, Any]) -> list[str]:
    """The report's lines for ``summary``'s keys."""
    if r["render_jitter_ratio"] is None:
        jitter = f"render jitter: not measured ({r['jitter_still_frames']} still frames)"
    else:
        jitter = (f"render jitter: {r['render_jitter_ratio']:.3f} of the real face's on "
                  f"{r['jitter_still_frames']} still frames (the real face's 5-frame mean "
                  f"moving under {r['jitter_still_below']:g} of the eye distance a frame; "
                  f"points moving {r['jitter_real_motion']:.4f} real, "
                  f"{r['jitter_render_motion']:.4f} ours)")
    lag = "n/a" if r["filter_lag_frames"] is None else f"{r['filter_lag_frames']:.2f}"
    return [jitter, f"filter lag: the sent face trails the tracked one by {lag} frames "
                    f"(over {r['lag_moving_frames']} moving frames)"]
