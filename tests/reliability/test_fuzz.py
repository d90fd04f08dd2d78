"""Bad packets (issue 8, reliability item 2): over a million fuzzed and mutated packets through
the real code paths, with zero crashes and exact counts, and corrupt packets in a log and on
the wire counted and skipped.

Paths: ``protocol.packet.decode`` and ``decode_frames`` (vectorised), the receiver's per-packet
path ``receiver.playout.Playout.push`` (never raises on content; ``received + corrupt`` is
every push), ``protocol.log.read_log`` of a ``.fwlog`` with corrupt records, a real
``receiver.receiver.receive`` over ZeroMQ on 127.0.0.1, and a raw TCP peer declaring a frame
of 1 GiB to a receiver's packet socket.

The oracle is this file's own reading of the format table in ``protocol/packet.py`` (widths,
ranges, steps, CRC-16/CCITT-FALSE from ``binascii``, flag bits 6 and 7 reserved), with its
own bit packer: a 39-byte string is a valid packet iff its version nibble is 1, its CRC
matches and no reserved flag is set. Counts are asserted exactly wherever the oracle knows
them.

Which bit errors are always caught: the CRC's generator x^16 + x^12 + x^5 + 1 is (x + 1)
times a primitive polynomial of degree 15, so every error of an odd number of bits, every
two-bit error within 32767 bits and every burst of at most 16 bits changes the CRC; a packet
is 312 bits. Every 1- and 2-bit error of several packets is tried here (exhaustively), and
random odd-weight errors and bursts; errors of 4 or more bits can pass (about 1 in 32768 of
the even-weight ones): such mutants are valid packets, must decode to in-range values, and
count as received.

Budget: ``SHARES`` (packets per test, 1,100,624 in all per normal run; each test asserts its
own count). For a longer run every share is scaled by ``FACEWIRE_FUZZ_PACKETS / 1,100,624``
and the seed is ``FACEWIRE_FUZZ_SEED`` (each failure message names it)::

    FACEWIRE_FUZZ_PACKETS=10000000 .venv/bin/python -m pytest -q tests/reliability/test_fuzz.py
    .venv/bin/python tests/reliability/test_fuzz.py --packets 10000000 --seed 7
"""

from __future__ import annotations

import binascii
import contextlib
import hashlib
import math
import os
import random
import socket
import struct
import sys
import threading
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import zmq

if __name__ == "__main__":  # run as a script: find tests/conftest.py as pytest does
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from conftest import free_endpoint, start
from facewire.protocol.control import Camera, Error, Hello, HelloRequest, decode_message
from facewire.protocol.log import LogWriter, read_log
from facewire.protocol.packet import PacketError, decode, decode_frames
from facewire.protocol.relay import relay
from facewire.protocol.transport import ControlServer, PacketSubscriber, control_endpoint
from facewire.receiver.playout import STATUSES, Playout
from facewire.receiver import receiver as receiver_module
from facewire.receiver.receiver import receive

# -- budget ----------------------------------------------------------------------------------

