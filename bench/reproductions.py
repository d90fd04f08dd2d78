"""``facewire bench reproductions``: issues 16's and 24's reproductions, built and scored, one
table.

Each reproduction is a model built from a short, hard enrollment segment of a tuning clip
(``bench.clips``) and scored by ``bench quality`` (``measure_quality``) on frames of the same
clip the model never saw:

    ========  ====================================================  ==========  ===========
    key       enrollment                                             built from  scored on
    ========  ====================================================  ==========  ===========
    occluded  lp_d3.mp4 with dark hair pasted over the mouth in most  0:140 of    lp_d3.mp4
              of its first 84 frames (``bench.occluded``, seed 16)    the copy    140:
    closed    lp_d18.mp4: the mouth never opens wide                  0:60        60:
    motion    openface_multi_face.avi: the man with glasses talks     200:272     272:452
              and laughs, his head at some 220 mm/s (the build's
              self-check measures 218 mm/s, 20 deg/s), 2.4 s
    hand      hdtf_edmarkey.mp4 with a real hand (latentsync_demo2's, 0:120 of    the clip
              ``bench.handover``) held over the mouth and cheek in   the copy    120:
              its first 96 frames
    glasses   retalk_5.mp4: a woman with glasses talks and moves     0:60        60:
              her head, 2.4 s (``sender.enroll.align``)
    ========  ====================================================  ==========  ===========

The motion segment: the clip's front man moves across the frame between frames 130 and
300 (the 90th percentile of the face's speed over 2.4 s windows 180-220 mm/s there,
10-60 mm/s in frames 300-560; before frame 25 the tracker follows another person, after
575 it jumps to him again); its later frames 272:452 include both his fast and his still
parts. Its model (at 67812c8 and until the fix) took a motion-blurred neutral frame and
showed doubled glasses rims and smeared lips (``sender.enroll.registration``).

The table has one row per reproduction, the columns ``COLUMNS``: the rendering's render
NME over all 68 points and over the mouth, face SSIM, the packets' held-out NME, and the
x264 reference's render NME and SSIM at about our bit rate (``bench.quality``'s names).
``--models DIR`` scores ``DIR/KEY.fwm`` where it exists instead of building (a model
built by another commit, say), ``--limit N`` scores only the first N held-out frames (a
quick check of the plumbing), ``--only KEY`` runs some. Heavy: five builds (15-90 s each
on the shared machine) and about 740 scored frames (some 0.3 s each, the x264 reference's
two passes included).

    facewire bench reproductions --data ../shared/data [--work DIR] [--models DIR] [--json]
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from facewire.bench.occluded import occlude
from facewire.bench.quality import measure_quality
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import range_text
from facewire.protocol.errors import FacewireError


class ReproductionError(FacewireError, ValueError):
    """A reproduction cannot be run: a clip is missing or a key is unknown (named)."""


@dataclass(frozen=True)
class Reproduction:
    """One reproduction: ``clip`` in the data's ``video`` folder, the model built from
    ``enrol`` (of the occluded copy when ``occluded``, of the copy with the hand ``hand``
    of ``bench.handover`` over the first ``HAND_PART`` of it when ``hand``), scored on
    ``score``."""

    key: str
    title: str
    clip: str
    enrol: slice
    score: slice
    occluded: bool = False
    hand: str | None = None


REPRODUCTIONS = (
    Reproduction("occluded", "occluded mouth", "lp_d3.mp4", slice(0, 140), slice(140, None),
                 occluded=True),
    Reproduction("closed", "no open mouth", "lp_d18.mp4", slice(0, 60), slice(60, None)),
    Reproduction("motion", "fast head motion", "openface_multi_face.avi", slice(200, 272),
                 slice(272, 452)),
    Reproduction("hand", "real hand on mouth", "hdtf_edmarkey.mp4", slice(0, 120),
                 slice(120, None), hand="back"),
    Reproduction("glasses", "glasses, short", "retalk_5.mp4", slice(0, 60), slice(60, None)),
)
HAND_PART = 0.8
COLUMNS = ("render_nme_mean", "render_nme_mouth", "face_ssim_mean", "nme_heldout_mean",
           "h264_render_nme_mean", "h264_face_ssim_mean")
_HEADS = ("render NME", "mouth", "SSIM", "held-out NME", "x264 NME", "x264 SSIM")


def run_reproductions(data: str | os.PathLike[str], work: str | os.PathLike[str],
                      models: str | os.PathLike[str] | None = None,
                      only: Sequence[str] | None = None, limit: int | None = None,
                      progress: Progress = no_progress) -> dict[str, Any]:
    """Build and score the reproductions (module docstring).

    Args:
        data: the shared data folder (its ``video`` folder holds the clips).
        work: a folder for the occluded copy and the models built.
        models: a folder of models to score as they are (``KEY.fwm``); the others are built.
        only: the keys to run (``REPRODUCTIONS``'); all when None.
        limit: score only the first ``limit`` (> 0) held-out frames of each.
        progress: wraps an iterable to show progress: ``progress(items, label, total)``.

    Returns:
        ``{"rows": [{"key", "title", "clip", "enrol", "score", "model", "built", COLUMNS...}],
        "columns": COLUMNS}``, percent for the NMEs.

    Raises:
        ReproductionError: an unknown key, a bad limit or a missing clip.
    """
    from facewire.bench.handover import hand_over
    from facewire.sender.enroll.build import build_model

    keys = [r.key for r in REPRODUCTIONS]
    unknown = sorted(set(only or ()) - set(keys))
    if unknown:
        raise ReproductionError(f"--only: unknown reproduction {unknown[0]!r}, expected one "
                                f"of {', '.join(keys)}")
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int)
                              or limit < 1):
        raise ReproductionError(f"--limit: expected a positive frame count, got {limit!r}")
    video, out = Path(data) / "video", Path(work)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for r in REPRODUCTIONS:
        if only and r.key not in only:
            continue
        clip = video / r.clip
        if not clip.is_file():
            raise ReproductionError(f"{clip}: the clip of reproduction {r.key!r} is missing")
        given = None if models is None else Path(models) / f"{r.key}.fwm"
        model, built = (given, False) if given is not None and given.is_file() else (
            out / f"{r.key}.fwm", True)
        if built:
            if r.occluded:
                copy = occlude(clip, out / f"{r.key}.mp4", r.enrol)
                build_model(copy.path, model, progress=progress)
            elif r.hand is not None:
                held = hand_over(clip, out / f"{r.key}.mp4", r.enrol, HAND_PART, r.hand,
                                 data=video)
                build_model(held.path, model, progress=progress)
            else:
                build_model(clip, model, r.enrol, progress=progress)
        score = r.score if limit is None else slice(
            r.score.start, r.score.start + limit if r.score.stop is None
            else min(r.score.stop, r.score.start + limit))
        result = measure_quality(model, clip, score, progress)
        rows.append({"key": r.key, "title": r.title, "clip": r.clip,
                     "enrol": range_text(r.enrol), "score": range_text(score),
                     "model": str(model), "built": built,
                     **{c: result.get(c) for c in COLUMNS}})
    return {"rows": rows, "columns": list(COLUMNS)}


def format_table(summary: dict[str, Any]) -> list[str]:
    """The table's lines: a header, then one row per reproduction (NMEs in percent)."""
    lines = [f"{'reproduction':<18} {'clip':<24} {'enrol':>8} {'scored':>8} "
             + " ".join(f"{h:>12}" for h in _HEADS)]
    for row in summary["rows"]:
        cells = [f"{'-' if row[c] is None else format(row[c], '.4f' if 'ssim' in c else '.3f')}"
                 for c in COLUMNS]
        lines.append(f"{row['title']:<18} {row['clip']:<24} {row['enrol']:>8} "
                     f"{row['score']:>8} " + " ".join(f"{c:>12}" for c in cells))
    return lines
