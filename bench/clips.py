"""The shared clips split in two: those the system is tuned on, and those that judge it.

The pose weights and filters (``sender.pose``), the lift (``sender.lift``), the heuristics'
thresholds (``sender.heuristics``), the classifier's floor (``sender.classify``), the
tracker's settings (``sender.tracker``) and the rig's phantoms (``models.rig``,
``sender.enroll.fit``) were chosen by measuring on the clips of ``TUNING_CLIPS`` in
``../shared/data/video`` (their docstrings name them). A figure measured on those clips says
how well the tuning fits them, not how well the system works; ``EVALUATION_CLIPS`` are the
clips no tuning has looked at, kept for judging: lp_d9 (glasses, raised brows, smile, cheek
puff), lp_d19 (glasses, smile), openface_lighting (strong lighting changes), lp_d8 (frowns,
mouth shapes), three talking heads of the HDTF kind (hdtf_radio34, hdtf_aoc, retalk_2) and
aniportrait_ref (a talking woman). The tuning set holds the clips whose material the
enrollment's reproductions are cut from (real hands: mediapipe_selfie, latentsync_demo2;
glasses on a moving head: retalk_5; strong emotion: retalk_4; eye work: lp_d7). Tune only on
the first set; a test fails when the system's code names a clip of the second.

Protocol of an evaluation (``split_frames``): the person model is built from the clip's first
``ENROLL_FRACTION`` of frames, K = floor(0.4 N) of the N frames that decode (a container may
state another count, or none: openface_lighting.wmv decodes 88), and ``bench quality`` scores
frames K..N-1, which the model never saw:

    facewire model build V --frames 0:K -o M.fwm
    facewire bench quality --model M.fwm --source V --frames K: --json
"""

from __future__ import annotations

TUNING_CLIPS = ("lp_d0.mp4", "lp_d3.mp4", "lp_d14.mp4", "lp_d18.mp4", "hdtf_katiehill.mp4",
                "openface_default.wmv", "openface_gaze.avi", "openface_multi_face.avi",
                "hamilton_short.mp4", "lp_d7.mp4", "obama_speaking.mp4", "hdtf_edmarkey.mp4",
                "hdtf_radio2.mp4", "retalk_1.mp4", "retalk_4.mp4", "retalk_5.mp4",
                "mediapipe_selfie.mp4", "latentsync_demo2.mp4")
EVALUATION_CLIPS = ("lp_d9.mp4", "lp_d19.mp4", "openface_lighting.wmv", "lp_d8.mp4",
                    "hdtf_radio34.mp4", "hdtf_aoc.mp4", "retalk_2.mp4", "aniportrait_ref.mp4")
ENROLL_FRACTION = 0.4


def subset(name: str) -> str | None:
    """``"tuning"`` or ``"evaluation"`` for a shared clip's file name, else None."""
    if name in TUNING_CLIPS:
        return "tuning"
    if name in EVALUATION_CLIPS:
        return "evaluation"
    return None


def split_frames(count: int) -> tuple[slice, slice]:
    """The enrollment frames and the scored frames of a clip of ``count`` frames.

    Raises:
        ValueError: fewer than 3 frames (nothing to enrol from, or nothing to score).
    """
    if isinstance(count, bool) or not isinstance(count, int) or count < 3:
        raise ValueError(f"count: expected a frame count of at least 3, got {count!r}")
    enrol = int(count * ENROLL_FRACTION)
    return slice(0, enrol), slice(enrol, None)