SHARES = {  # packets per test in a normal run
    "one_and_two_bit_errors": 8 * (312 + 312 * 311 // 2),  # 8 packets, exhaustively
    "random_bit_errors": 200_000,
    "valid_crc_random_fields": 200_000,
    "playout_counts": 200_000,
    "playout_order": 100_000,
    "log_records": 10_000,
}
DEFAULT_PACKETS = sum(SHARES.values())  # 1,100,624; and the wire's few hundred
PACKETS = int(os.environ.get("FACEWIRE_FUZZ_PACKETS", DEFAULT_PACKETS))
SEED = int(os.environ.get("FACEWIRE_FUZZ_SEED", 20261126))
SCALE = PACKETS / DEFAULT_PACKETS
WHY = f"(FACEWIRE_FUZZ_SEED={SEED}, FACEWIRE_FUZZ_PACKETS={PACKETS})"


def share(name: str) -> int:
    return max(1, round(SHARES[name] * SCALE))


def rng_for(name: str) -> np.random.Generator:
    return np.random.default_rng([SEED, zlib.crc32(name.encode())])


# -- the oracle: the format table of protocol/packet.py, read independently -------------------

PACKET, BODY, BITS = 39, 37, 312
WIDTHS = np.array([4, 8, 16] + [11] * 3 + [12] * 2 + [11] + [8] * 18 + [7] * 8)
LO = np.array([-102.4] * 3 + [-1024.0] * 2 + [-2147.0] + [-32.0] * 18 + [0.0] * 8)
STEP = np.array([0.1] * 3 + [0.5] * 2 + [1.0] + [0.25] * 18 + [1 / 16] * 8)
TOP = (1 << WIDTHS[3:]) - 1
RESERVED = 0xC0  # Flag defines bits 0..5
_STARTS = np.concatenate([[0], np.cumsum(WIDTHS)[:-1]])
_WEIGHTS = np.concatenate([1 << np.arange(w - 1, -1, -1, dtype=np.int32) for w in WIDTHS])


def crcs(body: np.ndarray) -> np.ndarray:
    """(N,) CRC-16/CCITT-FALSE of each (N, 37) row, by ``binascii``."""
    raw = np.ascontiguousarray(body, np.uint8).tobytes()
    return np.array([binascii.crc_hqx(raw[i:i + BODY], 0xFFFF)
                     for i in range(0, len(raw), BODY)], np.int64)


def pack(fields: np.ndarray) -> np.ndarray:
    """(N, 35) field codes (version, flags, seq, 32 quantised) -> (N, 39) packets, CRC right."""
    bits = np.empty((len(fields), 8 * BODY), np.uint8)
    for i, (first, width) in enumerate(zip(_STARTS, WIDTHS)):
        bits[:, first:first + width] = (fields[:, [i]] >> np.arange(width - 1, -1, -1)) & 1
    return with_crc(np.packbits(bits, axis=1))


def with_crc(body: np.ndarray) -> np.ndarray:
    crc = crcs(body)
    return np.concatenate([body, (crc >> 8)[:, None], (crc & 0xFF)[:, None]],
                          axis=1).astype(np.uint8)


def unpack(packets: np.ndarray) -> np.ndarray:
    """(N, 39) packets -> (N, 35) field codes."""
    bits = np.unpackbits(packets[:, :BODY], axis=1)
    return np.add.reduceat(bits * _WEIGHTS, _STARTS, axis=1).astype(np.int64)


def reasons(packets: np.ndarray) -> np.ndarray:
    """(N,) object: the ``PacketError`` reason each 39-byte row must get, None if valid."""
    fields = unpack(packets)
    crc_ok = crcs(packets[:, :BODY]) == (packets[:, 37].astype(np.int64) << 8 | packets[:, 38])
    out = np.full(len(packets), None, object)
    out[fields[:, 1] & RESERVED != 0] = "reserved"
    out[~crc_ok] = "crc"
    out[fields[:, 0] != 1] = "version"
    return out


def reason(data: object) -> str | None:
    """What ``Playout.push`` must make of one item: None (received) or why it is corrupt."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        return "type"
    raw = bytes(data)
    if len(raw) != PACKET:
        return "size"
    if raw[0] >> 4 != 1:
        return "version"
    if binascii.crc_hqx(raw[:BODY], 0xFFFF) != raw[37] << 8 | raw[38]:
        return "crc"
    return "reserved" if (raw[0] << 4 | raw[1] >> 4) & RESERVED else None


def random_fields(rng: np.random.Generator, n: int, seq: np.ndarray | None = None,
                  extremes: float = 0.2) -> np.ndarray:
    """(N, 35) codes of valid packets: random flags (no reserved bit), codes over the whole
    range of each quantiser with a share of ``extremes`` at its ends."""
    fields = np.empty((n, len(WIDTHS)), np.int64)
    fields[:, 0] = 1
    fields[:, 1] = rng.integers(0, 64, n)
    fields[:, 2] = rng.integers(0, 1 << 16, n) if seq is None else np.asarray(seq) % 65536
    codes = rng.integers(0, TOP + 1, (n, len(TOP)))
    ends = rng.random((n, len(TOP))) < extremes
    tops = np.broadcast_to(TOP, ends.shape)[ends]
    codes[ends] = np.where(rng.random(len(tops)) < 0.5, 0, tops)
    fields[:, 3:] = codes
    return fields


def check_decoded(frames: np.ndarray, fields: np.ndarray) -> None:
    """The decoded records hold exactly the table's value of each code (so each lies in its
    quantiser's range), all finite."""
    value = LO + fields[:, 3:] * STEP
    assert np.array_equal(frames["seq"], fields[:, 2]), WHY
    assert np.array_equal(frames["flags"], fields[:, 1]), WHY
    assert np.array_equal(frames["rotation"], np.radians(value[:, 0:3]).astype(np.float32)), WHY
    assert np.array_equal(frames["translation"], value[:, 3:6].astype(np.float32)), WHY
    assert np.array_equal(frames["residuals"].reshape(-1, 18),
                          value[:, 6:24].astype(np.float32)), WHY
    assert np.array_equal(frames["q"], value[:, 24:].astype(np.float32)), WHY
    for name in ("rotation", "translation", "residuals", "q"):
        assert np.isfinite(frames[name]).all(), WHY


def flip(packets: np.ndarray, rows: np.ndarray, bits: np.ndarray) -> None:
    """XOR bit ``bits[i]`` (0 = the most significant bit of byte 0) of row ``rows[i]``,
    in place; a bit named twice is flipped back."""
    np.bitwise_xor.at(packets, (rows, bits // 8), (0x80 >> (bits % 8)).astype(np.uint8))


def test_the_shares_add_up_to_a_million() -> None:
    assert DEFAULT_PACKETS >= 1_000_000 and sum(share(k) for k in SHARES) >= 0.99 * PACKETS


# -- decode and decode_frames ----------------------------------------------------------------

def test_every_one_and_two_bit_error_is_caught() -> None:
    """All 312 one-bit and 48,516 two-bit errors of each of several valid packets: every one
    is refused (vectorised and, for one bit, one by one), as the CRC guarantees."""
    rng = rng_for("one_and_two_bit_errors")
    per = 312 + 312 * 311 // 2
    count = max(1, share("one_and_two_bit_errors") // per)
    base = pack(random_fields(rng, count))
    i, j = np.triu_indices(BITS, 1)
    singles = np.zeros((BITS, PACKET), np.uint8)
    singles[np.arange(BITS), np.arange(BITS) // 8] = 0x80 >> (np.arange(BITS) % 8)
    masks = np.concatenate([singles, singles[i] ^ singles[j]])
    assert len(masks) == per and (np.unpackbits(masks, axis=1).sum(axis=1) <= 2).all()
    tried = 0
    for packet in base:
        assert decode(packet.tobytes()).seq >= 0
        mutants = packet ^ masks
        frames, errors = decode_frames(mutants)
        refused = errors != None  # noqa: E711 (elementwise on an object array)
        assert refused.all(), f"{(~refused).sum()} errors of <= 2 bits passed {WHY}"
        assert set(errors) <= {"version", "crc"} and not frames.view(np.uint8).any()
        if not tried:
            assert list(errors) == list(reasons(mutants)), WHY
        for mutant in mutants[:BITS]:
            try:
                decode(mutant.tobytes())
            except PacketError as exc:
                assert exc.reason in ("version", "crc")
            else:
                raise AssertionError(f"a one-bit error passed decode {WHY}")
        tried += len(mutants)
    assert tried == count * per


def test_random_bit_errors_are_caught_or_decode_in_range() -> None:
    """Odd numbers of flipped bits and bursts up to 16 bits: always refused. Even numbers of
    4 to 16 bits and overwritten bytes: refused exactly where the oracle refuses them, and a
    mutant that passes decodes to in-range values like any valid packet."""
    rng = rng_for("random_bit_errors")
    n = share("random_bit_errors")
    base = pack(random_fields(rng, 512))
    tried = passed = 0
    for lo in range(0, n, 25_000):
        m = min(25_000, n - lo)
        kind = rng.integers(0, 4, m)  # 0 odd weight, 1 burst, 2 even weight, 3 bytes
        mutants = base[rng.integers(0, len(base), m)]
        rows = np.arange(m)
        odd = rows[kind == 0]
        weight = 2 * rng.integers(1, 8, len(odd)) + 1  # 3 .. 15 bits
        flip(mutants, np.repeat(odd, weight),
             rng.integers(0, BITS, int(weight.sum())))  # repeats cancel in pairs: still odd
        burst = rows[kind == 1]
        length = rng.integers(2, 17, len(burst))
        first = rng.integers(0, BITS - length + 1)
        pattern = rng.integers(0, 2, (len(burst), 16)).astype(bool)
        pattern[:, 0] = True
        pattern[np.arange(len(burst)), length - 1] = True
        pattern &= np.arange(16) < length[:, None]
        r, c = np.nonzero(pattern)
        flip(mutants, burst[r], first[r] + c)
        even = rows[kind == 2]
        weight = 2 * rng.integers(2, 9, len(even))  # 4 .. 16 bits
        flip(mutants, np.repeat(even, weight), rng.integers(0, BITS, int(weight.sum())))
        over = rows[kind == 3]
        nbytes = rng.integers(1, 7, len(over))
        mutants[np.repeat(over, nbytes), rng.integers(0, PACKET, int(nbytes.sum()))] = \
            rng.integers(0, 256, int(nbytes.sum()), dtype=np.uint8)

        frames, errors = decode_frames(mutants)
        expected = reasons(mutants)
        assert list(errors) == list(expected), WHY
        ok = errors == None  # noqa: E711
        assert not (ok & (kind < 2)).any(), f"an odd-weight error or a burst passed {WHY}"
        check_decoded(frames[ok], unpack(mutants[ok]))
        assert not frames[~ok].view(np.uint8).any()
        passed += int(ok.sum())
        tried += m
    assert tried == n
    # Unchanged mutants (flips that cancel, bytes overwritten with themselves) and the rare
    # CRC collision pass; far fewer than 1 in 100.
    assert passed < n / 100, WHY


def test_valid_crc_packets_with_random_fields() -> None:
    """Packets whose CRC is right but whose fields are random: unknown versions, reserved
    flag bits, every quantised code including the extremes, any sequence number. The version
    and reserved bits are refused; everything else decodes to exactly the table's values,
    vectorised and one by one alike."""
    rng = rng_for("valid_crc_random_fields")
    n = share("valid_crc_random_fields")
    checked = 0
    for lo in range(0, n, 50_000):
        m = min(50_000, n - lo)
        fields = random_fields(rng, m, extremes=0.25)
        fields[:, 0] = np.where(rng.random(m) < 0.75, 1, rng.integers(0, 16, m))
        fields[:, 1] = rng.integers(0, 256, m)
        fields[:2, 3:] = [np.zeros_like(TOP), TOP]  # all codes at the bottom, at the top
        packets = pack(fields)
        frames, errors = decode_frames(packets)
        want = np.where(fields[:, 0] != 1, "version",
                        np.where(fields[:, 1] & RESERVED, "reserved", None))
        assert list(errors) == list(want), WHY
        ok = errors == None  # noqa: E711
        assert 0.1 < ok.mean() < 0.3
        check_decoded(frames[ok], fields[ok])
        assert not frames[~ok].view(np.uint8).any()
        for k in range(min(m, 2000)):  # the scalar path agrees
            try:
                frame = decode(packets[k].tobytes())
            except PacketError as exc:
                assert exc.reason == want[k], WHY
                continue
            assert want[k] is None and frame.to_record().tobytes() == frames[k].tobytes(), WHY
        checked += m
    assert checked == n


# -- the receiver's per-packet path ----------------------------------------------------------

_NOT_BYTES = (None, 39, 3.5, float("nan"), "x" * 39, [0] * 39, (1, 2), {}, object(),
              np.zeros(39, np.uint8), np.float64(1.0), True, Exception("packet"))


class Garbage:
    """Items that are never valid packets, drawn with a seeded ``random.Random`` (cheaper per
    draw than numpy): random bytes of any length 0..100, mutants of given packets (1 to 3
    flipped bits, cut short, extended), CRC-right packets with a bad version or a reserved
    flag bit, bytes-likes that are not bytes, and objects that are no bytes at all. A random
    39-byte string gets version 0, so that it cannot be valid by chance."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.r = random.Random(int(rng.integers(1 << 62)))
        fields = random_fields(rng, 1024)
        fields[:512, 0] = rng.choice([0, *range(2, 16)], 512)
        fields[512:, 1] |= rng.choice([0x40, 0x80, 0xC0], 512)
        self.bad_fields = [p.tobytes() for p in pack(fields)]

    def random_bytes(self, size: int) -> bytes:
        raw = self.r.randbytes(size)
        return bytes([raw[0] & 0x0F]) + raw[1:] if size == PACKET else raw

    def __call__(self, near: list[bytes]) -> object:
        r = self.r
        kind = r.randrange(8)
        base = bytearray(r.choice(near))
        if kind == 0:
            return self.random_bytes(r.randrange(101))
        if kind == 1:  # 1 to 3 flipped bits: always caught by the CRC
            for bit in r.sample(range(BITS), r.randrange(1, 4)):
                base[bit // 8] ^= 0x80 >> (bit % 8)
            return bytes(base)
        if kind == 2:
            return bytes(base[:r.randrange(PACKET)])
        if kind == 3:
            return bytes(base) + r.randbytes(r.randrange(1, 62))
        if kind == 4:
            return r.choice(self.bad_fields)
        if kind == 5:
            return r.choice(_NOT_BYTES)
        if kind == 6:  # bytes-like, not bytes
            raw = self.random_bytes(r.randrange(80))
            return bytearray(raw) if r.random() < 0.5 else memoryview(raw)
        return memoryview(np.frombuffer(self.random_bytes(PACKET) * 2, np.uint8)[::2])  # strided


def check_states(states: list) -> None:
    """Every state is finite and in range: a rotation matrix, residuals and Q within their
    quantisers' ranges, a weight in [0, 1], a known status."""
    rotation = np.stack([s.rotation for s in states])
    assert np.isfinite(rotation).all(), WHY
    assert np.abs(rotation @ rotation.transpose(0, 2, 1) - np.eye(3)).max() < 1e-6, WHY
    assert np.isfinite(np.stack([s.translation for s in states])).all(), WHY
    residuals, q = np.stack([s.residuals for s in states]), np.stack([s.q for s in states])
    assert (np.abs(residuals) <= 32).all() and (q >= 0).all() and (q < 8).all(), WHY
    assert all(0.0 <= s.weight <= 1.0 and s.status in STATUSES for s in states), WHY


def test_playout_counts_every_push_exactly() -> None:
    """Pushes of every kind, in random order: random bytes of each length 0..100, mutants of
    the stream's packets, CRC-right packets with random fields (valid ones with random
    sequence numbers: strays and restarts), a stream with sequence jumps, non-bytes objects.
    ``received`` is exactly the oracle's valid items, ``corrupt`` all the others, every
    valid packet is accounted for (played, duplicate, late, stray, discarded, or the one
    restart candidate left), and every state is finite and in range."""
    rng = rng_for("playout_counts")
    n = share("playout_counts")
    valid_budget = max(20, n // 40)  # valid packets cost ~0.15 ms each, garbage ~4 us
    seqs = np.cumsum(np.where(rng.random(valid_budget) < 0.02,
                              rng.integers(2, 70_000, valid_budget), 1)) + 65_000
    stream = [p.tobytes() for p in pack(random_fields(rng, valid_budget, seq=seqs))]
    garbage = Garbage(rng)
    others: list[object] = [garbage.random_bytes(k % 101) for k in range(n // 2)]  # each length
    others += [p.tobytes() for p in pack(random_fields(rng, max(1, valid_budget // 4)))]
    others += [garbage(stream) for _ in range(n - valid_budget - len(others))]
    order = rng.permutation(len(others))
    in_stream = np.zeros(n, bool)
    in_stream[rng.choice(n, valid_budget, replace=False)] = True
    streamed, other = iter(stream), (others[k] for k in order)
    placed = [next(streamed) if s else next(other) for s in in_stream]  # the stream in order
    valid = sum(reason(item) is None for item in placed)
    playout = Playout(30.0)
    states = []
    pops_every = max(1, n // (2 * valid_budget))
    for k, item in enumerate(placed):
        playout.push(item, k / (30.0 * pops_every))
        if k % pops_every == 0:
            states.append(playout.pop())
    for _ in range(10 * playout.window):  # drain
        if playout.drained:
            break
        states.append(playout.pop())
    check_states(states)
    played = sum(s.arrival_s is not None for s in states)
    stats = playout.stats
    assert playout.drained, WHY
    assert stats["received"] == valid and stats["corrupt"] == n - valid, (stats, WHY)
    accounted = played + sum(stats[k] for k in ("duplicate", "late", "stray", "discarded"))
    assert stats["received"] - accounted in (0, 1), (stats, played, WHY)
    assert stats["restarts"] >= 1 and stats["stray"] >= 1, stats  # the jumps were exercised


def test_valid_packets_between_garbage_are_all_played_in_order() -> None:
    """A stream whose sequence numbers wrap, each packet after a run of garbage (mutants of
    the packets around it among them): every valid packet is played, in order, with its own
    content, and every piece of garbage is counted as corrupt, nothing else."""
    rng = rng_for("playout_order")
    n = share("playout_order")
    valid = max(10, n // 50)
    seqs = np.arange(valid) + 65_536 - valid // 2
    fields = random_fields(rng, valid, seq=seqs)
    fields[:, 1] |= 1  # face present: every played slot is "received"
    fields[:, 1] &= ~2
    stream = [p.tobytes() for p in pack(fields)]
    playout = Playout(30.0)
    make = Garbage(rng)
    garbage = 0
    played: list = []
    pushed = 0
    for i, packet in enumerate(stream):
        near = stream[max(0, i - 2):i + 3]
        for _ in range(make.r.randrange(2 * (n - valid) // valid + 1)):
            item = make(near)
            assert reason(item) is not None
            playout.push(item, i / 30.0)
            garbage += 1
        playout.push([bytes, bytearray, memoryview][i % 3](packet), i / 30.0)
        pushed += 1
        state = playout.pop()
        if state.seq is not None:
            played.append(state)
    while not playout.drained:
        state = playout.pop()
        if state.seq is not None:
            played.append(state)
    stats = playout.stats
    assert [s.seq for s in played] == [int(s) % 65536 for s in seqs], WHY
    assert all(s.status == "received" for s in played), WHY
    for state, packet in zip(played, stream):
        frame = decode(packet)
        assert np.array_equal(state.residuals, frame.residuals) and \
            np.array_equal(state.q, frame.q) and \
            np.array_equal(state.translation, frame.translation.astype(np.float64))
    assert stats["received"] == valid and stats["corrupt"] == garbage, (stats, WHY)
    assert not any(stats[k] for k in ("duplicate", "late", "stray", "discarded", "concealed",
                                      "skipped", "restarts")), stats
    assert pushed + garbage >= n * 0.9


# -- the packet log --------------------------------------------------------------------------

HELLO = Hello("0f" * 32, 4096, 30.0, Camera(500.0, 500.0, 320.0, 240.0, 640, 480), ("mouth",))
RECORD = 8 + PACKET + 4


def test_a_log_with_corrupt_records_keeps_every_intact_one(tmp_path: Path) -> None:
    """A real log in which every other record is damaged one way or another (bit flips in
    its time, packet or CRC-32; a right CRC-32 over a corrupt or invalid packet or a NaN or
    infinite time; random bytes; bytes cut out; garbage inserted between records; the tail
    cut): ``read_log`` keeps every intact record, in order, with its time, and counts each
    damaged one as lost (an insertion of L bytes as ``max(1, round(L / 51))``)."""
    rng = rng_for("log_records")
    damaged = share("log_records")
    total = 2 * damaged + 3  # odd records 1 .. 2 damaged - 1 damaged; the last one cut short
    path = tmp_path / "fuzz.fwlog"
    fields = random_fields(rng, total, seq=np.arange(total))
    packets = pack(fields)
    times = 1.7e9 + np.arange(total) / 30.0
    with LogWriter(path, HELLO) as log:
        for packet, t in zip(packets, times):
            log.write(packet.tobytes(), float(t))
    data = bytearray(path.read_bytes())
    head = len(data) - total * RECORD
    pieces = [bytes(data[:head])]
    keep: list[int] = []
    lost = 0
    mutants = pack(random_fields(rng, total))  # valid packets with random fields
    for k in range(total):
        record = bytearray(data[head + k * RECORD:head + (k + 1) * RECORD])
        if k % 2 == 0 or k >= total - 2:
            keep.append(k)
            pieces.append(bytes(record))
            continue
        kind = rng.integers(0, 9)
        body = record[:-4]
        if kind == 0:  # flipped bits anywhere in the record: its CRC-32 no longer matches
            for bit in rng.choice(8 * RECORD, int(rng.integers(1, 4)), replace=False):
                record[bit // 8] ^= 0x80 >> (bit % 8)
        elif kind in (1, 2, 3):  # a right CRC-32 over a bad packet or a bad time
            if kind == 1:
                body[8 + rng.integers(0, PACKET)] ^= 1 << rng.integers(0, 8)
            elif kind == 2:
                bad = fields[k].copy()
                bad[1] |= 0x80
                body[8:] = pack(bad[None])[0].tobytes()
            else:
                body[:8] = struct.pack(">d", rng.choice([math.nan, math.inf, -math.inf]))
            record = body + struct.pack(">I", zlib.crc32(body))
        elif kind == 4:
            record = bytearray(rng.bytes(RECORD))
        elif kind == 5:  # bytes cut out of the record
            cut = int(rng.integers(1, RECORD))
            at = int(rng.integers(0, RECORD - cut + 1))
            del record[at:at + cut]
        elif kind == 6:  # garbage inserted after an intact record
            keep.append(k)
            pieces.append(bytes(record))
            size = int(rng.integers(1, 3 * RECORD))
            pieces.append(rng.bytes(size))
            lost += max(1, round(size / RECORD))
            continue
        elif kind == 7:  # a valid packet with random fields under a right CRC-32: kept
            body[8:] = mutants[k].tobytes()
            packets[k] = mutants[k]
            record = body + struct.pack(">I", zlib.crc32(body))
            keep.append(k)
            pieces.append(bytes(record))
            continue
        else:  # a record of the right size, its packet random bytes, CRC-32 right
            body[8:] = rng.bytes(PACKET)
            record = body + struct.pack(">I", zlib.crc32(body))
            if reasons(np.frombuffer(bytes(body[8:]), np.uint8)[None])[0] is None:
                packets[k] = np.frombuffer(bytes(body[8:]), np.uint8)
                keep.append(k)
                pieces.append(bytes(record))
                continue
        pieces.append(bytes(record))
        lost += 1
    cut = int(rng.integers(1, RECORD))  # and the last record cut short
    path.write_bytes(b"".join(pieces)[:-cut])
    keep.pop()
    lost += 1
    log = read_log(path)
    assert log.lost == lost, (log.lost, lost, WHY)
    assert np.array_equal(log.packets, packets[keep]), WHY
    assert np.array_equal(log.times, times[keep]), WHY
    assert log.hello == HELLO


# -- the wire --------------------------------------------------------------------------------

class _WireSender(threading.Thread):
    """A fake sender of test code: an XPUB for packets (it sees the receiver subscribe) and
    the real ``ControlServer`` answering the Hello. Once the receiver has subscribed it
    publishes ``messages`` at once, with no limit on its queue: they wait in the receiver's
    queue while it sets up, so that no deadline of the live playout depends on this thread's
    timing (it shares the receiver's process and GIL: a pause of either, a garbage
    collection say, would otherwise make a packet late on a link that loses nothing)."""

    def __init__(self, endpoint: str, hello: Hello, messages: list[bytes]) -> None:
        super().__init__(daemon=True)
        self.endpoint, self.hello, self.messages = endpoint, hello, messages
        self.sent = 0
        self.halt = threading.Event()
        self.bound = threading.Event()
        self.start()
        assert self.bound.wait(10)

    def run(self) -> None:
        context = zmq.Context()
        pub = context.socket(zmq.XPUB)
        pub.linger, pub.sndhwm = 0, 0  # no limit: nothing is dropped on this side
        pub.bind(self.endpoint)
        server = ControlServer(control_endpoint(self.endpoint))
        self.bound.set()
        try:
            while not self.halt.is_set():
                if pub.poll(0) and pub.recv() == b"\x01" and not self.sent:  # subscribed
                    for message in self.messages:
                        pub.send(message)
                        self.sent += 1
                request = server.recv(2)
                if request is not None:
                    peer, raw = request
                    reply = self.hello if isinstance(decode_message(raw), HelloRequest) \
                        else Error("this sender only says hello")
                    server.reply(peer, reply)
        finally:
            server.close()
            pub.close()
            context.term()


def test_corrupt_packets_on_the_wire_are_counted_and_skipped(generic_model: Path) -> None:
    """A real receiver behind real ZeroMQ: 90 valid packets, each after up to 8 pieces of
    garbage (random bytes of 0..100 bytes, mutants of the packets around it, CRC-
    right packets with a bad version or reserved bits). The summary counts every piece as
    corrupt and plays every valid packet: one frame each, none lost."""
    rng = rng_for("wire")
    data = generic_model.read_bytes()
    hello = Hello(hashlib.sha256(data).hexdigest(), len(data), 60.0,
                  Camera(640.0, 640.0, 319.5, 239.5, 640, 480), ())
    fields = random_fields(rng, 90, seq=np.arange(90) + 40_000, extremes=0.0)
    fields[:, 1] = 1
    stream = [p.tobytes() for p in pack(fields)]
    messages, garbage, make = [], 0, Garbage(rng)
    for i, packet in enumerate(stream):
        junk: list[bytes] = []
        want = make.r.randrange(9)
        while len(junk) < want:
            item = make(stream[max(0, i - 2):i + 3])
            if isinstance(item, (bytes, bytearray)):  # what a socket can carry
                junk.append(bytes(item))
        garbage += len(junk)
        messages += [*junk, packet]
    endpoint = free_endpoint()
    sender = _WireSender(endpoint, hello, messages)
    try:
        thread, _, result = start(receive, connect=endpoint, model_path=generic_model,
                                  size=(64, 48), max_frames=90, idle_timeout_s=5.0)
        thread.join(60)
    finally:
        sender.halt.set()
        sender.join(10)
    assert not thread.is_alive() and "error" not in result, result.get("error")
    assert sender.sent == 90 + garbage
    counts = {k: result[k] for k in ("ended", "frames", "received", "corrupt", "lost", "late",
                                     "duplicates", "stray", "discarded", "restarts")}
    assert counts == {"ended": "max_frames", "frames": 90, "received": 90, "corrupt": garbage,
                      "lost": 0, "late": 0, "duplicates": 0, "stray": 0, "discarded": 0,
                      "restarts": 0}, counts


def _zmtp_greeting() -> bytes:
    """A ZMTP 3.0 greeting, NULL mechanism, as a server (RFC 23/ZMTP)."""
    return b"\xff" + bytes(8) + b"\x7f" + b"\x03\x00" + b"NULL".ljust(20, b"\x00") + b"\x01" \
        + bytes(31)


def _zmtp_ready(socket_type: bytes) -> bytes:
    body = b"\x05READY\x0bSocket-Type" + struct.pack(">I", len(socket_type)) + socket_type
    return bytes([0x04, len(body)]) + body


def _read(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = conn.recv(n - len(data))
        assert chunk, "the peer closed during the handshake"
        data += chunk
    return data


def _accept_as_pub(server: socket.socket) -> socket.socket:
    """The next connection to ``server``, after a ZMTP handshake posing as a PUB socket."""
    conn, _ = server.accept()
    conn.settimeout(10)
    conn.sendall(_zmtp_greeting())
    assert _read(conn, 64)[:1] == b"\xff"
    conn.sendall(_zmtp_ready(b"PUB"))
    header = _read(conn, 2)
    assert _read(conn, header[1]).startswith(b"\x05READY")
    return conn


def test_a_frame_declaring_a_gigabyte_ends_the_connection_at_its_header() -> None:
    """A raw TCP peer posing as a sender (a ZMTP handshake as a PUB) sends one packet, then
    a frame header declaring 1 GiB. The receiver's packet socket takes the packet and drops
    the connection at the header (``protocol.transport.MAX_PACKET_FRAME``), without waiting
    for the gigabyte it would otherwise have allocated."""
    endpoint = free_endpoint()
    port = int(endpoint.rsplit(":", 1)[1])
    with socket.create_server(("127.0.0.1", port)) as server:
        server.settimeout(10)
        with PacketSubscriber(endpoint) as sub:
            conn = _accept_as_pub(server)
            with conn:
                conn.sendall(b"\x00\x03abc")  # a short message: a corrupt packet
                assert sub.recv(5000) == b"abc"
                conn.sendall(b"\x02" + struct.pack(">Q", 1 << 30))
                tick = time.monotonic()
                with contextlib.suppress(ConnectionResetError):  # closed, by FIN or RST
                    while conn.recv(4096):  # the subscription, then the end
                        pass
                assert time.monotonic() - tick < 5


def test_a_receiver_cut_off_by_a_bad_frame_connects_again(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """libzmq does not reconnect a connecting socket after a protocol error; a real
    ``receive`` opens its packet socket anew after ``REOPEN_S`` without packets (1 s here)
    and connects again by itself."""
    monkeypatch.setattr(receiver_module, "REOPEN_S", 1.0)
    endpoint = free_endpoint()
    port = int(endpoint.rsplit(":", 1)[1])
    with socket.create_server(("127.0.0.1", port)) as server:
        server.settimeout(10)
        thread, stop, result = start(receive, connect=endpoint, cache_dir=tmp_path / "cache")
        try:
            conn = _accept_as_pub(server)
            with conn:
                conn.sendall(b"\x02" + struct.pack(">Q", 1 << 30))
                with contextlib.suppress(ConnectionResetError):
                    while conn.recv(4096):
                        pass
            again = _accept_as_pub(server)  # a new socket, a new handshake
            again.close()
        finally:
            stop.set()
            thread.join(10)
    assert result.get("ended") == "stop", result


def test_the_relay_drops_a_sender_declaring_a_gigabyte_and_goes_on() -> None:
    """The same frame header from the relay's upstream side: its packet socket drops that
    connection at the header (``protocol.relay`` sets the transport's limits) and the relay
    keeps running. (libzmq does not reconnect a connecting socket after such a protocol
    error, so that upstream stays cut off until the relay restarts: only the hostile peer
    loses.)"""
    upstream, downstream = free_endpoint(), free_endpoint()
    port = int(upstream.rsplit(":", 1)[1])
    with socket.create_server(("127.0.0.1", port)) as server:
        server.settimeout(10)
        thread, stop, result = start(relay, inp=upstream, out=downstream)
        try:
            conn = _accept_as_pub(server)
            with conn:
                conn.sendall(b"\x02" + struct.pack(">Q", 1 << 30))
                tick = time.monotonic()
                with contextlib.suppress(ConnectionResetError):
                    while conn.recv(4096):
                        pass
                assert time.monotonic() - tick < 5
            assert thread.is_alive()
        finally:
            stop.set()
            thread.join(10)
    assert "error" not in result, result


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--packets", type=int, default=DEFAULT_PACKETS)
    parser.add_argument("--seed", type=int, default=SEED)
    args, rest = parser.parse_known_args()
    os.environ["FACEWIRE_FUZZ_PACKETS"] = str(args.packets)
    os.environ["FACEWIRE_FUZZ_SEED"] = str(args.seed)
    sys.exit(pytest.main([__file__, "-q", "-p", "no:cacheprovider", *rest]))
