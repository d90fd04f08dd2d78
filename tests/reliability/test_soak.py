"""Soak: one hour of 30 Hz traffic through the playout buffer, on synthetic time.

The packets are a real log's frames (lp_d0.mp4 encoded with its own model) repeated for an
hour, ``HOUR`` = 108,000 packets, renumbered from ``FIRST_SEQ`` so that the 16-bit sequence
number wraps twice, and encoded again (``protocol.packet.encode_frames``). Their arrival
times are synthetic: packet ``k`` leaves a sender whose clock runs ``SKEW`` slow at
``k / 30 (1 + SKEW)`` s and arrives ``BASE_S`` plus a uniform jitter in ``[0, JITTER_S)``
later; ``LOSS`` of them never arrive and ``DUPLICATE`` arrive twice.

``play_live`` plays them through a ``receiver.playout.Playout`` with the live receiver's rule
(``receiver.receiver``, "Threads, packets and playing on arrival"): each packet is pushed at
its arrival, the next slot is popped as soon as the playout is ``ready``, and a missing slot
is concealed once its deadline ``due()`` has passed; the time is the arrival times', so an
hour takes as long as the playout's own work (about 20 s).

Checked: no growth in memory after the first ``WARM_UP`` packets (interpreter blocks and
resident size), no drift of the playout (the delay from a packet's arrival to its slot
being played stays bounded and has no trend; the buffer stays a few slots deep), and no
packet lost that was delivered (each delivered packet is played exactly once, in order,
and only the slots of undelivered packets are concealed).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from logsender import encoded_log

from facewire.protocol.packet import FRAME_DTYPE, SEQ_MODULO, Flag, encode_frames
from facewire.receiver.playout import DEFAULT_DEPTH, FrameState, Playout

RATE_HZ = 30.0
HOUR = 108_000
FIRST_SEQ = 60_000  # wraps after 5536 packets, and again 65536 later
SKEW = 40e-6  # the sender's clock runs 40 ppm slow: 0.14 s (4 slots) over the hour
BASE_S = 0.020
JITTER_S = 0.015
LOSS = 0.005
DUPLICATE = 0.002
WARM_UP = 10_000


def play_live(playout: Playout, packets: np.ndarray, arrivals: np.ndarray
              ) -> Iterator[tuple[FrameState, float]]:
    """Yield (state, time played) for every pop of the live receiver's rule (module
    docstring), ``packets`` (N, 43) uint8 in arrival order at ``arrivals`` (N,) s; then
    the slots still buffered, as the receiver drains them at the end."""
    for i in range(len(packets)):
        data, t = packets[i], float(arrivals[i])
        while not playout.ready and (due := playout.due()) is not None and due <= t:
            yield playout.pop(), due
        playout.push(data.tobytes(), t)
        while playout.ready:
            yield playout.pop(), t
    while not playout.drained:
        yield playout.pop(), float(arrivals[-1])


@pytest.fixture(scope="module")
def frames(person_model: Path, shared_data: Path) -> np.ndarray:
    """The real log's frames (``FRAME_DTYPE``)."""
    return encoded_log(person_model, shared_data / "video" / "lp_d0.mp4").frames


def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@dataclass
class Soak:
    """What an hour through ``play_live`` gave."""

    delivered: np.ndarray  # (D,) the numbers k of the packets delivered, ascending
    copies: int  # duplicates delivered
    played: np.ndarray  # (D',) wire seq of each slot played, in order
    delay: np.ndarray  # (D',) s from each played packet's arrival to its slot played
    depth: np.ndarray  # slots buffered ahead (Playout.ahead), every 1000 pops
    stats: dict[str, int]  # the playout's
    blocks: int  # growth of the interpreter's allocated blocks after the warm-up
    rss: int  # growth of the resident size after the warm-up, bytes
    latency_s: float  # the playout's depth in time


