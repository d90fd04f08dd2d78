"""The update traffic shaper: whatever a receiver asks, its update bytes stay within the limits
over any 1 s and any 60 s, and its windowed measure is the one the benchmark reports."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.protocol.shaper import (
    LIMIT_KBPS_1S,
    LIMIT_KBPS_60S,
    MAX_MESSAGE_BYTES,
    UpdateShaper,
    window_kbps,
)


def _greedy(shaper: UpdateShaper, peer: object, sizes: list[int], start: float = 0.0
            ) -> np.ndarray:
    """A receiver asking for the next message as soon as the last one is sent."""
    times, now = [], start
    for size in sizes:
        now = shaper.schedule(peer, size, now)
        times.append(now)
    return np.array(times)


def test_a_greedy_receiver_stays_within_both_limits() -> None:
    rng = np.random.default_rng(3)
    sizes = rng.integers(200, MAX_MESSAGE_BYTES + 1, 400).tolist()
    times = _greedy(UpdateShaper(), "a", sizes)
    kbps_1s = window_kbps(times, sizes, 1.0)
    kbps_60s = window_kbps(times, sizes, 60.0)
    assert kbps_1s <= LIMIT_KBPS_1S and kbps_60s <= LIMIT_KBPS_60S
    assert kbps_1s > 0.9 * LIMIT_KBPS_1S and kbps_60s > 0.85 * LIMIT_KBPS_60S  # not idle
    assert times[-1] > 60  # 400 messages of ~800 bytes need over a minute


def test_an_unshaped_schedule_would_fail_the_measure() -> None:
    sizes = [MAX_MESSAGE_BYTES] * 10
    assert window_kbps(np.arange(10) * 0.1, sizes, 1.0) > LIMIT_KBPS_1S


def test_receivers_are_shaped_each_on_its_own_and_forgotten_when_full() -> None:
    shaper = UpdateShaper()
    first = _greedy(shaper, "a", [1000] * 5)
    second = _greedy(shaper, "b", [1000] * 5)
    assert np.allclose(first, second)  # b does not wait behind a
    assert shaper.peers() == 2
    shaper.schedule("c", 10, 1000.0)  # long after: a and b are as new again
    assert shaper.peers() == 1


def test_bursts_after_a_pause_are_bounded_too() -> None:
    shaper = UpdateShaper()
    times = np.concatenate([_greedy(shaper, "a", [1300] * 20),
                            _greedy(shaper, "a", [1300] * 20, start=40.0)])
    sizes = [1300] * 40
    assert window_kbps(times, sizes, 60.0) <= LIMIT_KBPS_60S
    assert window_kbps(times, sizes, 1.0) <= LIMIT_KBPS_1S


def test_bad_sizes_and_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match="update message of"):
        UpdateShaper().schedule("a", MAX_MESSAGE_BYTES + 1, 0.0)
    with pytest.raises(ValueError, match="times and sizes"):
        window_kbps([0.0, 1.0], [1], 1.0)
    assert window_kbps([], [], 1.0) == 0.0


def test_three_chunks_go_at_once_and_three_more_when_the_window_has_passed() -> None:
    times = _greedy(UpdateShaper(), "a", [1314] * 9)
    assert np.allclose(times, [0, 0, 0, 1.1, 1.1, 1.1, 2.2, 2.2, 2.2])
    # arrivals up to 0.1 s late still carry at most 4000 bytes in any second
    late = times + np.tile([0.1, 0.0, 0.0], 3)
    assert window_kbps(late, [1314] * 9, 1.0) <= LIMIT_KBPS_1S
