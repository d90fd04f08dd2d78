"""Shared fixtures: where the real third-party material lives, and how its absence is handled.

Tests that need ``../shared/data`` ask for the ``shared_data`` fixture. Without the folder they
skip with a reason, except under ``FACEWIRE_REQUIRE_REAL_DATA=1`` (set by CI), where they fail.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of real test material; skip (or fail under CI) when it is absent."""
    if not (SHARED_DATA / "SOURCES.md").is_file():
        message = f"real test material not found at {SHARED_DATA}"
        if os.environ.get("FACEWIRE_REQUIRE_REAL_DATA") == "1":
            pytest.fail(message + " (FACEWIRE_REQUIRE_REAL_DATA=1)")
        pytest.skip(message)
    return SHARED_DATA
