"""How every command reports: a human summary, then with ``--json`` one JSON object last."""

from __future__ import annotations

import json
from typing import Any


def report(summary: dict[str, Any], lines: list[str], as_json: bool) -> None:
    """Print the human lines, then (with ``as_json``) the summary as the last line."""
    for line in lines:
        print(line)
    if as_json:
        print(json.dumps(summary, sort_keys=True))
