"""``facewire bench clips``: every single-person shared clip, enrolled on its first part and
scored on the rest, x264 at its floor beside it: one table.

Each clip of ``bench.clips`` (both subsets) but ``MULTI_PERSON`` is evaluated by the clips'
protocol (``bench.clips.split_frames``): the model is built from its first 40 % of frames
(``facewire model build V --frames 0:K``) and scored by ``bench quality`` on frames K..N-1
(``measure_quality``; learning off: the model as built), which bring the x264 reference at
its lowest rate (``bench.quality``). A row holds ``COLUMNS``; its verdicts:

- ``render_ok``: our render NME at or below x264's (``bench quality``'s
  ``met.render_nme_at_most_h264``: the tracker lost our face on no more frames than x264's,
  and our mean is at most x264's, or x264's face was never found);
- ``ssim_ok``: our face SSIM at or above x264's (``met.face_ssim_above_h264``).

The summary says how many rows pass each (``render_ok_clips``, ``ssim_ok_clips``,
``clips``) and the share of clips whose SSIM passes (``ssim_ok_share``; issue 24's target is
every clip for the render NME and 90 % for the SSIM).

``--models DIR`` scores ``DIR/<clip stem>.fwm`` where it exists instead of building (a model
of another commit), ``--only CLIP`` runs some clips, ``--limit N`` scores only the first N
held-out frames of each (a quicker, noisier table: say so when quoting it). Heavy: one build
per clip (15-90 s each) and some 0.3 s per scored frame.

    facewire bench clips --data ../shared/data [--work DIR] [--models DIR] [--limit N] [--json]
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from facewire.bench.clips import EVALUATION_CLIPS, TUNING_CLIPS, split_frames, subset
from facewire.bench.quality import measure_quality
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.video import decoded_once, range_text, read_frames
from facewire.protocol.errors import FacewireError

MULTI_PERSON = ("openface_multi_face.avi",)
COLUMNS = ("nme_heldout_mean", "render_nme_mean", "h264_render_nme_mean", "face_ssim_mean",
           "h264_face_ssim_mean", "h264_kbps")
_HEADS = ("held-out NME", "render NME", "x264 NME", "SSIM", "x264 SSIM", "x264 kbit/s")


class ClipTableError(FacewireError, ValueError):
    """A clip is missing or unknown, or a bad limit (named)."""


def single_person_clips() -> tuple[str, ...]:
    """The shared clips the table covers, tuning first, each subset in its order."""
    return tuple(c for c in TUNING_CLIPS + EVALUATION_CLIPS if c not in MULTI_PERSON)


def run_clip_table(data: str | os.PathLike[str], work: str | os.PathLike[str],
                   models: str | os.PathLike[str] | None = None,
                   only: Sequence[str] | None = None, limit: int | None = None,
                   progress: Progress = no_progress) -> dict[str, Any]:
    """Build and score every clip's row (module docstring).

    Returns:
        ``{"rows": [{"clip", "subset", "frames", "enrol", "score", "model", "built",
        COLUMNS..., "render_ok", "ssim_ok"}], "columns", "clips", "render_ok_clips",
        "ssim_ok_clips", "ssim_ok_share", "limit", "unit"}`` (NMEs in percent).

    Raises:
        ClipTableError: an unknown clip in ``only``, a missing clip, or a bad limit.
    """
    from facewire.sender.enroll.build import build_model

    clips = single_person_clips()
    unknown = sorted(set(only or ()) - set(clips))
    if unknown:
        raise ClipTableError(f"--only: {unknown[0]!r} is not a single-person shared clip")
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int)
                              or limit < 1):
        raise ClipTableError(f"--limit: expected a positive frame count, got {limit!r}")
    video, out = Path(data) / "video", Path(work)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in clips:
        if only and name not in only:
            continue
        clip = video / name
        if not clip.is_file():
            raise ClipTableError(f"{clip}: a shared clip of the table is missing")
        given = None if models is None else Path(models) / f"{clip.stem}.fwm"
        model, built = (given, False) if given is not None and given.is_file() else (
            out / f"{clip.stem}.fwm", True)
        with decoded_once(clip):  # counted, built from and scored with one decoding
            count = sum(1 for _ in read_frames(clip))  # what decodes (a container may differ)
            enrol, score = split_frames(count)
            if limit is not None:
                score = slice(score.start, min(count, score.start + limit))
            if built:
                build_model(clip, model, enrol, progress=progress)
            result = measure_quality(model, clip, score, progress)
        row = {"clip": name, "subset": subset(name), "frames": count,
               "enrol": range_text(enrol), "score": range_text(score), "model": str(model),
               "built": built, **{c: result.get(c) for c in COLUMNS}}
        row["render_ok"] = result["met"]["render_nme_at_most_h264"]
        row["ssim_ok"] = result["met"]["face_ssim_above_h264"]
        rows.append(row)
    ssim_ok = sum(bool(r["ssim_ok"]) for r in rows)
    return {"rows": rows, "columns": list(COLUMNS), "clips": len(rows),
            "render_ok_clips": sum(bool(r["render_ok"]) for r in rows),
            "ssim_ok_clips": ssim_ok,
            "ssim_ok_share": round(ssim_ok / len(rows), 3) if rows else None,
            "limit": limit, "unit": {"nme": "percent of the eye distance"}}


def format_clip_table(summary: dict[str, Any]) -> list[str]:
    """The table's lines: a header, a row per clip (NMEs in percent), and the counts."""
    lines = [f"{'clip':<24} {'subset':<10} {'scored':>9} "
             + " ".join(f"{h:>12}" for h in _HEADS) + "  verdict"]
    for row in summary["rows"]:
        cells = [f"{'-' if row[c] is None else format(row[c], '.4f' if 'ssim' in c else '.3f')}"
                 for c in COLUMNS]
        verdict = ", ".join(v for v, ok in (("NME<=x264", row["render_ok"]),
                                            ("SSIM>=x264", row["ssim_ok"])) if ok) or "-"
        lines.append(f"{row['clip']:<24} {row['subset'] or '-':<10} {row['score']:>9} "
                     + " ".join(f"{c:>12}" for c in cells) + f"  {verdict}")
    lines.append(f"render NME at or below x264's on {summary['render_ok_clips']} of "
                 f"{summary['clips']} clips; face SSIM at or above x264's on "
                 f"{summary['ssim_ok_clips']} ({summary['ssim_ok_share']})"
                 + (f"; first {summary['limit']} held-out frames only" if summary["limit"]
                    else ""))
    return lines
