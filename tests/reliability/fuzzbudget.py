"""The fuzz tests' seed and budget (tests/reliability/test_fuzz.py, test_wire_faults.py).

``SHARES`` gives the packets of each test, 1,184,720 in all per normal run (each test asserts
its own count). For a longer run every share is scaled by ``FACEWIRE_FUZZ_PACKETS /
1,184,720``; every draw is seeded from ``FACEWIRE_FUZZ_SEED`` and the test's own name, and
``WHY``, which names both, goes into every failure message.
"""

from __future__ import annotations

import os
import zlib

import numpy as np

SHARES = {  # packets per test in a normal run
    "one_and_two_bit_errors": 8 * (344 + 344 * 343 // 2),  # 8 packets, exhaustively
    "random_bit_errors": 200_000,
    "valid_crc_random_fields": 200_000,
    "playout_counts": 200_000,
    "playout_order": 100_000,
    "log_records": 10_000,
}
DEFAULT_PACKETS = sum(SHARES.values())  # 1,184,720; and the wire's few hundred
PACKETS = int(os.environ.get("FACEWIRE_FUZZ_PACKETS", DEFAULT_PACKETS))
SEED = int(os.environ.get("FACEWIRE_FUZZ_SEED", 20261126))
SCALE = PACKETS / DEFAULT_PACKETS
WHY = f"(FACEWIRE_FUZZ_SEED={SEED}, FACEWIRE_FUZZ_PACKETS={PACKETS})"


def share(name: str) -> int:
    return max(1, round(SHARES[name] * SCALE))


def rng_for(name: str) -> np.random.Generator:
    return np.random.default_rng([SEED, zlib.crc32(name.encode())])
