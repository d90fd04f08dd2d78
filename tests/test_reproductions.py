"""``facewire bench reproductions``: the table's plumbing (the heavy run is a measurement).

The generic model stands in for the built ones (``--models``) and only two held-out frames
are scored (``--limit``), so the test runs the real scoring path in seconds.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from facewire.bench.reproductions import (
    COLUMNS,
    REPRODUCTIONS,
    ReproductionError,
    format_table,
    run_reproductions,
)


def test_the_reproductions_are_tuning_clips_with_disjoint_ranges():
    from facewire.bench.clips import subset

    for r in REPRODUCTIONS:
        assert subset(r.clip) == "tuning", r.clip
        assert r.enrol.stop is not None and r.enrol.stop <= r.score.start, r.key


def test_the_table_scores_given_models(shared_data: Path, generic_model: Path,
                                       tmp_path: Path):
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(generic_model, models / "motion.fwm")
    summary = run_reproductions(shared_data, tmp_path / "work", models=models,
                                only=["motion"], limit=2)
    (row,) = summary["rows"]
    assert row["key"] == "motion" and not row["built"] and row["score"] == "272:274"
    assert set(COLUMNS) <= set(row)
    assert isinstance(row["nme_heldout_mean"], float)
    lines = format_table(summary)
    assert len(lines) == 2 and "fast head motion" in lines[1] and "272:274" in lines[1]


def test_bad_options_are_named(shared_data: Path, tmp_path: Path):
    with pytest.raises(ReproductionError, match="--only: unknown reproduction 'nope'"):
        run_reproductions(shared_data, tmp_path, only=["nope"])
    with pytest.raises(ReproductionError, match="--limit"):
        run_reproductions(shared_data, tmp_path, limit=0)
    with pytest.raises(ReproductionError, match="is missing"):
        run_reproductions(tmp_path, tmp_path, only=["closed"])


def test_the_command_reports_an_unknown_key_in_one_line(shared_data: Path, tmp_path: Path):
    done = subprocess.run([sys.executable, "-m", "facewire.cli", "bench", "reproductions",
                           "--data", str(shared_data), "--only", "nope", "--json"],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "unknown reproduction 'nope'" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and done.stdout == ""
