"""Bad packets (issue 8, reliability item 2): over a million fuzzed and mutated packets through
the real code paths, with zero crashes and exact counts, and corrupt records in a log counted
and skipped (tests/reliability/test_wire_faults.py does the same on the wire).

Paths: ``protocol.packet.decode`` and ``decode_frames`` (vectorised), the receiver's per-packet
path ``receiver.playout.Playout.push`` (never raises on content; ``received + corrupt`` is
every push) and ``protocol.log.read_log`` of a ``.fwlog`` with corrupt records. The oracle is
``packetoracle``, this suite's own reading of the format table; counts are asserted exactly
wherever the oracle knows them.

Which bit errors are always caught: the CRC's generator x^16 + x^12 + x^5 + 1 is (x + 1)
times a primitive polynomial of degree 15, so every error of an odd number of bits, every
two-bit error within 32767 bits and every burst of at most 16 bits changes the CRC; a packet
is 344 bits. Every 1- and 2-bit error of several packets is tried here (exhaustively), and
random odd-weight errors and bursts; errors of 4 or more bits can pass (about 1 in 32768 of
the even-weight ones): such mutants are valid packets, must decode to in-range values, and
count as received.

Budget: ``fuzzbudget.SHARES`` (packets per test, 1,184,720 in all per normal run). For a
longer run every share is scaled by ``FACEWIRE_FUZZ_PACKETS / 1,184,720`` and the seed is
``FACEWIRE_FUZZ_SEED`` (each failure message names it)::

    FACEWIRE_FUZZ_PACKETS=10000000 .venv/bin/python -m pytest -q tests/reliability/test_fuzz.py
    .venv/bin/python tests/reliability/test_fuzz.py --packets 10000000 --seed 7
"""

from __future__ import annotations

import math
import os
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

if __name__ == "__main__":  # run as a script: the budget from the command line, set before
    # fuzzbudget reads it, and tests/conftest.py found as pytest finds it
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--packets", type=int, help="packets in all (default 1,184,720)")
    parser.add_argument("--seed", type=int)
    args, REST = parser.parse_known_args()
    for variable, value in (("FACEWIRE_FUZZ_PACKETS", args.packets),
                            ("FACEWIRE_FUZZ_SEED", args.seed)):
        if value is not None:
            os.environ[variable] = str(value)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuzzbudget import DEFAULT_PACKETS, PACKETS, SHARES, WHY, rng_for, share
from packetoracle import (
    BITS,
    CODES,
    PACKET,
    RESERVED,
    TOP,
    VERSION,
    Garbage,
    check_decoded,
    flip,
    pack,
    random_fields,
    reason,
    reasons,
    unpack,
)

from facewire.protocol.control import Camera, Hello
from facewire.protocol.log import LogWriter, read_log
from facewire.protocol.packet import PacketError, decode, decode_frames
from facewire.receiver.playout import STATUSES, Playout


def test_the_shares_add_up_to_a_million() -> None:
    assert DEFAULT_PACKETS >= 1_000_000 and sum(share(k) for k in SHARES) >= 0.99 * PACKETS


# -- decode and decode_frames ----------------------------------------------------------------

def test_every_one_and_two_bit_error_is_caught() -> None:
    """All 344 one-bit and 58,996 two-bit errors of each of several valid packets: every one
    is refused (vectorised and, for one bit, one by one), as the CRC guarantees."""
    rng = rng_for("one_and_two_bit_errors")
    per = BITS + BITS * (BITS - 1) // 2
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
        fields[:, 0] = np.where(rng.random(m) < 0.75, VERSION, rng.integers(0, 16, m))
        fields[:, 1] = rng.integers(0, 256, m)
        fields[:2, 3] = [0, (1 << 11) - 1]  # the serial at its bottom and top, and
        fields[:2, CODES:] = [np.zeros_like(TOP), TOP]  # all codes at the bottom, at the top
        packets = pack(fields)
        frames, errors = decode_frames(packets)
        want = np.where(fields[:, 0] != VERSION, "version",
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
    damaged one as lost (an insertion of L bytes as ``max(1, round(L / 55))``)."""
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
        written, kept, record_lost = _damage(rng, record, fields[k], mutants[k])
        pieces += written
        lost += record_lost
        if kept is not None:
            packets[k] = kept
            keep.append(k)
    cut = int(rng.integers(1, RECORD))  # and the last record cut short
    path.write_bytes(b"".join(pieces)[:-cut])
    keep.pop()
    lost += 1
    log = read_log(path)
    assert log.lost == lost, (log.lost, lost, WHY)
    assert np.array_equal(log.packets, packets[keep]), WHY
    assert np.array_equal(log.times, times[keep]), WHY
    assert log.hello == HELLO


def _damage(rng: np.random.Generator, record: bytearray, fields: np.ndarray,
            mutant: np.ndarray) -> tuple[list[bytes], np.ndarray | None, int]:
    """One log record (time, packet, CRC-32) damaged in one of nine ways, drawn from ``rng``;
    ``fields`` (39,) are its packet's codes and ``mutant`` (43,) a valid packet with random
    fields. Returns the bytes that take its place in the log, the packet that ``read_log``
    must keep of them (None if none) and the number of records it must count as lost."""
    kind = rng.integers(0, 9)
    body = record[:-4]
    if kind == 0:  # flipped bits anywhere in the record: its CRC-32 no longer matches
        for bit in rng.choice(8 * RECORD, int(rng.integers(1, 4)), replace=False):
            record[bit // 8] ^= 0x80 >> (bit % 8)
    elif kind in (1, 2, 3):  # a right CRC-32 over a bad packet or a bad time
        if kind == 1:
            body[8 + rng.integers(0, PACKET)] ^= 1 << rng.integers(0, 8)
        elif kind == 2:
            bad = fields.copy()
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
        size = int(rng.integers(1, 3 * RECORD))
        packet = np.frombuffer(bytes(record[8:8 + PACKET]), np.uint8)
        return [bytes(record), rng.bytes(size)], packet, max(1, round(size / RECORD))
    elif kind == 7:  # a valid packet with random fields under a right CRC-32: kept
        body[8:] = mutant.tobytes()
        return [bytes(body + struct.pack(">I", zlib.crc32(body)))], mutant, 0
    else:  # a record of the right size, its packet random bytes, CRC-32 right
        body[8:] = rng.bytes(PACKET)
        record = body + struct.pack(">I", zlib.crc32(body))
        packet = np.frombuffer(bytes(body[8:]), np.uint8)
        if reasons(packet[None])[0] is None:
            return [bytes(record)], packet, 0
    return [bytes(record)], None, 1


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q", "-p", "no:cacheprovider", *REST]))
