"""The packet format of ``protocol/packet.py`` read independently, as the fuzz tests' oracle,
and a source of garbage that is never a valid packet.

The oracle is its own reading of the format table (widths, ranges, steps, CRC-16/CCITT-FALSE
from ``binascii``, flag bits 6 and 7 reserved), with its own bit packer: a 43-byte string is
a valid packet iff its version nibble is 2, its CRC matches and no reserved flag is set.
"""

from __future__ import annotations

import binascii
import random

import numpy as np
from fuzzbudget import WHY

PACKET, BODY, BITS, VERSION = 43, 41, 344, 2
# version, flags, seq, serial, then the quantised codes (from column CODES on): rotation,
# shift_xy, shift_z, residuals, q, shade
CODES = 4
WIDTHS = np.array([4, 8, 16, 11] + [11] * 3 + [12] * 2 + [11] + [8] * 18 + [7] * 8 + [7] * 3)
LO = np.array([-102.4] * 3 + [-1024.0] * 2 + [-2147.0] + [-32.0] * 18 + [0.0] * 8
              + [-1.0] * 3)
STEP = np.array([0.1] * 3 + [0.5] * 2 + [1.0] + [0.25] * 18 + [1 / 16] * 8 + [1 / 64] * 3)
TOP = (1 << WIDTHS[CODES:]) - 1
RESERVED = 0xC0  # Flag defines bits 0..5
_STARTS = np.concatenate([[0], np.cumsum(WIDTHS)[:-1]])
_WEIGHTS = np.concatenate([1 << np.arange(w - 1, -1, -1, dtype=np.int32) for w in WIDTHS])


def crcs(body: np.ndarray) -> np.ndarray:
    """(N,) CRC-16/CCITT-FALSE of each (N, 37) row, by ``binascii``."""
    raw = np.ascontiguousarray(body, np.uint8).tobytes()
    return np.array([binascii.crc_hqx(raw[i:i + BODY], 0xFFFF)
                     for i in range(0, len(raw), BODY)], np.int64)


def pack(fields: np.ndarray) -> np.ndarray:
    """(N, 39) field codes (version, flags, seq, serial, 35 quantised) -> (N, 43) packets,
    CRC right."""
    bits = np.empty((len(fields), 8 * BODY), np.uint8)
    for i, (first, width) in enumerate(zip(_STARTS, WIDTHS)):
        bits[:, first:first + width] = (fields[:, [i]] >> np.arange(width - 1, -1, -1)) & 1
    return with_crc(np.packbits(bits, axis=1))


def with_crc(body: np.ndarray) -> np.ndarray:
    crc = crcs(body)
    return np.concatenate([body, (crc >> 8)[:, None], (crc & 0xFF)[:, None]],
                          axis=1).astype(np.uint8)


def unpack(packets: np.ndarray) -> np.ndarray:
    """(N, 43) packets -> (N, 39) field codes."""
    bits = np.unpackbits(packets[:, :BODY], axis=1)
    return np.add.reduceat(bits * _WEIGHTS, _STARTS, axis=1).astype(np.int64)


def reasons(packets: np.ndarray) -> np.ndarray:
    """(N,) object: the ``PacketError`` reason each 43-byte row must get, None if valid."""
    fields = unpack(packets)
    crc_ok = crcs(packets[:, :BODY]) == (packets[:, BODY].astype(np.int64) << 8
                                         | packets[:, BODY + 1])
    out = np.full(len(packets), None, object)
    out[fields[:, 1] & RESERVED != 0] = "reserved"
    out[~crc_ok] = "crc"
    out[fields[:, 0] != VERSION] = "version"
    return out


def reason(data: object) -> str | None:
    """What ``Playout.push`` must make of one item: None (received) or why it is corrupt."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        return "type"
    raw = bytes(data)
    if len(raw) != PACKET:
        return "size"
    if raw[0] >> 4 != VERSION:
        return "version"
    if binascii.crc_hqx(raw[:BODY], 0xFFFF) != raw[BODY] << 8 | raw[BODY + 1]:
        return "crc"
    return "reserved" if (raw[0] << 4 | raw[1] >> 4) & RESERVED else None


def random_fields(rng: np.random.Generator, n: int, seq: np.ndarray | None = None,
                  extremes: float = 0.2) -> np.ndarray:
    """(N, 39) codes of valid packets: random flags (no reserved bit), any serial, codes over
    the whole range of each quantiser with a share of ``extremes`` at its ends."""
    fields = np.empty((n, len(WIDTHS)), np.int64)
    fields[:, 0] = VERSION
    fields[:, 1] = rng.integers(0, 64, n)
    fields[:, 2] = rng.integers(0, 1 << 16, n) if seq is None else np.asarray(seq) % 65536
    fields[:, 3] = rng.integers(0, 1 << 11, n)
    codes = rng.integers(0, TOP + 1, (n, len(TOP)))
    ends = rng.random((n, len(TOP))) < extremes
    tops = np.broadcast_to(TOP, ends.shape)[ends]
    codes[ends] = np.where(rng.random(len(tops)) < 0.5, 0, tops)
    fields[:, CODES:] = codes
    return fields


def check_decoded(frames: np.ndarray, fields: np.ndarray) -> None:
    """The decoded records hold exactly the table's value of each code (so each lies in its
    quantiser's range), all finite."""
    value = LO + fields[:, CODES:] * STEP
    assert np.array_equal(frames["seq"], fields[:, 2]), WHY
    assert np.array_equal(frames["flags"], fields[:, 1]), WHY
    assert np.array_equal(frames["serial"], fields[:, 3]), WHY
    assert np.array_equal(frames["rotation"], np.radians(value[:, 0:3]).astype(np.float32)), WHY
    assert np.array_equal(frames["translation"], value[:, 3:6].astype(np.float32)), WHY
    assert np.array_equal(frames["residuals"].reshape(-1, 18),
                          value[:, 6:24].astype(np.float32)), WHY
    assert np.array_equal(frames["q"], value[:, 24:32].astype(np.float32)), WHY
    assert np.array_equal(frames["shade"], value[:, 32:].astype(np.float32)), WHY
    for name in ("rotation", "translation", "residuals", "q", "shade"):
        assert np.isfinite(frames[name]).all(), WHY


def flip(packets: np.ndarray, rows: np.ndarray, bits: np.ndarray) -> None:
    """XOR bit ``bits[i]`` (0 = the most significant bit of byte 0) of row ``rows[i]``,
    in place; a bit named twice is flipped back."""
    np.bitwise_xor.at(packets, (rows, bits // 8), (0x80 >> (bits % 8)).astype(np.uint8))


_NOT_BYTES = (None, 43, 3.5, float("nan"), "x" * 43, [0] * 43, (1, 2), {}, object(),
              np.zeros(43, np.uint8), np.float64(1.0), True, Exception("packet"))


class Garbage:
    """Items that are never valid packets, drawn with a seeded ``random.Random`` (cheaper per
    draw than numpy): random bytes of any length 0..100, mutants of given packets (1 to 3
    flipped bits, cut short, extended), CRC-right packets with a bad version or a reserved
    flag bit, bytes-likes that are not bytes, and objects that are no bytes at all. A random
    43-byte string gets version 0, so that it cannot be valid by chance."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.r = random.Random(int(rng.integers(1 << 62)))
        fields = random_fields(rng, 1024)
        fields[:512, 0] = rng.choice([v for v in range(16) if v != VERSION], 512)
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
