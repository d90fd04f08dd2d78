"""The shared clips split into tuning and evaluation (``bench.clips``): every clip in one
subset, no tuning that names an evaluation clip, and the system judged on one it never saw."""

from __future__ import annotations

from pathlib import Path

import pytest

from facewire.bench.clips import EVALUATION_CLIPS, TUNING_CLIPS, split_frames, subset
from facewire.bench.quality import TARGET_NME_HELDOUT, format_quality, quality
from facewire.models.infra.video import read_frames
from facewire.sender.enroll.build import build_model

ROOT = Path(__file__).resolve().parents[1]
TUNED = ("models", "sender", "receiver", "protocol")  # the code whose settings were tuned


def test_every_shared_clip_is_in_exactly_one_subset(shared_data: Path) -> None:
    clips = sorted(p.name for p in (shared_data / "video").iterdir() if p.suffix != ".md")
    assert not set(TUNING_CLIPS) & set(EVALUATION_CLIPS)
    assert sorted(TUNING_CLIPS + EVALUATION_CLIPS) == clips
    assert [subset(c) for c in ("lp_d0.mp4", "lp_d9.mp4", "other.mp4")] == \
        ["tuning", "evaluation", None]


def test_no_tuned_code_names_an_evaluation_clip() -> None:
    """Tuning cites the clips it measured on; none of them may be an evaluation clip."""
    sources = [p for folder in TUNED for p in (ROOT / folder).rglob("*.py")]
    assert len(sources) > 30
    for path in sources:
        text = path.read_text()
        for clip in EVALUATION_CLIPS:
            assert Path(clip).stem not in text, f"{path.relative_to(ROOT)} names {clip}"


def test_split_frames() -> None:
    assert split_frames(587) == (slice(0, 234), slice(234, None))
    assert split_frames(3) == (slice(0, 1), slice(1, None))
    for bad in (2, 0, 2.5, True):
        with pytest.raises(ValueError, match="count"):
            split_frames(bad)


def test_the_system_on_an_evaluation_clip(shared_data: Path, tmp_path: Path) -> None:
    """openface_lighting, which no tuning has seen: a model from its first 40 %, scored on
    the rest, meets the held-out NME target and beats the pose alone (measured: 2.2 % and
    2.7 %). Its face SSIM is below x264's at 2.5 times our rate (0.77 against 0.82): light
    that changes is what a texture captured once cannot follow, so that is not asserted."""
    video = shared_data / "video" / "openface_lighting.wmv"
    enrol, scored = split_frames(sum(1 for _ in read_frames(video)))  # 88: the file says 0
    model = tmp_path / "lighting.fwm"
    build_model(video, model, frames=enrol)
    r, lines = quality(model, video, frames=scored)
    assert r["subset"] == "evaluation" and r["measured_frames"] == 53
    assert r["nme_heldout_mean"] <= TARGET_NME_HELDOUT
    assert r["nme_heldout_mean"] < r["nme_rigid_only_mean"]
    assert lines == format_quality(r).splitlines()
    assert "clip: in the evaluation subset (bench.clips): no tuning has seen it" in lines
