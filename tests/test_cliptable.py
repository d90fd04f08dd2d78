"""``bench clips``: which clips its table covers, and its refusals (the table itself is a long
run: ``facewire bench clips --data ../shared/data``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from facewire.bench.clips import EVALUATION_CLIPS, TUNING_CLIPS
from facewire.bench.cliptable import ClipTableError, run_clip_table, single_person_clips
from facewire.cli import main


def test_the_table_covers_every_single_person_clip_on_disk(shared_data: Path) -> None:
    clips = single_person_clips()
    on_disk = {p.name for p in (shared_data / "video").iterdir()}
    assert set(clips) == on_disk - {"openface_multi_face.avi"}
    assert set(clips) <= set(TUNING_CLIPS + EVALUATION_CLIPS)


@pytest.mark.parametrize(("only", "limit", "match"), [
    (["openface_multi_face.avi"], None, "not a single-person shared clip"),
    (["nope.mp4"], None, "nope.mp4"),
    (None, 0, "--limit"),
])
def test_bad_options_are_refused_before_any_work(tmp_path: Path, only: list[str] | None,
                                                 limit: int | None, match: str) -> None:
    with pytest.raises(ClipTableError, match=match):
        run_clip_table(tmp_path, tmp_path / "work", only=only, limit=limit)
    assert not (tmp_path / "work").exists() or not any((tmp_path / "work").iterdir())


def test_a_missing_clip_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "video").mkdir()
    assert main(["bench", "clips", "--data", str(tmp_path), "--only", "retalk_2.mp4"]) != 0
    assert "retalk_2.mp4: a shared clip of the table is missing" in capsys.readouterr().err
