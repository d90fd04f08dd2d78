"""Headless Chromium for the tests that drive a page: the pytest side of
``facewire.bench.chromium`` (the driver, ``DevTools``, and ``WEBGL_FLAGS``, re-exported here).

Without Chromium on PATH a browser test skips with the reason ``chromium_binary`` gives,
except under ``FACEWIRE_REQUIRE_REAL_DATA=1`` (CI), where it fails with it.
"""

from __future__ import annotations

import os

import pytest

from facewire.bench.chromium import WEBGL_FLAGS, ChromiumMissing, DevTools, chromium_binary

__all__ = ["WEBGL_FLAGS", "DevTools", "find_chromium"]


def find_chromium() -> str:
    """The path of the Chromium binary; skip the calling test (or fail it under CI) when there is
    none."""
    try:
        return chromium_binary()
    except ChromiumMissing as missing:
        if os.environ.get("FACEWIRE_REQUIRE_REAL_DATA") == "1":
            pytest.fail(f"{missing} (FACEWIRE_REQUIRE_REAL_DATA=1)")
        pytest.skip(str(missing))