def soak(frames: np.ndarray, seed: int = 8) -> Soak:
    """An hour of ``frames``, repeated, on synthetic time (module docstring)."""
    rng = np.random.default_rng(seed)
    stream = np.resize(frames, HOUR)
    stream["seq"] = (FIRST_SEQ + np.arange(HOUR)) % SEQ_MODULO
    encoded, clamped = encode_frames(stream)
    assert not clamped.any()
    # who arrives when: the lost ones never, the duplicated ones twice (the copy 1-30 ms on)
    k = np.arange(HOUR)
    sent = k / RATE_HZ * (1 + SKEW)
    delivered = k[rng.random(HOUR) >= LOSS]
    copies = delivered[rng.random(len(delivered)) < DUPLICATE]
    index = np.concatenate([delivered, copies])
    arrivals = np.concatenate([
        sent[delivered] + BASE_S + rng.uniform(0, JITTER_S, len(delivered)),
        sent[copies] + BASE_S + JITTER_S + rng.uniform(0.001, 0.030, len(copies))])
    order = np.argsort(arrivals, kind="stable")
    index, arrivals = index[order], arrivals[order]
    assert (np.diff(index[np.isin(index, copies, invert=True)]) > 0).all()  # no reordering

    playout = Playout(RATE_HZ)
    played = np.full(HOUR, -1, np.int64)
    delay = np.full(HOUR, np.nan)
    depth = np.zeros(HOUR // 1000 + 2, np.int64)
    n = pops = blocks = rss = 0
    ordered = encoded[index]  # alive to the end, like every array the loop writes into
    for state, when in play_live(playout, ordered, arrivals):
        pops += 1
        if state.arrival_s is not None:
            played[n], delay[n] = state.seq, when - state.arrival_s
            n += 1
        if pops % 1000 == 0:
            depth[pops // 1000] = playout.ahead
        if pops == WARM_UP:
            blocks, rss = sys.getallocatedblocks(), _rss()
    return Soak(delivered, len(copies), played[:n], delay[:n], depth[1:pops // 1000 + 1],
                playout.stats, sys.getallocatedblocks() - blocks, _rss() - rss,
                playout.latency_s)


def test_an_hour_of_traffic_with_no_growth_no_drift_and_no_delivered_packet_lost(
        frames: np.ndarray) -> None:
    hour = soak(frames)
    stats, delivered = hour.stats, hour.delivered
    # no growth: what the warm-up allocated is all the hour needs (a leak of one object
    # per packet would be about 100,000 blocks and several MB)
    assert hour.blocks < 10_000 and hour.rss < 2 * 1024**2, (hour.blocks, hour.rss)
    # no lost packet that was delivered: each played once, in order, none late
    assert stats["received"] == len(delivered) + hour.copies, stats
    assert stats["duplicate"] == hour.copies, stats
    assert stats["late"] == stats["stray"] == stats["discarded"] == 0, stats
    assert stats["skipped"] == stats["restarts"] == 0, stats
    assert len(hour.played) == len(delivered)
    steps = np.diff(hour.played) % SEQ_MODULO
    assert (steps >= 1).all() and (steps < SEQ_MODULO // 2).all()  # in order, across wraps
    ext = hour.played[0] + np.concatenate([[0], np.cumsum(steps)])
    assert (ext == FIRST_SEQ + delivered).all()
    assert stats["concealed"] == HOUR - len(delivered)  # only the undelivered slots
    # no drift: the delay and the buffer are bounded, and flat from the first minutes to
    # the last
    d, tenth = hour.delay[WARM_UP:], (len(hour.delay) - WARM_UP) // 10
    assert d.min() >= 0 and d.max() <= hour.latency_s + 1e-6, (d.min(), d.max())
    assert abs(d[-tenth:].mean() - d[:tenth].mean()) < 0.002
    assert hour.depth.max() <= 2 * DEFAULT_DEPTH
    tenth = len(hour.depth) // 10
    assert abs(hour.depth[-tenth:].mean() - hour.depth[:tenth].mean()) < 1


def test_a_packet_overtaken_by_its_successor_is_played_not_late() -> None:
    """Reordering within one packet period: packet ``n`` arriving right after ``n + 1``, which
    itself comes with the stream's usual jitter, is played in its slot, not concealed as
    late. The swaps are far apart (more than the playout's window of recent packets), so
    each is the first the playout sees in a while."""
    rng = np.random.default_rng(3)
    count, swaps = 600, range(100, 600, 100)
    stream = np.zeros(count, FRAME_DTYPE)
    stream["seq"], stream["flags"] = np.arange(count), Flag.FACE_PRESENT
    encoded, _ = encode_frames(stream)
    arrivals = np.arange(count) / RATE_HZ + BASE_S + rng.uniform(0, JITTER_S, count)
    for n in swaps:
        arrivals[n] = arrivals[n + 1] + 0.0005
    order = np.argsort(arrivals, kind="stable")
    playout = Playout(RATE_HZ)
    states = [s for s, _ in play_live(playout, encoded[order], arrivals[order])]
    late = [n for n in swaps if not any(s.seq == n and s.arrival_s is not None
                                        for s in states)]
    jitter = [round(float(arrivals[n + 1] - (n + 1) / RATE_HZ - BASE_S) * 1000, 1) for n in late]
    assert not late, f"packets {late} were concealed as late (their successors came with " \
        f"{jitter} ms of jitter, of {1000 * JITTER_S:g} ms at most): {playout.stats}"
