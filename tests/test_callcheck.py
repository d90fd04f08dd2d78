"""``facewire bench call``: two real ``facewire call`` processes on loopback, each sending a
clip looped, sampled for memory and judged on their summaries."""

from __future__ import annotations

from pathlib import Path

import pytest

from facewire.bench.callcheck import CallCheckError, call_check
from facewire.models.infra.sound import read_sound


def test_a_short_call_is_sampled_and_judged(generic_model: Path, person_model: Path,
                                            shared_data: Path) -> None:
    """A sends hdtf_edmarkey (with its sound), B lp_d0 (silent), 60 s: both sides' counts,
    their memory every 10 s and the voice's way from A to B are in the summary (the verdicts
    are the machine's: a loaded one renders too slowly for a call)."""
    video = shared_data / "video"
    summary, lines = call_check(generic_model, str(video / "hdtf_edmarkey.mp4"),
                                person_model, str(video / "lp_d0.mp4"), 60.0)
    assert read_sound(video / "lp_d0.mp4") is None
    assert len(summary["samples"]) >= 3
    assert all(s["rss_mb_a"] > 0 and s["rss_mb_b"] > 0 for s in summary["samples"][1:])
    a_to_b, b_to_a = summary["a_to_b"], summary["b_to_a"]
    for direction in (a_to_b, b_to_a):
        assert direction["ended"] == "stop"  # hung up by the run, not ended on its own
        assert direction["packets_sent"] > 0 and direction["received"] > 0
        assert isinstance(direction["lost"], int)
    assert a_to_b["voice_sent"] > 0 and a_to_b["voice_received"] > 0
    assert a_to_b["voice_corrupt"] == 0 and a_to_b["av_skew_ms_p95"] is not None
    assert not b_to_a["voice_sent"] and not b_to_a["voice_received"]
    assert b_to_a["sync_held"] is False  # no voice: nothing held
    assert summary["memory"]["a"]["rss_mb_max"] >= summary["memory"]["a"]["rss_mb_first"] > 0
    assert lines[-1] in ("passed", "not passed")


def test_a_side_that_cannot_start_ends_the_check_naming_it(person_model: Path,
                                                           shared_data: Path,
                                                           tmp_path: Path) -> None:
    video = str(shared_data / "video" / "lp_d0.mp4")
    with pytest.raises(CallCheckError, match="side b"):
        call_check(person_model, video, tmp_path / "missing.fwm", video, 60.0)
